"""A real Ray cluster of separate node processes, started with the commands of docs/cluster.md as written
(the blocks marked `<!-- cluster-test: NAME -->`): a head with no CPUs, a CPU worker and a worker that
advertises a GPU, each with 2 CPUs, on one machine; the cache and runs on a shared (temporary) folder.

- the guide's run command, as written, computes the smoke grid on the cluster: the same keys and the same
  bytes in every published file as the local reference run (process pool, other thread counts);
- steps on CUDA reserve the GPU Ray assigns, memory hints reach Ray, and a request no node can hold
  fails at once naming the stage, its request and the largest node;
- the node running the fit is killed after its first checkpoint: the run finishes, the fit resumes from
  that checkpoint on the shared disk, tmp/ is clean, the results equal the uninterrupted run's (the time
  lost and the steps recomputed are printed);
- a node whose environment and clock differ stops the run before any step, naming the node.

The test only ever stops the processes it started (found by their process tree and by the private Ray
temp folder on their command line): never `ray stop`, which would stop every Ray on the machine.
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from pipeline.store import MANIFEST, Store
from tests import test_e2e_workflow as e2e
from tests.test_e2e_workflow import ALL_LABELS, FAST, FIT, PREPROCESS, SCENE, Place, checkpoints, lease_holder

pytestmark = pytest.mark.slow
ray = pytest.importorskip("ray")

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "cluster.md"
VENV_BIN = Path(sys.executable).parent


# ---- the guide ----------------------------------------------------------------------------------------------
def guide_blocks(text: str | None = None) -> dict[str, str]:
    """The shell blocks marked `<!-- cluster-test: NAME -->` in docs/cluster.md, by name."""
    text = GUIDE.read_text(encoding="utf-8") if text is None else text
    pattern = re.compile(r"<!-- cluster-test: ([\w-]+) -->\s*```sh\n(.*?)```", re.DOTALL)
    return {name: body.strip() for name, body in pattern.findall(text)}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def process_table() -> dict[int, tuple[int, str]]:
    """pid -> (parent pid, command line) of every process."""
    table = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", encoding="ascii", errors="replace") as f:
                parent = int(f.read().rsplit(")", 1)[1].split()[1])
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                command = f.read().replace(b"\0", b" ").decode(errors="replace")
        except (OSError, IndexError, ValueError):
            continue
        table[int(entry)] = (parent, command)
    return table


def descendants(root: int, table: dict[int, tuple[int, str]]) -> set[int]:
    children: dict[int, list[int]] = {}
    for pid, (parent, _) in table.items():
        children.setdefault(parent, []).append(pid)
    found, todo = set(), [root]
    while todo:
        pid = todo.pop()
        found.add(pid)
        todo.extend(children.get(pid, []))
    return found


class GuideCluster:
    """The guide's cluster on this machine: env block, token, head, workers, all as written plus the
    test-only flags the module docstring lists."""

    def __init__(self, shared: Path):
        self.blocks = guide_blocks()
        self.shared = shared
        self.port = free_port()
        self.temp = Path(tempfile.mkdtemp(prefix="rt", dir="/tmp"))   # short: Ray's socket paths are limited
        self.nodes: dict[str, subprocess.Popen] = {}
        self.logs: dict[str, Path] = {}
        base = dict(os.environ, PATH=f"{VENV_BIN}{os.pathsep}{os.environ.get('PATH', '')}", PYTHONPATH=str(ROOT),
                    OMP_NUM_THREADS="1", RAY_USAGE_STATS_ENABLED="0", HF_HUB_OFFLINE="1")
        for name in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH", "RAY_ADDRESS"):
            base.pop(name, None)
        env_block = re.sub(r"\bSHARED=\S+", f"SHARED={shlex.quote(str(shared))}", self.blocks["env"])
        env_block = re.sub(r"\bHEAD=\S+", "HEAD=127.0.0.1", env_block)
        dumped = subprocess.run(["bash", "-c", env_block + "\nenv -0"], env=base, check=True, capture_output=True)
        self.env = dict(item.split("=", 1) for item in dumped.stdout.decode().split("\0") if "=" in item)
        assert self.env["RAY_AUTH_MODE"] == "token" and self.env["RAY_AUTH_TOKEN_PATH"].startswith(str(shared))

    def line(self, block: str) -> str:
        return self.blocks[block].replace("6379", str(self.port))

    def sh(self, block: str, **kwargs) -> subprocess.CompletedProcess:
        return subprocess.run(["bash", "-c", self.line(block)], env=self.env, cwd=ROOT, capture_output=True,
                              text=True, check=False, **kwargs)

    def start_node(self, name: str, block: str, extra_env: dict[str, str] | None = None, timeout: float = 90) -> None:
        command = self.line(block)
        assert command.startswith("ray start") and "\n" not in command, command
        test_flags = ["--block", f"--dashboard-agent-listen-port={free_port()}"]
        if "--head" in command:
            test_flags += [f"--temp-dir={self.temp}", "--include-dashboard=false",
                           f"--dashboard-port={free_port()}"]
        else:
            test_flags += ["--num-cpus=2"]
        self.logs[name] = self.temp / f"{name}.log"
        with open(self.logs[name], "w") as out:
            self.nodes[name] = subprocess.Popen(["bash", "-c", f"exec {command} {' '.join(test_flags)}"],
                                                env=dict(self.env, **(extra_env or {})), cwd=ROOT, stdout=out,
                                                stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + timeout
        while "Ray runtime started" not in self.logs[name].read_text(errors="replace"):
            if self.nodes[name].poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"node {name} did not start: {self.logs[name].read_text()[-3000:]}")
            time.sleep(0.1)

    def node_of(self, pid: int) -> str | None:
        """The node (name) whose processes include `pid`."""
        table = process_table()
        for name, proc in self.nodes.items():
            if pid in descendants(proc.pid, table):
                return name
        return None

    def node_id(self, name: str) -> str:
        """The Ray node id of a node, from its raylet's command line."""
        table = process_table()
        for pid in descendants(self.nodes[name].pid, table):
            found = re.search(r"--node_id=([0-9a-f]+)", table[pid][1])
            if found and "raylet" in table[pid][1].split()[0]:
                return found.group(1)
        raise AssertionError(f"no raylet found for node {name}")

    def kill_node(self, name: str) -> None:
        """SIGKILL every process of the node at once (its `ray start`, raylet, agents, workers)."""
        proc = self.nodes.pop(name)
        pids = descendants(proc.pid, process_table())
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        proc.wait(timeout=30)

    def close(self) -> None:
        for name in list(self.nodes):
            self.kill_node(name)
        # Workers outlive their raylet for a moment and are reparented: find them by our temp folder.
        marker = str(self.temp)
        for _ in range(20):
            left = [pid for pid, (_, command) in process_table().items() if marker in command and pid != os.getpid()]
            if not left:
                break
            for pid in left:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            time.sleep(0.1)
        shutil.rmtree(self.temp, ignore_errors=True)

    # ---- the run command --------------------------------------------------------------------------------
    def run_command(self, place: Place, *extra: str) -> str:
        command = self.line("run").replace("workflows/comparison.toml", "workflows/smoke.toml")
        assert command.startswith("dualnerf run ") and "--cache $SHARED/cache" in command
        sets = " ".join(f"--set {shlex.quote(item)}" for item in FAST)
        return f"{command} --out {shlex.quote(str(place.reports))} {sets} {' '.join(extra)}"

    def start_run(self, place: Place, *extra: str) -> subprocess.Popen:
        place.root.mkdir(parents=True, exist_ok=True)
        n = len(list(place.root.glob("out-*.txt")))
        with open(place.root / f"out-{n}.txt", "w") as out, open(place.root / f"err-{n}.txt", "w") as err:
            proc = subprocess.Popen(["bash", "-c", "exec " + self.run_command(place, *extra)],
                                    env=dict(self.env, SHARED=str(place.root)), cwd=ROOT,
                                    stdout=out, stderr=err, text=True, start_new_session=True)
        proc.out_path, proc.err_path = out.name, err.name
        return proc


