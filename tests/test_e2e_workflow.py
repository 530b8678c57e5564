"""End-to-end behaviour of `dualnerf run` on the smoke workflow (tiny procedural scene; baseline and full
DualNeRF rows), with real subprocesses and a temporary cache, runs and report folder per test:

- killed (SIGTERM mid-fit, then SIGKILL of the whole process tree mid-edit) and resumed: the same keys and
  byte-identical results as one uninterrupted run;
- two runs started at once on one cache compute every step exactly once and both report results;
- the Ray executor gives the same keys and byte-identical results as the process pool, and the serial
  executor with every step on 3 threads the same as the pool's 1- and 2-thread steps;
- a failing cell (InstructPix2Pix weights that do not exist) does not stop the original-scene evaluation;
- after a complete run, --dry-run lists every step as cached and a rerun computes nothing.

Parameters are shrunk with --set (FAST) so a whole grid takes about a minute on 2 busy cores. The
uninterrupted reference run is shared by the module; other tests start from a cache seeded with copies
of its upstream entries (content-addressed: a copied entry is exactly what that key would compute) and
compute the steps they are about.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.lease import pid_alive
from pipeline.store import MANIFEST
from tests.test_e2e_signals import process_tree

ROOT = Path(__file__).resolve().parents[1]
WORKFLOW = "workflows/smoke.toml"
FAST = ["preprocess.max_size=64",
        "fit.iterations=80", "fit.rays_per_batch=256", "fit.samples_per_ray=32", "fit.grid_levels=2",
        "fit.grid_max_resolution=32", "fit.plane_levels=1", "fit.plane_max_resolution=64", "fit.checkpoint_every=5",
        "fit.eval_every=20", "fit.curve_views=1", "fit.render_samples_per_ray=32",
        "edit.iterations=20", "edit.rays_per_batch=256", "edit.edit_rate=5", "edit.edit_count=1",
        "edit.checkpoint_every_rounds=1", "edit.lpips_net=vgg", "edit.patch_size=16",
        "evaluate.n_frames=4", "evaluate.path_scale=0.5"]
SCENE, PREPROCESS, FIT = "scene[tiny]", "preprocess[tiny]", "fit[tiny]"
ORIGINAL = "evaluate[tiny, original]"
EDIT_BASE, EDIT_FULL = "edit[baseline, seed 0]", "edit[DF+SA+CCI, seed 0]"
EVAL_BASE, EVAL_FULL = "evaluate[baseline, seed 0]", "evaluate[DF+SA+CCI, seed 0]"
ALL_LABELS = [SCENE, PREPROCESS, FIT, ORIGINAL, EDIT_BASE, EVAL_BASE, EDIT_FULL, EVAL_FULL]

STARTED: list[subprocess.Popen] = []


@pytest.fixture(autouse=True)
def no_leftovers():
    """Whatever a failing test leaves running is killed with its process group."""
    yield
    while STARTED:
        proc = STARTED.pop()
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        proc.wait()


class Place:
    """One test's cache, runs and report folders."""

    def __init__(self, root: Path):
        self.root = root
        self.cache, self.runs, self.reports = root / "cache", root / "runs", root / "reports"

    def command(self, *extra: str, dry_run: bool = False, executor: str = "process") -> list[str]:
        sets = [arg for item in FAST for arg in ("--set", item)]
        return [sys.executable, "-m", "experiments.cli", "--cache", str(self.cache), "--runs", str(self.runs), "--quiet",
                "run", WORKFLOW, "--reports", str(self.reports), "--executor", executor, *sets, *extra,
                *(["--dry-run"] if dry_run else [])]

    def start(self, *extra: str, **kwargs) -> subprocess.Popen:
        env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", RAY_USAGE_STATS_ENABLED="0",
                   HF_HUB_OFFLINE="1")
        # Output goes to files, not pipes: a pipe held open by a killed run's leftovers would block reading.
        self.root.mkdir(parents=True, exist_ok=True)
        n = len(list(self.root.glob("out-*.txt")))
        with open(self.root / f"out-{n}.txt", "w") as out, open(self.root / f"err-{n}.txt", "w") as err:
            proc = subprocess.Popen(self.command(*extra, **kwargs), cwd=ROOT, env=env, stdout=out, stderr=err,
                                    text=True, start_new_session=True)
        proc.out_path, proc.err_path = out.name, err.name
        STARTED.append(proc)
        return proc

    def run(self, *extra: str, timeout: float = 300, **kwargs) -> tuple[int, str, str, float]:
        started = time.perf_counter()
        proc = self.start(*extra, **kwargs)
        proc.wait(timeout=timeout)
        elapsed = time.perf_counter() - started
        return proc.returncode, Path(proc.out_path).read_text(), Path(proc.err_path).read_text(), elapsed

    def records(self) -> list[dict]:
        found = [json.loads(p.read_text()) for p in self.runs.glob("*/*/run.json")]
        return sorted(found, key=lambda r: r["started"])

    def keys(self, record: dict | None = None) -> dict[str, str]:
        record = record or self.records()[-1]
        return {step["label"]: step["key"] for step in record["steps"]}

    def entry(self, key: str) -> Path:
        return self.cache / "objects" / key[:2] / key

    def seed_from(self, other: Place, labels: list[str]) -> None:
        """Copy `other`'s published entries for `labels` into this cache."""
        for label in labels:
            key = other.keys()[label]
            shutil.copytree(other.entry(key), self.entry(key))


