"""Leases: exclusive, kept alive by a heartbeat counter, taken over when the holder died or went silent for
its ttl as the observer's own clock measures it; a holder that lost its lease fences itself."""
from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from pipeline.lease import HOST, Lease, LeaseLost, LeaseWatch, read_beat, read_lease


class FakeClock:
    def __init__(self, now: float = 1000.0):
        self.now = now

    def __call__(self) -> float:
        return self.now


def test_exclusive_and_released(tmp_path):
    path = tmp_path / "k.lease"
    first, second = Lease(path), Lease(path)
    assert first.try_acquire()
    assert not second.try_acquire()
    assert read_lease(path).token == first.token
    first.release()
    assert not path.exists() and not first.beat_file.exists()
    assert second.try_acquire()
    first.release()                      # releasing a lease we no longer hold leaves the holder's alone
    assert read_lease(path).token == second.token
    second.release()


def test_heartbeat_advances_the_counter_and_keeps_the_lease(tmp_path):
    lease = Lease(tmp_path / "k.lease", ttl_s=0.3)
    assert lease.try_acquire()
    try:
        seen = {read_beat(lease.path, lease.token)}
        deadline = time.monotonic() + 5
        while len(seen) < 3 and time.monotonic() < deadline:
            seen.add(read_beat(lease.path, lease.token))
            time.sleep(0.01)
        assert len(seen) >= 3                      # the counter moves every ttl/3
        lease.ensure_held("publish")               # renewed recently, file still ours
        other = Lease(lease.path, ttl_s=0.3)
        for _ in range(8):                         # 0.4 s of watching: longer than the ttl, but it beats
            assert not other.try_acquire()
            time.sleep(0.05)
    finally:
        lease.release()


def test_a_silent_holder_on_another_host_is_taken_over_after_its_ttl_on_the_observers_clock(tmp_path):
    path = tmp_path / "k.lease"
    # A holder on another host (its pid cannot be checked) with a wall clock far in the past or future:
    # only the heartbeat counter matters.
    path.write_text(json.dumps({"host": "elsewhere", "pid": 1, "token": "old", "ttl_s": 10, "acquired": 0}))
    (tmp_path / "k.lease.old.beat").write_text("7")
    clock = FakeClock()
    taker = Lease(path, clock=clock)
    assert not taker.try_acquire()                 # first look: the counter was just seen
    clock.now += 9.9
    assert not taker.try_acquire()                 # silent, but not for a whole ttl yet
    (tmp_path / "k.lease.old.beat").write_text("8")
    clock.now += 5
    assert not taker.try_acquire()                 # it beat: the silence starts again
    clock.now += 10
    assert taker.try_acquire() and read_lease(path).token == taker.token
    assert taker.took_over[0].token == "old" and taker.took_over[1] == pytest.approx(10)
    assert not (tmp_path / "k.lease.old.beat").exists()      # the former holder's beat file went with it
    taker.release()


def test_a_lease_written_by_an_older_version_is_watched_with_the_observers_ttl(tmp_path):
    path = tmp_path / "k.lease"
    path.write_text(json.dumps({"host": "elsewhere", "pid": 1, "token": "old", "expires": time.time() + 3600}))
    clock = FakeClock()
    taker = Lease(path, ttl_s=2, clock=clock)
    assert not taker.try_acquire()
    clock.now += 2
    assert taker.try_acquire()
    taker.release()


def test_lease_of_dead_process_on_this_host_is_taken_over_at_once(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], check=False, capture_output=True, text=True)
    path = tmp_path / "k.lease"
    path.write_text(json.dumps({"host": HOST, "pid": int(dead.stdout), "token": "old", "ttl_s": 3600}))
    taker = Lease(path)
    assert taker.try_acquire()
    taker.release()
    path.write_text("{not json")                 # a damaged lease file does not block forever
    damaged = Lease(path)
    assert damaged.try_acquire()
    damaged.release()


def test_a_holder_silent_past_its_safe_window_fences_itself(tmp_path):
    clock = FakeClock()
    lease = Lease(tmp_path / "k.lease", ttl_s=3600, clock=clock)     # the heartbeat thread will not run
    assert lease.try_acquire()
    try:
        lease.ensure_held("publish")
        assert lease.held()
        clock.now += 0.75 * 3600 + 1            # e.g. SIGSTOPped: its own clock ran on meanwhile
        assert not lease.held()
        with pytest.raises(LeaseLost, match="refusing to publish"):
            lease.ensure_held("publish")
    finally:
        lease.release()


def test_a_holder_whose_lease_was_broken_fences_itself(tmp_path):
    clock = FakeClock()
    holder = Lease(tmp_path / "k.lease", ttl_s=3600, clock=clock)
    assert holder.try_acquire()
    watch_clock = FakeClock()
    taker = Lease(holder.path, ttl_s=3600, clock=watch_clock)
    assert not taker.try_acquire()
    watch_clock.now += 3600                     # the observer saw no heartbeat for the ttl
    assert taker.try_acquire()
    with pytest.raises(LeaseLost, match=f"{HOST} pid"):
        holder.ensure_held("write checkpoint 3")   # its own clock says fresh, but the file is not its own
    holder.release()                            # leaves the new holder's lease alone
    assert read_lease(taker.path).token == taker.token
    taker.ensure_held("publish")
    taker.release()


def test_watch_counts_the_silence_from_its_own_first_look(tmp_path):
    path = tmp_path / "k.lease"
    path.write_text(json.dumps({"host": "elsewhere", "pid": 1, "token": "t", "ttl_s": 5}))
    clock = FakeClock()
    watch = LeaseWatch(clock)
    holder = read_lease(path)
    assert watch.silent_for(path, holder) == 0
    clock.now += 4
    assert not watch.expired(path, holder)
    clock.now += 1
    assert watch.expired(path, holder)