def shared_place(cluster: GuideCluster, name: str) -> Place:
    """One run's `$SHARED`: a folder of the shared folder, with the guide's cache/ and runs/ in it."""
    place = Place(cluster.shared / name)
    place.cache, place.runs = place.root / "cache", place.root / "runs"
    return place


@pytest.fixture(scope="module")
def cluster(tmp_path_factory, smoke_reference):
    """The guide's cluster. After the local reference run: it has built the field kernels (nodes that start
    while one is building would race for torch's build folder), and the two do not share the cores."""
    shared = tmp_path_factory.mktemp("shared")
    started = time.perf_counter()
    guide = GuideCluster(shared)
    try:
        token = guide.sh("token")
        assert token.returncode == 0, token.stderr
        assert len(Path(guide.env["RAY_AUTH_TOKEN_PATH"]).read_text().strip()) == 64
        guide.start_node("head", "head")
        # One at a time: two nodes starting at once on one machine race for the same socket names.
        guide.start_node("cpu", "worker")
        guide.start_node("gpu", "gpu-worker")
        print(f"\ncluster of 3 `ray start` nodes up in {time.perf_counter() - started:.1f} s")
        yield guide
    finally:
        guide.close()


def finish(proc: subprocess.Popen, timeout: float = 400) -> tuple[int, str, str]:
    proc.wait(timeout=timeout)
    return proc.returncode, Path(proc.out_path).read_text(), Path(proc.err_path).read_text()


