"""Fencing and clocks with real processes: a writer paused (SIGSTOP) past its lease is taken over and, once
resumed, neither publishes nor writes scratch; a process whose wall clock runs 60 s ahead neither deletes a
live writer's temp folder nor takes its lease."""
from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest

from pipeline.lease import read_lease
from pipeline.store import MANIFEST, Store
from tests.test_pipeline_crash import finish, start, trace_lines, wait_for


def checkpoint_writers(trace: Path) -> list[tuple[int, int]]:
    """(pid, step) of every checkpoint renamed into place, in order."""
    return [(int(parts[0]), int(parts[2])) for parts in trace_lines(trace) if parts[1] == "checkpoint"]


def _counting_step(tmp_path, n):
    """(checkpoint trace, the one-step workflow counting to n at 0.1 s a step, cache folder)."""
    trace, ckpts = tmp_path / "trace", tmp_path / "checkpoints"
    steps = [{"stage": "count", "label": "c", "params": {"n": n, "trace": str(trace), "step_seconds": 0.1,
                                                         "checkpoint_trace": str(ckpts)}}]
    return ckpts, steps, tmp_path / "cache"


@pytest.mark.slow
def test_a_writer_paused_past_its_lease_neither_publishes_nor_writes_scratch(tmp_path):
    n = 40
    ckpts, steps, cache = _counting_step(tmp_path, n)
    ttl = 3.0
    first = start(tmp_path, "first", steps, cache, lease_ttl_s=ttl)
    wait_for(lambda: len(checkpoint_writers(ckpts)) >= 3, what="the first writer's checkpoints")
    first.send_signal(signal.SIGSTOP)
    try:
        stopped_at = len(checkpoint_writers(ckpts))
        second = start(tmp_path, "second", steps, cache, lease_ttl_s=ttl)
        # The second writer waits out the first's silence (one ttl on its own clock), takes over, resumes.
        wait_for(lambda: any(pid == second.pid for pid, _ in checkpoint_writers(ckpts)), timeout=30,
                 what="the second writer's first checkpoint")
        assert read_lease(Store(cache).leases / next(Store(cache).leases.glob("*.lease")).name).pid == second.pid
    finally:
        first.send_signal(signal.SIGCONT)
    b, a = finish(second), finish(first)
    assert b["status"] == ["done"]
    assert a["status"] == ["cached"] and a["results"] == b["results"]          # it waited for the new holder
    result = Path(b["results"][0])
    assert json.loads((result / MANIFEST).read_text())["pid"] == second.pid
    assert (result / "total.txt").read_text() == f"{n * (n - 1) // 2}\n"
    writers = checkpoint_writers(ckpts)
    assert all(pid == second.pid for pid, _ in writers[stopped_at:]), writers   # nothing from the woken one
    resumed = json.loads((result / MANIFEST).read_text())["resumed_from_checkpoint"]
    assert resumed is not None and resumed >= stopped_at - 1
    first_log = (tmp_path / "runs" / "first" / "logs" / "c.log").read_text()
    assert "lost the lease" in first_log and "refusing to write checkpoint" in first_log
    assert "nothing was published" in first_log
    second_log = (tmp_path / "runs" / "second" / "logs" / "c.log").read_text()
    assert "took over the lease on" in second_log and f"pid {first.pid} (no heartbeat for" in second_log
    store = Store(cache)
    assert not list(store.tmp.iterdir()) and not list(store.leases.iterdir())
    assert not store.scratch_path(result.name).exists()


@pytest.mark.slow
def test_a_process_with_a_clock_60s_ahead_leaves_a_live_writers_work_alone(tmp_path):
    n = 25
    ckpts, steps, cache = _counting_step(tmp_path, n)
    writer = start(tmp_path, "writer", steps, cache)
    wait_for(lambda: len(checkpoint_writers(ckpts)) >= 2, what="the writer's checkpoints")
    store = Store(cache)
    live_tmp = list(store.tmp.iterdir())
    assert len(live_tmp) == 1
    # The same key from a host whose wall clock runs 60 s ahead: it starts a run (whose start removes
    # orphaned temp folders) and asks for the lease. It must wait for the writer and reuse its result.
    skewed = start(tmp_path, "skewed", steps, cache, clock_offset_s=60)
    skewed_log = tmp_path / "runs" / "skewed" / "logs" / "c.log"
    wait_for(lambda: skewed_log.exists() and "waiting for lease" in skewed_log.read_text(), what="the skewed waiter")
    assert live_tmp[0].exists()
    w, s = finish(writer), finish(skewed)
    assert w["status"] == ["done"] and s["status"] == ["cached"] and s["results"] == w["results"]
    assert {pid for pid, _ in checkpoint_writers(ckpts)} == {writer.pid}
    assert json.loads((Path(w["results"][0]) / MANIFEST).read_text())["pid"] == writer.pid
    assert "took over" not in skewed_log.read_text()


def test_orphan_clean_up_reads_no_clock(tmp_path, monkeypatch):
    """In-process version of the above: with the wall clock 60 s ahead (or behind) the live writer's tmp
    folder stays, and the folders of a dead writer and of a former holder go."""
    import time

    store = Store(tmp_path / "cache")
    lease = store.lease("c" * 64)
    assert lease.try_acquire()
    try:
        live = store.new_tmp("c" * 64, lease.token)
        former = store.new_tmp("c" * 64, "0" * 32)          # a writer that lost the lease to `lease`
        unleased = store.new_tmp("d" * 64, "1" * 32)
        real = time.time
        for offset in (60, -60):
            monkeypatch.setattr(time, "time", lambda offset=offset: real() + offset)
            assert store.orphan_tmp() == sorted([former, unleased])
            monkeypatch.undo()
        store.remove_orphan_tmp()
        assert live.exists() and not former.exists() and not unleased.exists()
    finally:
        lease.release()


def test_gc_watches_leases_it_cannot_prove_dead_before_removing_their_work(tmp_path):
    store = Store(tmp_path / "cache")
    store.leases.mkdir(parents=True)
    silent = "e" * 64                                  # a holder on another host that stopped beating
    (store.leases / f"{silent}.lease").write_text(json.dumps({"host": "elsewhere", "pid": 1, "token": "s" * 32,
                                                              "ttl_s": 0.3}))
    (store.leases / f"{silent}.lease.{'s' * 32}.beat").write_text("4")
    silent_tmp = store.new_tmp(silent, "s" * 32)
    live = store.lease("f" * 64)
    assert live.try_acquire()
    try:
        live_tmp = store.new_tmp("f" * 64, live.token)
        assert store.orphan_tmp() == []                # without watching, neither can be judged
        report = store.gc(set(), watch_s=1.0)
    finally:
        live.release()
    assert not silent_tmp.exists() and not (store.leases / f"{silent}.lease").exists()
    assert live_tmp.exists()
    assert f"leases/{silent}.lease" in report.removed_other
