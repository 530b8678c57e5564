"""Leases: exclusive, kept alive by the heartbeat, taken over when expired or when the holder died."""
from __future__ import annotations

import json
import subprocess
import sys
import time

from pipeline.lease import HOST, Lease, read_lease


def test_exclusive_and_released(tmp_path):
    path = tmp_path / "k.lease"
    first, second = Lease(path), Lease(path)
    assert first.try_acquire()
    assert not second.try_acquire()
    assert read_lease(path).token == first.token
    first.release()
    assert not path.exists()
    assert second.try_acquire()
    first.release()                      # releasing a lease we no longer hold leaves the holder's alone
    assert read_lease(path).token == second.token
    second.release()


def test_heartbeat_extends_expiry(tmp_path):
    lease = Lease(tmp_path / "k.lease", ttl_s=0.3)
    assert lease.try_acquire()
    try:
        first_expiry = read_lease(lease.path).expires
        deadline = time.monotonic() + 5
        while read_lease(lease.path).expires == first_expiry and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.35)                 # longer than the ttl: without heartbeats it would have expired
        assert not read_lease(lease.path).is_stale()
        assert not Lease(lease.path).try_acquire()
    finally:
        lease.release()


def test_expired_lease_of_other_host_is_taken_over(tmp_path):
    path = tmp_path / "k.lease"
    path.write_text(json.dumps({"host": "elsewhere", "pid": 1, "token": "old", "expires": time.time() + 60}))
    assert not Lease(path).try_acquire()         # live on another host: we cannot check its pid, so wait
    path.write_text(json.dumps({"host": "elsewhere", "pid": 1, "token": "old", "expires": time.time() - 1}))
    taker = Lease(path)
    assert taker.try_acquire() and read_lease(path).token == taker.token
    taker.release()


def test_lease_of_dead_process_on_this_host_is_taken_over(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], check=False, capture_output=True, text=True)
    path = tmp_path / "k.lease"
    path.write_text(json.dumps({"host": HOST, "pid": int(dead.stdout), "token": "old",
                                "expires": time.time() + 60}))
    taker = Lease(path)
    assert taker.try_acquire()
    taker.release()
    path.write_text("{not json")                 # a damaged lease file does not block forever
    damaged = Lease(path)
    assert damaged.try_acquire()
    damaged.release()