@pytest.fixture(scope="module")
def reference(smoke_reference) -> Place:
    """The uninterrupted local run of the smoke grid (tests/e2e_fixtures.py: shared by the session)."""
    return smoke_reference


def run_reference(root: Path) -> Place:
    place = Place(root)
    code, out, err, elapsed = place.run()
    assert code == 0, err
    print(f"\nreference run (full smoke grid, FAST settings): {elapsed:.1f} s")
    assert "run: 8 steps (8 computed, 0 cached)" in out
    assert sorted(place.keys()) == sorted(ALL_LABELS)
    return place


def manifest(place: Place, key: str) -> dict:
    return json.loads((place.entry(key) / MANIFEST).read_text())


def assert_same_results(reference: Place, other: Place, record: dict | None = None) -> None:
    """Same labels and keys as the reference, and the same bytes in every output file (published files hold
    no wall-clock times or paths); metrics.json and model files are additionally compared byte for byte."""
    keys = other.keys(record)
    assert keys == reference.keys()
    for label, key in keys.items():
        mine, theirs = manifest(other, key), manifest(reference, key)
        assert sorted(mine["files"]) == sorted(theirs["files"]), label
        differing = {name for name in mine["files"] if mine["files"][name]["sha256"] != theirs["files"][name]["sha256"]}
        assert not differing, f"{label}: {sorted(differing)} differ"
        for name in theirs["files"]:
            if name.startswith("model/") or name == "metrics.json":
                assert (other.entry(key) / name).read_bytes() == (reference.entry(key) / name).read_bytes(), \
                    f"{label}: {name}"


def wait_for(predicate, timeout: float = 180.0, what: str = "condition", proc: subprocess.Popen | None = None):
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"the run ended (exit {proc.returncode}) before {what}: "
                                 f"{Path(proc.err_path).read_text()[-2000:]}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def checkpoints(place: Place, key: str) -> list[Path]:
    folder = place.cache / "scratch" / key / "checkpoints"
    return sorted(p for p in folder.glob("*") if p.name.isdigit()) if folder.is_dir() else []


def lease_holder(place: Place, key: str) -> int | None:
    try:
        return int(json.loads((place.cache / "leases" / f"{key}.lease").read_text())["pid"])
    except (OSError, ValueError, KeyError):
        return None


def computed_keys(place: Place) -> list[tuple[str, int]]:
    """(key, pid) of every computation started, over all of this place's step logs (one per attempt)."""
    pattern = re.compile(r"=== computing .* \(([0-9a-f]{64})\) on \S+ pid (\d+)")
    return [(m.group(1), int(m.group(2))) for log in place.runs.glob("*/*/logs/*.log")
            for m in pattern.finditer(log.read_text())]