def manifest(place: Place, key: str) -> dict:
    return json.loads((place.entry(key) / MANIFEST).read_text())


# ---- the tests ----------------------------------------------------------------------------------------------
def test_the_guides_commands_run_the_smoke_grid_on_the_cluster_like_a_local_run(cluster, smoke_reference):
    deadline = time.monotonic() + 30
    while True:          # `ray status` reports the autoscaler's view, which lags a node's start by seconds
        status = cluster.sh("status")
        assert status.returncode == 0, status.stderr
        if "/4.0 CPU" in status.stdout and "/1.0 GPU" in status.stdout:        # both workers joined
            break
        assert time.monotonic() < deadline, status.stdout
        time.sleep(1)
    place = shared_place(cluster, "main")
    started = time.perf_counter()
    code, out, err = finish(cluster.start_run(place))
    elapsed = time.perf_counter() - started
    assert code == 0, err[-4000:]
    assert "run: 8 steps (8 computed, 0 cached)" in out
    assert "cluster: 2 step node(s) checked" in err
    assert "(_ray_execute pid=" in err                            # the steps ran in Ray workers
    assert sorted(place.keys()) == sorted(ALL_LABELS)
    e2e.assert_same_results(smoke_reference, place)
    nodes = {}
    record = place.records()[-1]
    for step in record["steps"]:
        log = Path(step["log"])
        assert log.is_absolute() and log.is_relative_to(place.runs) and "=== computing" in log.read_text()
        placement = manifest(place, step["key"])["placement"]
        assert placement["executor"] == "ray" and placement["assigned"]["CPU"] >= 1
        nodes.setdefault(placement["node_id"][:8], []).append(step["label"])
    print(f"\nsmoke grid on the cluster (8 steps computed, probe included): {elapsed:.1f} s; steps per node: {nodes}")


