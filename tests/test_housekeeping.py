"""Housekeeping: orphaned temp folders of dead writers are listed and removed by the next run; a worker
that loaded pycolmap stops cleanly on SIGTERM without native stack dumps; a failed run ends with its
first error and the log holding it."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.lease import HOST
from pipeline.store import Store

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")


def dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def make_orphans(store: Store) -> tuple[Path, Path, Path, object]:
    """tmp folders of: a writer killed without a lease file, a dead holder of an unexpired lease, a live
    writer (this process holds its lease)."""
    killed = store.new_tmp("a" * 64)
    (killed / "half.bin").write_bytes(b"x" * 10)
    dead = store.new_tmp("b" * 64)
    store.leases.mkdir(parents=True, exist_ok=True)
    (store.leases / f"{'b' * 64}.lease").write_text(json.dumps(
        {"host": HOST, "pid": dead_pid(), "token": "t", "ttl_s": 3600}))
    live_lease = store.lease("c" * 64)
    assert live_lease.try_acquire()
    live = store.new_tmp("c" * 64, live_lease.token)
    return killed, dead, live, live_lease


def test_cache_verify_lists_orphaned_temp_folders(tmp_path, capsys):
    from experiments.cli import main

    store = Store(tmp_path / "cache")
    killed, dead, live, lease = make_orphans(store)
    try:
        assert main(["--cache", str(store.root), "cache", "verify"]) == 0
    finally:
        lease.release()
    out = capsys.readouterr().out
    assert f"ORPHAN tmp/{killed.name}" in out and f"ORPHAN tmp/{dead.name}" in out
    assert live.name not in out and "2 orphaned temporary folder(s)" in out


def test_the_next_run_removes_orphans_of_dead_writers_only(tmp_path):
    from pipeline.dag import Step
    from pipeline.executors import SerialExecutor
    from pipeline.runner import run_steps
    from tests.pipeline_stages import REGISTRY

    store = Store(tmp_path / "cache")
    killed, dead, live, lease = make_orphans(store)
    try:
        result = run_steps([Step("count", {"n": 2}, label="c")], registry=REGISTRY, store=store,
                           executor=SerialExecutor(threads=1), run_dir=tmp_path / "runs", quiet=True)
    finally:
        lease.release()
    assert result.ok
    assert not killed.exists() and not dead.exists() and live.exists()


def test_a_killed_writer_leaves_a_temp_folder_that_the_next_run_removes(tmp_path):
    """The issue's case: kill -9 during a step leaves cache/tmp/<key>.<nonce>."""
    spec = {"cache": str(tmp_path / "cache"), "run_dir": str(tmp_path / "runs"), "executor": "serial",
            "steps": [{"stage": "suicide", "label": "s", "params": {}}]}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    subprocess.run([sys.executable, "-m", "tests.pipeline_stages", str(tmp_path / "spec.json")], check=False, cwd=ROOT,
                   env=ENV, capture_output=True, timeout=120)
    store = Store(tmp_path / "cache")
    left = list(store.tmp.iterdir())
    assert left and store.orphan_tmp() == sorted(left)
    store.remove_orphan_tmp()
    assert list(store.tmp.iterdir()) == []


SIGTERM_CHILD = """
import os, signal, sys, time
def handler(signum, frame):
    raise KeyboardInterrupt("SIGTERM")
signal.signal(signal.SIGTERM, handler)
from dualnerf.io.colmap import load_pycolmap
load_pycolmap()
try:
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(5)
except KeyboardInterrupt:
    print("stopped cleanly", file=sys.stderr)
    sys.exit(143)
"""


def test_sigterm_after_loading_pycolmap_unwinds_without_a_native_stack_dump():
    proc = subprocess.run([sys.executable, "-c", SIGTERM_CHILD], check=False, cwd=ROOT, env=ENV, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 143, proc.stderr
    assert "stopped cleanly" in proc.stderr
    assert "stack trace" not in proc.stderr and "*** SIGTERM" not in proc.stderr


SFM_DRIVER = """
import json, sys
from pathlib import Path
from pipeline.dag import External, Step
from pipeline.executors import make_executor
from pipeline.runner import Terminated, run_steps, terminate_as_interrupt
from pipeline.store import Store
from stages import STAGES

source, cache, runs = sys.argv[1:4]
step = Step("preprocess", {"method": "sfm"}, {"source": External(source)}, label="sfm")
try:
    with terminate_as_interrupt():
        run_steps([step], registry=STAGES, store=Store(cache), executor=make_executor("process", jobs=1),
                  run_dir=Path(runs), quiet=True)
except Terminated:
    print("driver: terminated", file=sys.stderr)
    sys.exit(Terminated.exit_status)
"""


@pytest.mark.slow
def test_group_sigterm_during_sfm_stops_cleanly_without_glog_stack_dump(tiny_scene, tmp_path):
    folder = tmp_path / "photos"
    shutil.copytree(tiny_scene / "images", folder)
    proc = subprocess.Popen([sys.executable, "-c", SFM_DRIVER, str(folder), str(tmp_path / "cache"),
                             str(tmp_path / "runs")], cwd=ROOT, env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not list((tmp_path / "cache").glob("scratch/*/sfm/database.db")):
            time.sleep(0.05)
        assert proc.poll() is None, "SfM finished before it could be signalled"
        time.sleep(0.5)                            # inside pycolmap's feature extraction
        os.killpg(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 143, err
    assert "stack trace" not in err and "*** SIGTERM" not in err, err
    assert "driver: terminated" in err
    assert not list((tmp_path / "cache").glob("leases/*.lease")), "the worker did not release its lease"


def test_a_failed_run_ends_with_the_first_error_and_its_log(tiny_scene, tmp_path, monkeypatch, capsys):
    from experiments.cli import main

    scene = tmp_path / "scenes" / "broken"
    (scene / "images").mkdir(parents=True)
    for name in ("view_000.png", "view_001.png"):
        shutil.copyfile(tiny_scene / "images" / name, scene / "images" / name)
    shutil.copyfile(tiny_scene / "scene.toml", scene / "scene.toml")
    monkeypatch.chdir(tmp_path)
    status = main(["--quiet", "--cache", "cache", "--runs", "runs", "run", str(ROOT / "workflows" / "ablation.toml"),
                   "--executor", "serial", "--set", "scenes_dir=scenes", "--set", "scene=broken"])
    assert status == 1
    lines = capsys.readouterr().err.strip().splitlines()
    last = lines[-1]
    assert last.startswith("run: first error: preprocess[broken]:") and "at least 3" in last
    log = Path(last.rsplit("full log: ", 1)[1])
    assert log.is_file() and "at least 3" in log.read_text()
    assert sum("skipped" in line for line in lines) == 1, "skipped steps are one line, not a screen"
