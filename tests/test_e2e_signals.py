"""How a run with a process pool ends when it is signalled, with real processes (engine-level, cheap
test stages from tests.pipeline_stages; the full `dualnerf run` CLI gets the same checks in
tests/test_e2e_workflow.py):

- SIGTERM to the runner alone (`kill PID`) or to its whole process group (a job scheduler) stops it like
  Ctrl-C: exit status 143, one-line message, workers gone, lease released, checkpoints kept, run record
  `interrupted`; also when the stage's native library took SIGTERM over in the worker (glog in pycolmap).
- SIGKILL of the runner alone: its workers do not compute on as orphans (they follow their parent).
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.lease import pid_alive
from pipeline.store import Store

ROOT = Path(__file__).resolve().parents[1]

# A runner like `dualnerf run`'s (experiments.cli.main): run_steps inside terminate_as_interrupt, the CLI's
# exit statuses and messages.
DRIVER = """
import json, sys
from pathlib import Path
from pipeline.executors import make_executor
from pipeline.runner import Terminated, run_steps, terminate_as_interrupt
from pipeline.store import Store
from tests.pipeline_stages import REGISTRY, build_steps

spec = json.loads(Path(sys.argv[1]).read_text())
try:
    with terminate_as_interrupt():
        result = run_steps(build_steps(spec["steps"]), registry=REGISTRY, store=Store(spec["cache"]),
                           executor=make_executor("process", jobs=1), run_dir=Path(spec["run_dir"]), quiet=True)
except Terminated:
    print("driver: terminated", file=sys.stderr)
    sys.exit(Terminated.exit_status)
except KeyboardInterrupt:
    print("driver: interrupted", file=sys.stderr)
    sys.exit(130)