@pytest.mark.slow
def test_interrupted_and_resumed_run_equals_uninterrupted(reference, tmp_path):
    place = Place(tmp_path)
    place.seed_from(reference, [SCENE, PREPROCESS])
    keys = reference.keys()

    # 1. SIGTERM to `dualnerf run` (only the runner) once the fit has written a checkpoint.
    # One step at a time (--jobs 1), so what is left after each kill is known; the reference ran with the
    # default pool (two edits side by side): the same bytes either way.
    proc = place.start("--jobs", "1")
    wait_for(lambda: checkpoints(place, keys[FIT]), what="a fit checkpoint", proc=proc)
    worker = lease_holder(place, keys[FIT])
    assert worker is not None and worker != proc.pid
    tree = process_tree(proc.pid)
    assert worker in tree
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=60) == 143
    err_lines = Path(proc.err_path).read_text().strip().splitlines()
    assert err_lines[-1].startswith("dualnerf: terminated (SIGTERM); checkpoints are kept")
    assert "Traceback" not in Path(proc.err_path).read_text()
    wait_for(lambda: not any(pid_alive(pid) for pid in tree), timeout=10, what="no process of the run left")
    assert not list((place.cache / "leases").glob("*.lease"))
    assert checkpoints(place, keys[FIT])
    record = place.records()[-1]
    assert record["status"] == "interrupted"
    assert {s["label"]: s["status"] for s in record["steps"]}[FIT] == "interrupted"

    # 2. Resume; SIGKILL the whole process tree once the full DualNeRF edit has a checkpoint.
    proc = place.start("--jobs", "1")
    wait_for(lambda: checkpoints(place, keys[EDIT_FULL]), what="an edit checkpoint", proc=proc)
    tree = process_tree(proc.pid)
    assert len(tree) >= 2                           # the runner and its pool worker
    for pid in tree:
        os.kill(pid, signal.SIGKILL)
    proc.wait(timeout=30)
    assert not place.entry(keys[EDIT_FULL]).exists()

    # 3. Rerun to the end.
    code, out, err, _ = place.run("--jobs", "1")
    assert code == 0, err
    assert "(2 computed, 6 cached)" in out          # the interrupted edit and its evaluation
    assert_same_results(reference, place)
    assert manifest(place, keys[FIT])["resumed_from_checkpoint"] >= 5
    assert manifest(place, keys[EDIT_FULL])["resumed_from_checkpoint"] >= 5
    assert manifest(place, keys[EDIT_BASE])["resumed_from_checkpoint"] is None


@pytest.mark.slow
def test_other_thread_counts_and_the_serial_executor_give_the_same_bytes(reference, tmp_path):
    # The reference ran in the process pool, the fit on 2 threads and the edits on 1; here every step runs
    # in one process on 3 threads (a partition of the work that no power of two gives): same keys (the
    # thread count is not an input) and the same bytes in every published file.
    place = Place(tmp_path)
    threads = [arg for stage in ("fit", "edit", "evaluate") for arg in ("--set", f"{stage}.num_threads=3")]
    code, _, err, elapsed = place.run(*threads, "--set", "scene.workers=3", executor="serial")
    assert code == 0, err
    print(f"\nserial run on 3 threads: {elapsed:.1f} s")
    assert_same_results(reference, place)
    for label, key in place.keys().items():
        recorded = manifest(place, key)["record"].get("threads")
        if recorded is not None:
            assert recorded["kernel_threads"] in (0, 3) and recorded["torch_threads"] == 1, label


