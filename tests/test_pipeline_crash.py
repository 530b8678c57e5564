"""Crash safety and concurrency with real processes: SIGKILL mid-run and mid-publish, Ctrl-C, and two
processes asking for the same key."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.store import MANIFEST, Store
from tests.test_pipeline_store import tree_digest

ROOT = Path(__file__).resolve().parents[1]


def start(tmp_path: Path, name: str, steps: list[dict], cache: Path, **extra) -> subprocess.Popen:
    spec = {"cache": str(cache), "run_dir": str(tmp_path / "runs" / name), "steps": steps, **extra}
    spec_path = tmp_path / f"{name}.json"
    spec_path.write_text(json.dumps(spec))
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, "-m", "tests.pipeline_stages", str(spec_path)], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(proc: subprocess.Popen, timeout: float = 60) -> dict:
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err
    return json.loads(out.strip().splitlines()[-1])


def wait_for(predicate, timeout: float = 30.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def trace_lines(trace: Path) -> list[list[str]]:
    return [line.split() for line in trace.read_text().splitlines()] if trace.exists() else []


def counted(trace: Path) -> int:
    return sum(1 for parts in trace_lines(trace) if parts[1] != "resume")


@pytest.mark.slow
def test_sigkill_mid_run_resumes_from_checkpoint_with_identical_result(tmp_path):
    trace = tmp_path / "trace"
    n = 60
    steps = [{"stage": "count", "params": {"n": n, "trace": str(trace), "step_seconds": 0.05}, "label": "c"}]
    proc = start(tmp_path, "killed", steps, tmp_path / "cache")
    wait_for(lambda: counted(trace) >= 8, what="8 counted steps")
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed_at = counted(trace)
    assert killed_at < n
    store = Store(tmp_path / "cache")
    assert not list(store.entries())                                  # nothing published
    # the lease of the dead process is stale (dead pid): the rerun takes it over at once
    steps[0]["params"]["step_seconds"] = 0.0                          # non-semantic: same key
    result = finish(start(tmp_path, "rerun", steps, tmp_path / "cache"))
    lines = trace_lines(trace)[killed_at:]
    assert lines[0][1] == "resume"
    resumed_from = int(lines[0][2])
    assert resumed_from >= killed_at - 1 and resumed_from > 0         # did not restart from 0
    assert [int(p[1]) for p in lines[1:]] == list(range(resumed_from + 1, n + 1))
    fresh = finish(start(tmp_path, "fresh", [{"stage": "count", "params": {"n": n}}], tmp_path / "cache2"))
    assert tree_digest(Path(result["results"][0])) == tree_digest(Path(fresh["results"][0]))
    assert Path(result["results"][0]).name == Path(fresh["results"][0]).name         # same key
    manifest = json.loads((Path(result["results"][0]) / MANIFEST).read_text())
    assert manifest["resumed_from_checkpoint"] == resumed_from


@pytest.mark.parametrize("where", ["before_publish", "mid_manifest"])
def test_kill_during_publish_leaves_no_visible_entry(tmp_path, where):
    steps = [{"stage": "count", "params": {"n": 3}, "label": "c"}]
    proc = start(tmp_path, "dies", steps, tmp_path / "cache", die=where)
    proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    store = Store(tmp_path / "cache")
    assert not list(store.entries())
    assert list((store.root / "tmp").iterdir())                       # the unpublished attempt is in tmp/
    result = finish(start(tmp_path, "rerun", steps, tmp_path / "cache"))
    assert result["status"] == ["done"]
    assert (Path(result["results"][0]) / "total.txt").read_text() == "3\n"
    report = store.gc({Path(result["results"][0]).name})
    assert report.removed == [] and not list((store.root / "tmp").iterdir())


@pytest.mark.slow
def test_two_processes_same_key_compute_once(tmp_path):
    trace, gate = tmp_path / "trace", tmp_path / "gate"
    steps = [{"stage": "count", "params": {"n": 5, "trace": str(trace), "gate": str(gate)}, "label": "same"}]
    first = start(tmp_path, "first", steps, tmp_path / "cache")
    wait_for(lambda: counted(trace) >= 1, what="first process to start computing")
    second = start(tmp_path, "second", steps, tmp_path / "cache")
    second_log = tmp_path / "runs" / "second" / "logs" / "same.log"
    wait_for(lambda: second_log.exists() and "waiting for lease" in second_log.read_text(),
             what="second process to wait on the lease")
    gate.touch()
    a, b = finish(first), finish(second)
    assert a["status"] == ["done"] and b["status"] == ["cached"]
    assert a["results"] == b["results"]
    assert len({parts[0] for parts in trace_lines(trace)}) == 1       # one pid did all the counting
    assert counted(trace) == 5


@pytest.mark.slow
@pytest.mark.parametrize("executor", ["serial", "process"])
def test_ctrl_c_stops_cleanly_keeping_checkpoints(tmp_path, executor):
    trace = tmp_path / "trace"
    steps = [{"stage": "count", "label": "c",
              "params": {"n": 200, "trace": str(trace), "step_seconds": 0.05, "native_sigterm": True}}]
    proc = start(tmp_path, "interrupted", steps, tmp_path / "cache", executor=executor)
    wait_for(lambda: counted(trace) >= 3, what="3 counted steps")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode != 0 and "KeyboardInterrupt" in err, (proc.returncode, err[-3000:],
                                                                 trace.read_text()[-2000:])
    store = Store(tmp_path / "cache")
    assert not list(store.leases.glob("*.lease"))                     # lease released
    assert not list((store.root / "tmp").iterdir())                   # temp output removed
    assert list(store.scratch.glob("*/checkpoints/0*"))               # checkpoints kept
    record = json.loads((tmp_path / "runs" / "interrupted" / "run.json").read_text())
    assert record["status"] == "interrupted" and record["steps"][0]["status"] == "interrupted"
