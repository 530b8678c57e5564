"""Leases: at most one process computes a key at a time, without flock (unreliable on network file
systems) and without ever comparing the clocks of two hosts.

Files, in the store's leases/ folder:
    <k>.lease                 {host, pid, token, ttl_s, acquired}: who holds <k>. Created with complete
                              content by writing a private temp file and `os.link`ing it to the name (link
                              fails if the name exists); never rewritten while held.
    <k>.lease.<token>.beat    the holder's heartbeat: a counter its heartbeat thread rewrites (temp file +
                              rename) every ttl/3. Each holder writes only its own beat file, so a holder
                              that wakes up late can never overwrite a newer holder's state.

Expiry is judged by an *observer* (a process waiting for the key, `gc`) on its OWN monotonic clock: a lease
is expired once the observer has seen the same (token, counter) for the holder's `ttl_s`. Wall clocks are
only recorded for people to read. A holder on this host whose process is dead is expired at once.

Fencing, on the holder's side: the holder remembers when (on its own monotonic clock, CLOCK_BOOTTIME on
Linux so a suspended machine counts the time it slept) it last renewed successfully, and considers the
lease lost once `safe_s` = 3/4 ttl has passed without a renewal: an observer needs a full ttl of silence,
measured from the moment it *saw* the last counter, so the holder always gives up first. `ensure_held()`
checks that and re-reads the lease file (the token must still be ours); the engine calls it right before
publishing and before each checkpoint rename, so a writer that was paused (SIGSTOP, a stalled VM, a
network partition) past its lease notices when it resumes, and neither publishes nor writes scratch. What
remains is the instant between that check and the rename itself; a rename from that instant is harmless
(results are published by one rename and a second publish of a key keeps the first; a checkpoint of step N
holds the state of step N whoever wrote it).

Leases only prevent duplicate work and keep scratch single-writer: correctness of results comes from
publishing with a single rename.
"""
from __future__ import annotations

import json
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

HOST = socket.gethostname()
SAFE_FRACTION = 0.75          # a holder trusts its lease for this share of the ttl after its last renewal


def monotonic_clock() -> float:
    """Seconds on a clock that never jumps; on Linux it also counts time spent suspended (CLOCK_BOOTTIME),
    so a laptop that slept through its lease knows it when it wakes."""
    boottime = getattr(time, "CLOCK_BOOTTIME", None)
    if boottime is not None:
        try:
            return time.clock_gettime(boottime)
        except OSError:
            pass
    return time.monotonic()


class LeaseLost(RuntimeError):
    """The holder can no longer be sure it holds its lease: it must not publish or write scratch."""


@dataclass(frozen=True)
class LeaseInfo:
    host: str
    pid: int
    token: str
    ttl_s: float | None = None     # the holder's ttl (None: a lease written by an older version)
    acquired: float = 0.0          # the holder's wall clock at acquisition: for people, never compared

    def dead_here(self) -> bool:
        """Provably gone without waiting: its process on this host is dead, or the file is unreadable."""
        if self.token == UNREADABLE:
            return True
        return self.host == HOST and not pid_alive(self.pid)


UNREADABLE = "unreadable"


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
        data = json.loads(Path(path).read_text(encoding="utf-8"))
        ttl = data.get("ttl_s")
        return LeaseInfo(str(data["host"]), int(data["pid"]), str(data["token"]),
                         float(ttl) if ttl is not None else None, float(data.get("acquired", 0.0)))
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        # Unreadable lease content (leases are created whole, so this is damage): breakable at once.
        return LeaseInfo("?", -1, UNREADABLE)


def beat_path(path: Path, token: str) -> Path:
    return Path(path).with_name(f"{Path(path).name}.{token}.beat")


def read_beat(path: Path, token: str) -> int | None:
    """The heartbeat counter of the holder with `token`; None if its beat file is missing or unreadable."""
    try:
        return int(beat_path(path, token).read_text(encoding="ascii"))
    except (OSError, ValueError):
        return None


def _write_beat(path: Path, token: str, count: int) -> None:
    target = beat_path(path, token)
    tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex[:8]}")
    tmp.write_text(str(count), encoding="ascii")
    os.replace(tmp, target)


class LeaseWatch:
    """An observer's view of other processes' leases: a lease is expired once its (token, counter) has not
    changed for the holder's ttl on this process's clock. Keep one watch across polls: it remembers when
    it first saw each counter value."""

    def __init__(self, clock: Callable[[], float] = monotonic_clock, default_ttl_s: float = 30.0):
        self.clock = clock
        self.default_ttl_s = default_ttl_s
        self._seen: dict[Path, tuple[str, int | None, float]] = {}

    def silent_for(self, path: Path, holder: LeaseInfo) -> float:
        """How long this observer has seen the holder's heartbeat unchanged (0 on the first look)."""
        beat = read_beat(path, holder.token)
        now = self.clock()
        seen = self._seen.get(Path(path))
        if seen is None or seen[:2] != (holder.token, beat):
            self._seen[Path(path)] = (holder.token, beat, now)
            return 0.0
        return now - seen[2]

    def expired(self, path: Path, holder: LeaseInfo) -> bool:
        if holder.dead_here():
            return True
        return self.silent_for(path, holder) >= (holder.ttl_s or self.default_ttl_s)


