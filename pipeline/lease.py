"""Leases: at most one process computes a key at a time, without flock (unreliable on network file systems).

A lease is a small JSON file {host, pid, token, expires}. It is created atomically with complete
content by writing a private temp file and `os.link`ing it to the lease name (link fails if the name
exists). The holder's heartbeat thread pushes `expires` forward every `ttl/3` seconds. A lease is
stale when it has expired, or when its holder is a dead process on this host; a stale lease is
broken by renaming it aside (checking afterwards that the moved file is the stale one, so a fresh
lease created in between is put back). Leases only prevent duplicate work: correctness comes from
publishing results with a single rename. Hosts sharing one cache folder need roughly synchronised
clocks (expiry times are compared across hosts); a holder on another host that died is taken over
after at most `ttl_s` (30 s by default).
"""
from __future__ import annotations

import json
import os
import socket
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

HOST = socket.gethostname()


@dataclass(frozen=True)
class LeaseInfo:
    host: str
    pid: int
    token: str
    expires: float

    def is_stale(self, now: float | None = None) -> bool:
        if (now or time.time()) > self.expires:
            return True
        return self.host == HOST and not pid_alive(self.pid)


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # A killed child that its parent has not reaped yet is a zombie: dead for our purposes.
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def read_lease(path: Path) -> LeaseInfo | None:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return LeaseInfo(str(data["host"]), int(data["pid"]), str(data["token"]), float(data["expires"]))
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError):
        # Unreadable lease content: treat as already expired so it can be broken.
        return LeaseInfo("?", -1, "unreadable", 0.0)


class Lease:
    def __init__(self, path: Path, ttl_s: float = 30.0):
        self.path = Path(path)
        self.ttl_s = ttl_s
        self.token = uuid.uuid4().hex
        self.lost = False          # set by the heartbeat if someone else took the lease over
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _content(self) -> str:
        return json.dumps({"host": HOST, "pid": os.getpid(), "token": self.token,
                           "expires": time.time() + self.ttl_s})

    def _private_file(self) -> Path:
        tmp = self.path.with_name(f".{self.path.name}.{self.token}.{uuid.uuid4().hex[:8]}")
        tmp.write_text(self._content(), encoding="utf-8")
        return tmp

    def try_acquire(self) -> bool:
        """Take the lease if free or stale; start the heartbeat. False if a live holder has it."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(2):   # second try after breaking a stale lease
            tmp = self._private_file()
            try:
                os.link(tmp, self.path)
                acquired = True
            except FileExistsError:
                acquired = False
            finally:
                tmp.unlink()
            if acquired:
                self._start_heartbeat()
                return True
            holder = read_lease(self.path)
            if holder is None:
                continue          # released between our link and read: try again
            if not holder.is_stale():
                return False
            break_stale(self.path, holder)
        return False

    def holder(self) -> LeaseInfo | None:
        return read_lease(self.path)

    def _start_heartbeat(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._beat, name=f"lease-{self.path.name}", daemon=True)
        self._thread.start()

    def _beat(self) -> None:
        while not self._stop.wait(self.ttl_s / 3):
            current = read_lease(self.path)
            if current is None or current.token != self.token:
                self.lost = True
                return
            tmp = self._private_file()
            os.replace(tmp, self.path)

    def release(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        current = read_lease(self.path)
        if current is not None and current.token == self.token:
            try:
                self.path.unlink()
            except FileNotFoundError:
                pass


def break_stale(path: Path, stale: LeaseInfo) -> None:
    grave = path.with_name(f".{path.name}.stale.{uuid.uuid4().hex}")
    try:
        os.rename(path, grave)
    except FileNotFoundError:
        return
    moved = read_lease(grave)
    if moved is not None and moved.token != stale.token:
        try:
            os.link(grave, path)   # we displaced a fresh lease: restore it unless replaced meanwhile
        except FileExistsError:
            pass
    grave.unlink()