def test_two_runs_at_once_compute_each_step_once(reference, tmp_path):
    place = Place(tmp_path)
    place.seed_from(reference, [SCENE, PREPROCESS, FIT])
    first, second = place.start(), place.start()
    for proc in (first, second):
        assert proc.wait(timeout=300) == 0, Path(proc.err_path).read_text()
    records = place.records()
    assert len(records) == 2 and records[0]["run"] != records[1]["run"]      # one run folder each
    computed = computed_keys(place)
    expected = sorted(v for k, v in reference.keys().items() if k not in (SCENE, PREPROCESS, FIT))
    assert sorted(key for key, _ in computed) == expected                  # each missing key exactly once
    for key, pid in computed:
        assert manifest(place, key)["pid"] == pid                          # ...by the process that published it
    counts = [re.search(r"\((\d+) computed, (\d+) cached\)", Path(p.out_path).read_text()).groups()
              for p in (first, second)]
    assert sum(int(c) for c, _ in counts) == len(expected)
    assert all(int(c) + int(k) == 8 for c, k in counts)
    for proc in (first, second):
        assert "report: " in Path(proc.out_path).read_text()
    for record in records:
        assert record["status"] == "done"
        assert_same_results(reference, place, record)


@pytest.mark.slow
def test_ray_executor_matches_process_pool(reference, tmp_path):
    pytest.importorskip("ray")
    place = Place(tmp_path)
    # Time: the scene, its SfM and the static fit come from the reference (the interrupted-run test covers
    # the fit); the original-scene evaluation and both edited cells are computed by Ray tasks.
    place.seed_from(reference, [SCENE, PREPROCESS, FIT])
    code, out, err, elapsed = place.run(executor="ray", timeout=400)
    assert code == 0, err
    print(f"\nray run (5 steps computed): {elapsed:.1f} s")
    assert "(5 computed, 3 cached)" in out
    assert "(_ray_execute pid=" in err                              # the steps really ran in Ray workers
    assert_same_results(reference, place)


@pytest.mark.slow
def test_failing_cell_does_not_stop_independent_cells(reference, tmp_path):
    place = Place(tmp_path)
    place.seed_from(reference, [SCENE, PREPROCESS, FIT])
    missing = tmp_path / "no-such-ip2p-model"
    code, _, err, _ = place.run("--set", "edit.editor=ip2p", "--set", f"edit.editor_model={missing}")
    assert code == 1
    status = {s["label"]: s for s in place.records()[-1]["steps"]}
    assert status[ORIGINAL]["status"] == "done"                 # computed here, not seeded
    assert place.entry(status[ORIGINAL]["key"]).is_dir()
    assert status[ORIGINAL]["key"] == reference.keys()[ORIGINAL]
    for label in (EDIT_BASE, EDIT_FULL):
        assert status[label]["status"] == "failed" and status[label]["user_error"]
        assert str(missing) in status[label]["error"]
        # the failure is listed on stderr with its log file, which holds the details
        log = Path(status[label]["log"])
        assert f"  {label}: " in err and f"    log: {log}" in err
        assert str(missing) in log.read_text()
    skipped = next(line for line in err.splitlines() if line.startswith("  skipped, as an upstream step failed:"))
    for label in (EVAL_BASE, EVAL_FULL):
        assert status[label]["status"] == "skipped"
        assert label in skipped                                  # one line for all skipped steps
    assert err.strip().splitlines()[-1].startswith("run: first error: ")   # the last line says what failed


@pytest.mark.slow
def test_complete_run_is_all_cached(reference, tmp_path):
    place = Place(tmp_path)
    place.cache, place.runs = reference.cache, tmp_path / "runs"       # the reference cache, read only
    code, out, err, _ = place.run(dry_run=True)
    assert code == 0, err
    states = {}
    for label in ALL_LABELS:
        line = next(line for line in out.splitlines() if line.strip().startswith(label + " "))
        key, state = line.split()[-2:]
        states[label] = state
        assert len(key) >= 12 and reference.keys()[label].startswith(key)      # the key, abbreviated
    assert set(states.values()) == {"cached"}, states
    code, out, err, elapsed = place.run()
    assert code == 0, err
    assert "run: 8 steps (0 computed, 8 cached)" in out
    assert not computed_keys(place)
    print(f"\nfully cached rerun: {elapsed:.2f} s wall (process start, keying, report)")