class Lease:
    def __init__(self, path: Path, ttl_s: float = 30.0, clock: Callable[[], float] = monotonic_clock):
        self.path = Path(path)
        self.ttl_s = ttl_s
        self.safe_s = ttl_s * SAFE_FRACTION
        self.clock = clock
        self.token = uuid.uuid4().hex
        self.watch = LeaseWatch(clock, default_ttl_s=ttl_s)
        self.lost = False          # set by the heartbeat or ensure_held once the lease may be someone else's
        self.lost_reason = ""
        self.took_over: tuple[LeaseInfo, float] | None = None   # (former holder, its silence) if we broke it
        self._last_renewal: float | None = None      # our clock when the last successful renewal began
        self._count = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def beat_file(self) -> Path:
        return beat_path(self.path, self.token)

    def _private_file(self) -> Path:
        tmp = self.path.with_name(f".{self.path.name}.{self.token}.{uuid.uuid4().hex[:8]}")
        tmp.write_text(json.dumps({"host": HOST, "pid": os.getpid(), "token": self.token, "ttl_s": self.ttl_s,
                                   "acquired": time.time()}), encoding="utf-8")
        return tmp

    def try_acquire(self) -> bool:
        """Take the lease if free, or if its holder is dead here or has been silent for its ttl as this
        lease's watch saw it (so a caller polling the same Lease object takes over an abandoned lease after
        one ttl). Starts the heartbeat. False while a live holder has it."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(2):   # second try after breaking a stale lease
            _write_beat(self.path, self.token, self._count)   # first: an observer always finds a counter
            started = self.clock()
            tmp = self._private_file()
            try:
                os.link(tmp, self.path)
                acquired = True
            except FileExistsError:
                acquired = False
            finally:
                tmp.unlink()
            if acquired:
                self.lost, self.lost_reason = False, ""
                self._last_renewal = started
                self._start_heartbeat()
                return True
            self.beat_file.unlink(missing_ok=True)
            holder = read_lease(self.path)
            if holder is None:
                continue          # released between our link and read: try again
            silence = self.watch.silent_for(self.path, holder)
            if not (holder.dead_here() or silence >= (holder.ttl_s or self.ttl_s)):
                return False
            if break_stale(self.path, holder):
                self.took_over = (holder, silence)
        return False

    def holder(self) -> LeaseInfo | None:
        return read_lease(self.path)

    # ---- the holder's side -------------------------------------------------------------------------
    def held(self) -> bool:
        """Cheap check (no file access): not known lost, and renewed within `safe_s` on our clock."""
        return (not self.lost and self._last_renewal is not None
                and self.clock() - self._last_renewal <= self.safe_s)

    def ensure_held(self, what: str = "publish") -> None:
        """Raise LeaseLost unless we certainly still hold the lease: renewed within `safe_s` on our own
        clock and the lease file still carries our token. Call right before an irreversible write."""
        reason = self.lost_reason if self.lost else ""
        if not reason:
            since = self.clock() - (self._last_renewal if self._last_renewal is not None else float("-inf"))
            if since > self.safe_s:
                reason = (f"its last heartbeat was {since:.1f} s ago on this host's clock (the process was "
                          f"paused, or cut off from the cache); after {self.safe_s:.1f} s another worker may "
                          f"have taken the lease over")
            else:
                current = read_lease(self.path)
                if current is None:
                    reason = "the lease file is gone (another worker saw no heartbeat for the ttl and broke it)"
                elif current.token != self.token:
                    reason = f"{current.host} pid {current.pid} holds it now"
        if reason:
            self.lost, self.lost_reason = True, reason
            raise LeaseLost(f"lost the lease {self.path.name} ({reason}); refusing to {what}")

    def _start_heartbeat(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._beat, name=f"lease-{self.path.name}", daemon=True)
        self._thread.start()

    def _beat(self) -> None:
        while not self._stop.wait(self.ttl_s / 3):
            started = self.clock()
            if started - self._last_renewal > self.safe_s:
                self.lost = True
                self.lost_reason = (f"no heartbeat for {started - self._last_renewal:.1f} s on this host's "
                                    f"clock (more than {self.safe_s:.1f} s): the process was paused or starved")
                return
            current = read_lease(self.path)
            if current is None or current.token != self.token:
                self.lost = True
                self.lost_reason = ("the lease file is gone" if current is None
                                    else f"{current.host} pid {current.pid} holds it now")
                return
            self._count += 1
            try:
                _write_beat(self.path, self.token, self._count)
            except OSError:
                continue            # a failed renewal does not count; ensure_held notices the silence
            self._last_renewal = started

    def release(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        current = read_lease(self.path)
        if current is not None and current.token == self.token:
            _remove_if_token(self.path, self.token)
        self.beat_file.unlink(missing_ok=True)
        self._last_renewal = None


def _remove_if_token(path: Path, token: str) -> bool:
    """Remove the lease file if it carries `token`: renamed aside first and checked afterwards, so a
    lease that replaced it in between is put back (unless yet another appeared). True if removed."""
    grave = path.with_name(f".{path.name}.gone.{uuid.uuid4().hex}")
    try:
        os.rename(path, grave)
    except FileNotFoundError:
        return False
    moved = read_lease(grave)
    if moved is not None and moved.token != token:
        try:
            os.link(grave, path)   # we displaced a different lease: restore it unless replaced meanwhile
        except FileExistsError:
            pass
        grave.unlink()
        return False
    grave.unlink()
    return True


def break_stale(path: Path, stale: LeaseInfo) -> bool:
    """Remove the lease of a holder judged dead or expired, and its beat file. True if this call removed it."""
    removed = _remove_if_token(path, stale.token)
    if removed and stale.token != UNREADABLE:
        beat_path(path, stale.token).unlink(missing_ok=True)
    return removed