def test_cuda_steps_reserve_the_gpu_ray_assigns_and_impossible_requests_fail_at_once(cluster, tmp_path):
    gpu_node = cluster.node_id("gpu")
    steps = [{"stage": "device_probe", "label": "on-cuda", "params": {"device": "cuda", "tag": "a"}},
             {"stage": "device_probe", "label": "on-cpu", "params": {"tag": "b"}},
             {"stage": "device_probe", "label": "two-gpus", "params": {"device": "cuda", "gpus": 2.0}},
             {"stage": "device_probe", "label": "64-cpus", "params": {"num_threads": 64}}]
    spec = {"cache": str(cluster.shared / "stub-cache"), "run_dir": str(cluster.shared / "runs" / "stub"),
            "executor": "ray", "ray_address": f"127.0.0.1:{cluster.port}", "steps": steps}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "tests.pipeline_stages", str(tmp_path / "spec.json")], cwd=ROOT,
                          env=cluster.env, capture_output=True, text=True, timeout=180, check=False)
    elapsed = time.perf_counter() - started
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["status"] == ["done", "done", "failed", "failed"], done.stderr[-3000:]
    on_cuda = json.loads((Path(result["results"][0]) / "seen.json").read_text())
    assert on_cuda["node_id"] == gpu_node and on_cuda["node_resources"]["GPU"] == 1
    assert on_cuda["gpu_ids"] == ["0"] and on_cuda["cuda_visible_devices"] == "0"      # the one Ray assigned
    assert on_cuda["assigned"]["GPU"] == 1
    on_cpu = json.loads((Path(result["results"][1]) / "seen.json").read_text())
    assert "GPU" not in on_cpu["assigned"] and on_cpu["assigned"]["CPU"] == 1
    assert on_cpu["assigned"]["memory"] == 1.5 * 2 ** 30                                # the memory hint, in bytes
    placement = json.loads((Path(result["results"][0]) / MANIFEST).read_text())["placement"]
    assert placement["gpu_ids"] == ["0"] and placement["node_id"] == gpu_node
    two_gpus, many_cpus = result["failed"]
    for error, asked in ((two_gpus, "2 GPU(s)"), (many_cpus, "64 CPU(s)")):
        assert "stage device_probe" in error and asked in error and "the largest node" in error, error
        assert "has 2 CPU(s), 1 GPU(s)" in error or "has 2 CPU(s), 0 GPU(s)" in error, error
    record = json.loads((cluster.shared / "runs" / "stub" / "run.json").read_text())
    refused = {s["label"]: s for s in record["steps"]}
    assert refused["two-gpus"]["duration_s"] < 1 and refused["64-cpus"]["duration_s"] < 1     # at once
    print(f"\nplacement stubs on the cluster: {elapsed:.1f} s")


def test_a_lost_node_costs_one_retry_that_resumes_from_its_checkpoint(cluster, smoke_reference):
    place = shared_place(cluster, "node-loss")
    place.seed_from(smoke_reference, [SCENE, PREPROCESS])
    keys = smoke_reference.keys()
    fit_key = keys[FIT]
    started = time.perf_counter()
    proc = cluster.start_run(place)
    deadline = time.monotonic() + 180
    while not checkpoints(place, fit_key):
        assert proc.poll() is None, Path(proc.err_path).read_text()[-3000:]
        assert time.monotonic() < deadline, "no fit checkpoint"
        time.sleep(0.02)
    first = checkpoints(place, fit_key)[0].name
    progress_file = place.cache / "scratch" / fit_key / "progress.json"

    def done() -> int:
        with contextlib.suppress(OSError, ValueError):
            return int(json.loads(progress_file.read_text())["done"])
        return 0

    # Kill mid-way between checkpoints (a few iterations past the first), as a real failure would land.
    deadline = time.monotonic() + 5
    while done() < int(first) + 3 and time.monotonic() < deadline:
        time.sleep(0.02)
    worker = lease_holder(place, fit_key)
    node = cluster.node_of(worker)
    assert node in ("cpu", "gpu")
    done_at_kill = max([done()] + [int(c.name) for c in checkpoints(place, fit_key)])
    killed_at = time.time()
    cluster.kill_node(node)
    code, out, err = finish(proc)
    elapsed = time.perf_counter() - started
    assert code == 0, err[-4000:]
    assert "run: 8 steps (6 computed, 2 cached)" in out
    e2e.assert_same_results(smoke_reference, place)
    fit = manifest(place, fit_key)
    resumed = fit["resumed_from_checkpoint"]
    assert resumed is not None and resumed >= int(first)
    store = Store(place.cache)
    assert not list(store.tmp.iterdir()) and not list(store.leases.iterdir())
    assert not store.scratch.is_dir() or not list(store.scratch.iterdir())
    # What the failure cost: from the kill to the retry's start, the iterations computed twice, and the
    # fit's wall time in the run record (both attempts) against the uninterrupted cluster run's.
    record = {s["key"]: s for s in place.records()[-1]["steps"]}
    log = Path(record[fit_key]["log"]).read_text()
    attempts = re.findall(r"^(\S+ \S+) INFO === computing", log, re.MULTILINE)
    assert len(attempts) == 2, log
    day, millis = attempts[1].split(",")
    retry_start = time.mktime(time.strptime(day, "%Y-%m-%d %H:%M:%S")) + int(millis) / 1000
    iterations = int(fit["params"]["iterations"])
    fit_wall = record[fit_key]["finished"] - record[fit_key]["started"]
    main = shared_place(cluster, "main")
    baseline = ""
    if main.runs.is_dir():
        before = {s["key"]: s for s in main.records()[-1]["steps"]}[fit_key]
        baseline = (f" vs {before['finished'] - before['started']:.1f} s in the uninterrupted cluster run "
                    f"(lost {fit_wall - (before['finished'] - before['started']):.1f} s)")
    print(f"\nnode loss: killed node '{node}' at fit iteration {done_at_kill}/{iterations} (newest checkpoint "
          f"{resumed}); the retry started computing {retry_start - killed_at:.1f} s after the kill and resumed from "
          f"checkpoint {resumed}: {done_at_kill - resumed} iterations recomputed (1 step: the fit); fit wall time "
          f"{fit_wall:.1f} s{baseline}; whole run {elapsed:.1f} s")


