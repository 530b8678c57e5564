"""The engine's StageContext: what a running stage sees (see pipeline.stage.StageContext).

Usable on its own, e.g. in a stage's unit tests:

    ctx = StepContext(key="test", params=params, inputs={}, out_dir=tmp / "out",
                      scratch_dir=tmp / "scratch", log=logging.getLogger("t"))
"""
from __future__ import annotations

import json
import logging
import shutil
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Protocol

from pipeline.hashing import file_records, list_files, record_problems, write_json_atomic

KEEP_CHECKPOINTS = 2
PROGRESS_FILE = "progress.json"
CHECKSUM_FILE = ".checksums.json"     # written into every checkpoint, last, before the rename
DAMAGED_PREFIX = "damaged-"           # damaged checkpoints are moved aside under this name


class Fence(Protocol):
    """The lease a step runs under (pipeline.lease.Lease): scratch is written only while it is held."""

    def held(self) -> bool: ...
    def ensure_held(self, what: str) -> None: ...


class StepContext:
    def __init__(self, *, key: str, params: Any, inputs: dict[str, Path], out_dir: Path, scratch_dir: Path,
                 log: logging.Logger, threads: int = 1, quiet: bool = True, label: str = "",
                 fence: Fence | None = None):
        self.key = key
        self.params = params
        self.inputs = dict(inputs)
        self.out_dir = Path(out_dir)
        self.scratch_dir = Path(scratch_dir)
        self.log = log
        self.threads = threads
        self.quiet = quiet
        self.label = label or key[:12]
        # Checked before every checkpoint rename and progress write: a writer that lost its lease (paused
        # past it, cut off) must not touch the scratch folder the new holder resumes from.
        self.fence = fence
        self.records: dict[str, Any] = {}
        self._intact: set[str] = set()     # checkpoints already verified by this context
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.scratch_dir.mkdir(parents=True, exist_ok=True)

    # ---- checkpoints ---------------------------------------------------------------------------
    @property
    def _checkpoints(self) -> Path:
        return self.scratch_dir / "checkpoints"

    def _complete_checkpoints(self) -> list[tuple[int, Path]]:
        if not self._checkpoints.is_dir():
            return []
        found = [(int(p.name), p) for p in self._checkpoints.iterdir() if p.name.isdigit() and p.is_dir()]
        return sorted(found)

    def latest_checkpoint(self) -> tuple[int, Path] | None:
        """The newest checkpoint whose files match the checksums written with it. A damaged one
        (truncated, changed, missing files) is reported by name and moved aside, and the next newest
        is tried; with none intact the step starts over, and the log says so."""
        damaged = []
        for step, folder in reversed(self._complete_checkpoints()):
            problems = [] if folder.name in self._intact else checkpoint_problems(folder)
            if not problems:
                self._intact.add(folder.name)
                if damaged:
                    self.log.warning("resuming from the older intact checkpoint %s instead", folder)
                return step, folder
            aside = folder.with_name(f"{DAMAGED_PREFIX}{folder.name}-{uuid.uuid4().hex[:8]}")
            folder.rename(aside)
            damaged.append(aside)
            self.log.warning("checkpoint %s is damaged (%s); moved it aside to %s (deleted with the scratch "
                             "folder once the step succeeds)", folder, "; ".join(problems), aside)
        if damaged:
            self.log.warning("no intact checkpoint left in %s: the step starts over from the beginning",
                             self._checkpoints)
        return None

    @contextmanager
    def checkpoint(self, step: int) -> Iterator[Path]:
        """Fill the yielded folder; it becomes checkpoint `step` by one rename only if the block
        finishes, so a kill mid-write leaves the previous checkpoint as the newest complete one."""
        if step < 0:
            raise ValueError(f"checkpoint step must be >= 0, got {step}")
        self._checkpoints.mkdir(parents=True, exist_ok=True)
        partial = self._checkpoints / f".partial-{step}-{uuid.uuid4().hex[:8]}"
        partial.mkdir()
        try:
            yield partial
            write_checksums(partial)
            if self.fence is not None:
                self.fence.ensure_held(f"write checkpoint {step}")
        except BaseException:
            shutil.rmtree(partial, ignore_errors=True)
            raise
        final = self._checkpoints / f"{step:012d}"
        if final.exists():
            shutil.rmtree(final)
        partial.rename(final)
        for _, old in self._complete_checkpoints()[:-KEEP_CHECKPOINTS]:
            shutil.rmtree(old, ignore_errors=True)

    # ---- records and progress ------------------------------------------------------------------
    def record(self, **entries: Any) -> None:
        for name, value in entries.items():
            try:
                json.dumps(value, allow_nan=False)
            except (TypeError, ValueError) as exc:
                raise TypeError(f"ctx.record({name}=...): value is not plain JSON ({exc})") from None
        self.records.update(entries)

    @contextmanager
    def progress(self, total: int, desc: str, initial: int = 0) -> Iterator[ProgressReporter]:
        reporter = ProgressReporter(total, desc, initial, label=self.label, quiet=self.quiet, log=self.log,
                                    progress_path=self.scratch_dir / PROGRESS_FILE,
                                    may_write=self.fence.held if self.fence is not None else None)
        try:
            yield reporter
        finally:
            reporter.close()