print(json.dumps({"status": list(result.status.values())}))
"""


STARTED: list[subprocess.Popen] = []


@pytest.fixture(autouse=True)
def no_leftovers():
    """Whatever a failing test leaves running (an orphaned worker) is killed with its process group."""
    yield
    while STARTED:
        proc = STARTED.pop()
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        for stream in (proc.stdout, proc.stderr):
            if stream:
                stream.close()
        proc.wait()


def start_driver(tmp_path: Path, name: str, params: dict) -> subprocess.Popen:
    spec = {"cache": str(tmp_path / "cache"), "run_dir": str(tmp_path / "runs" / name),
            "steps": [{"stage": "count", "label": "c", "params": params}]}
    (tmp_path / f"{name}.json").write_text(json.dumps(spec))
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    # Own session: the group signal below reaches the driver and its workers, nothing of pytest's.
    proc = subprocess.Popen([sys.executable, "-c", DRIVER, str(tmp_path / f"{name}.json")], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    STARTED.append(proc)
    return proc


def wait_for(predicate, timeout: float = 60.0, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def worker_pid(trace: Path) -> int | None:
    """The pid of the worker running the count stage (it writes "<pid> <i>" per counted step)."""
    lines = trace.read_text().splitlines() if trace.exists() else []
    return int(lines[0].split()[0]) if lines else None


def process_tree(root: int) -> list[int]:
    """`root` and all its descendants, from /proc (children found by their parent pid)."""
    parents: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        parents.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    tree, todo = [], [root]
    while todo:
        pid = todo.pop()
        tree.append(pid)
        todo.extend(parents.get(pid, []))
    return tree


def assert_stopped_cleanly(tmp_path: Path, proc: subprocess.Popen, tree: list[int], *,
                           expect_lease_gone: bool = True):
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert err.strip().splitlines()[-1] == "driver: terminated"
    assert "Traceback" not in err
    wait_for(lambda: not any(pid_alive(pid) for pid in tree), timeout=10, what=f"no process of {tree} left")
    store = Store(tmp_path / "cache")
    if expect_lease_gone:
        assert not list(store.leases.glob("*.lease"))                 # released, not merely stale
    assert list(store.scratch.glob("*/checkpoints/0*")), (err[-3000:], sorted(                      # in-stage
        str(p.relative_to(store.root)) for p in store.root.rglob("*"))[:50])                      # checkpoints kept
    assert not list(store.entries())                                  # nothing half-done was published
    record = json.loads((tmp_path / "runs" / "t" / "run.json").read_text())
    assert record["status"] == "interrupted"
    assert record["steps"][0]["status"] == "interrupted" and "SIGTERM" in record["steps"][0]["error"]


@pytest.mark.slow
@pytest.mark.parametrize("target", ["runner", "group"])
def test_sigterm_stops_like_ctrl_c(tmp_path, target):
    trace = tmp_path / "trace"
    proc = start_driver(tmp_path, "t", {"n": 400, "trace": str(trace), "step_seconds": 0.05})
    worker = wait_for(lambda: len(trace.read_text().splitlines()) >= 3 and worker_pid(trace) if trace.exists()
                      else None, what="3 counted steps")
    tree = process_tree(proc.pid)
    assert worker != proc.pid and worker in tree
    if target == "runner":
        proc.send_signal(signal.SIGTERM)            # `kill PID`: only the runner hears it
    else:
        os.killpg(proc.pid, signal.SIGTERM)         # a scheduler stopping the job: everyone hears it
    assert_stopped_cleanly(tmp_path, proc, tree)
    # ...and the rerun resumes from the kept checkpoint instead of starting over
    counted_before = len(trace.read_text().splitlines())
    rerun = start_driver(tmp_path, "rerun", {"n": 400, "trace": str(trace)})
    _, err = rerun.communicate(timeout=120)
    assert rerun.returncode == 0, err
    resumed = trace.read_text().splitlines()[counted_before].split()
    assert resumed[1] == "resume" and int(resumed[2]) >= counted_before - 2


@pytest.mark.slow
def test_group_sigterm_when_the_worker_lost_its_sigterm_handler(tmp_path):
    """glog (pycolmap) replaces the worker's SIGTERM handler and aborts without unwinding: the worker
    dies without releasing its lease, but the runner still stops cleanly and leaves no process behind;
    the dead holder's lease is stale, so a rerun takes it over at once."""
    trace = tmp_path / "trace"
    params = {"n": 400, "trace": str(trace), "step_seconds": 0.05, "native_sigterm": True}
    proc = start_driver(tmp_path, "t", params)
    worker = wait_for(lambda: len(trace.read_text().splitlines()) >= 3 and worker_pid(trace) if trace.exists()
                      else None, what="3 counted steps")
    tree = process_tree(proc.pid)
    assert worker in tree
    os.killpg(proc.pid, signal.SIGTERM)
    assert_stopped_cleanly(tmp_path, proc, tree, expect_lease_gone=False)
    rerun = start_driver(tmp_path, "rerun", {**params, "step_seconds": 0.0})
    _, err = rerun.communicate(timeout=120)
    assert rerun.returncode == 0, err


@pytest.mark.slow
def test_workers_follow_a_sigkilled_runner(tmp_path):
    trace = tmp_path / "trace"
    proc = start_driver(tmp_path, "t", {"n": 400, "trace": str(trace), "step_seconds": 0.05})
    worker = wait_for(lambda: len(trace.read_text().splitlines()) >= 3 and worker_pid(trace) if trace.exists()
                      else None, what="3 counted steps")
    tree = process_tree(proc.pid)
    assert worker in tree
    proc.send_signal(signal.SIGKILL)                # only the runner: nobody tells the worker
    proc.wait(timeout=30)                           # not communicate(): an orphan would hold the pipes open
    wait_for(lambda: not any(pid_alive(pid) for pid in tree), timeout=10, what=f"orphans of {tree} to exit")
    # the orphan did not count on after its parent died (give it the time of a few steps to prove it)
    counted = len(trace.read_text().splitlines())
    time.sleep(0.3)
    assert len(trace.read_text().splitlines()) == counted
    assert list(Store(tmp_path / "cache").scratch.glob("*/checkpoints/0*"))   # its checkpoints stay