def test_the_probe_stops_a_run_on_a_node_that_differs(cluster, tmp_path):
    fakes = tmp_path / "node-fakes"
    (fakes / "torch-0.0.1.dist-info").mkdir(parents=True)
    (fakes / "torch-0.0.1.dist-info" / "METADATA").write_text("Metadata-Version: 2.1\nName: torch\nVersion: 0.0.1\n")
    (fakes / "sitecustomize.py").write_text("import time\n_real = time.time\ntime.time = lambda: _real() + 90.0\n")
    cluster.start_node("bad", "worker", extra_env={"PYTHONPATH": f"{fakes}{os.pathsep}{ROOT}"})
    bad = cluster.node_id("bad")
    place = shared_place(cluster, "probe")
    started = time.perf_counter()
    code, _, err = finish(cluster.start_run(place), timeout=240)
    elapsed = time.perf_counter() - started
    cluster.kill_node("bad")
    assert code == 2, err[-3000:]
    message = err[err.index("dualnerf: error: "):]
    assert "nothing was run" in message and message.count("\nNode ") == 1, message
    paragraph = message[message.index("\nNode "):]
    assert f"Ray node {bad[:8]}" in paragraph
    assert re.search(r"packages\.torch: key computed for '\S+', this worker has '0\.0\.1'", paragraph), paragraph
    assert re.search(r"clock is \+(8\d|9\d)\.\d s", paragraph), paragraph
    assert "What to do: " in paragraph and "docs/cluster.md" in paragraph
    assert not (place.cache / "objects").exists() or not list((place.cache / "objects").iterdir())
    print(f"\nprobe refusing a node: {elapsed:.1f} s; message:\n{message}")


def test_a_relative_runs_folder_is_resolved_before_steps_get_their_log_paths(tmp_path, monkeypatch):
    from pipeline.dag import Step
    from pipeline.executors import SerialExecutor
    from pipeline.runner import run_steps
    from tests.pipeline_stages import REGISTRY

    monkeypatch.chdir(tmp_path)
    result = run_steps([Step("count", {"n": 2}, label="c")], registry=REGISTRY, store=Store("cache"),
                       executor=SerialExecutor(threads=1), run_dir=Path("runs") / "r", quiet=True)
    assert result.ok and result.run_file.is_absolute()
    record = json.loads(result.run_file.read_text())
    assert all(Path(step["log"]).is_absolute() for step in record["steps"])


def test_guide_blocks_are_single_commands_the_test_can_run():
    blocks = guide_blocks()
    assert set(blocks) == {"env", "token", "head", "worker", "gpu-worker", "status", "run"}   # all run here
    for name in ("head", "worker", "gpu-worker", "run", "status"):
        assert "\n" not in blocks[name], name
    assert blocks["run"].startswith("dualnerf run workflows/comparison.toml --executor ray --ray-address $HEAD:")
    assert "--cache $SHARED/cache" in blocks["run"] and "--runs $SHARED/runs" in blocks["run"]
    # Every sh block of the guide is one of these (tests/test_docs_commands.py leaves them to this file).
    assert len(re.findall(r"```sh\n", GUIDE.read_text(encoding="utf-8"))) == len(blocks)