def write_checksums(folder: Path) -> None:
    """Record the size and sha256 of every file in a finished checkpoint folder."""
    files = file_records(folder, list_files(folder, frozenset({CHECKSUM_FILE})))
    write_json_atomic(folder / CHECKSUM_FILE, {"files": files})


def checkpoint_problems(folder: Path) -> list[str]:
    """What is wrong with a checkpoint folder against its checksums; [] if intact."""
    try:
        expected = json.loads((folder / CHECKSUM_FILE).read_text(encoding="utf-8"))["files"]
    except FileNotFoundError:
        return [f"{CHECKSUM_FILE} is missing (written by an older version, or not by this engine)"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return [f"{CHECKSUM_FILE} is unreadable ({exc})"]
    return record_problems(folder, expected, list_files(folder, frozenset({CHECKSUM_FILE})),
                           unrecorded="not written with the checkpoint")


class ProgressReporter:
    """tqdm bar with ETA on stderr, or (quiet) a log line every ~10%; also keeps progress.json in the
    scratch folder current (at most twice a second) so `dualnerf status` can show running steps."""

    def __init__(self, total: int, desc: str, initial: int, *, label: str, quiet: bool,
                 log: logging.Logger, progress_path: Path | None, may_write: Callable[[], bool] | None = None):
        self.total, self.desc, self.done = max(int(total), 1), desc, int(initial)
        self.quiet, self.log, self.path = quiet, log, progress_path
        self.may_write = may_write
        self.started = time.time()
        self.start_done = self.done
        self.metrics: dict[str, float] = {}
        self._last_write = 0.0
        self._last_decile = self.done * 10 // self.total
        self._bar = None
        if not quiet:
            from tqdm import tqdm  # lazy: only running stages need it

            self._bar = tqdm(total=self.total, initial=self.done, desc=f"{label}: {desc}", file=sys.stderr,
                             dynamic_ncols=True, leave=True)
        self._write(force=True)

    def eta_s(self) -> float | None:
        rate_done = self.done - self.start_done
        if rate_done <= 0:
            return None
        return (time.time() - self.started) / rate_done * (self.total - self.done)

    def update(self, n: int = 1, **metrics: float) -> None:
        self.done += n
        self.metrics.update({k: float(v) for k, v in metrics.items()})
        if self._bar is not None:
            self._bar.update(n)
            if metrics:
                self._bar.set_postfix({k: f"{v:.4g}" for k, v in self.metrics.items()}, refresh=False)
        decile = self.done * 10 // self.total
        if decile > self._last_decile:
            self._last_decile = decile
            eta = self.eta_s()
            message = f"{self.desc}: {self.done}/{self.total} ({100 * self.done // self.total}%)"
            if eta is not None:
                message += f", eta {eta:.0f}s"
            if self.metrics:
                message += ", " + ", ".join(f"{k}={v:.4g}" for k, v in self.metrics.items())
            # quiet mode shows these lines; otherwise they only go to the log file (the bar is on screen)
            self.log.info(message, extra={"file_only": not self.quiet})
        self._write()

    def _write(self, force: bool = False) -> None:
        now = time.time()
        if self.path is None or (not force and now - self._last_write < 0.5):
            return
        if self.may_write is not None and not self.may_write():
            return
        self._last_write = now
        eta = self.eta_s()
        write_json_atomic(self.path, {"desc": self.desc, "done": self.done, "total": self.total,
                                      "eta_s": eta, "updated": now, "metrics": self.metrics})

    def close(self) -> None:
        self._write(force=True)
        if self._bar is not None:
            self._bar.close()
