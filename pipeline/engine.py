"""Computing one step, in whatever process an executor chose: check the store, take the lease (or
wait for whoever holds it), run the stage into a temp folder, publish, release.

Only plain data (`Job`, `Outcome`) crosses process or Ray boundaries; the store is reopened from
its path in the worker, so the engine keeps no state besides the cache.
"""
from __future__ import annotations

import functools
import logging
import os
import shutil
import socket
import subprocess
import sys
import time
import traceback
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.errors import UserError, describe, is_user_error
from pipeline.lease import LeaseLost
from pipeline.registry import load_ref
from pipeline.stage import build_params
from pipeline.store import Store


@dataclass(frozen=True)
class Job:
    key: str
    stage_ref: str                  # "module:Class"
    params: dict[str, Any]          # validated values (all fields)
    inputs: dict[str, str]          # input name -> folder/file path
    key_inputs: dict[str, Any]
    label: str
    log_path: str
    cache_root: str
    threads: int = 1
    quiet: bool = False
    lease_ttl_s: float = 30.0


@dataclass(frozen=True)
class Outcome:
    key: str
    status: str                     # "done" | "cached" | "failed"
    path: str | None = None
    error: str | None = None
    user_error: bool = False
    duration_s: float = 0.0
    started: float = 0.0
    finished: float = 0.0


@functools.lru_cache(maxsize=1)
def code_commit() -> str | None:
    """The git commit of the code (None outside a checkout); recorded, not keyed."""
    try:
        here = Path(__file__).parent
        result = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, check=False, capture_output=True,
                                text=True, timeout=5)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here, check=False,
                               capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    if result.returncode != 0:
        return None
    return result.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")


class _ScreenFilter(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not getattr(record, "file_only", False)


def step_logger(job: Job) -> tuple[logging.Logger, list[logging.Handler]]:
    logger = logging.getLogger(f"pipeline.step.{job.key[:16]}.{uuid.uuid4().hex[:6]}")
    logger.setLevel(logging.INFO)
    logger.propagate = False
    Path(job.log_path).parent.mkdir(parents=True, exist_ok=True)
    to_file = logging.FileHandler(job.log_path, encoding="utf-8")
    to_file.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    to_screen = logging.StreamHandler(sys.stderr)
    to_screen.setLevel(logging.INFO)
    to_screen.addFilter(_ScreenFilter())
    to_screen.setFormatter(logging.Formatter(f"[{job.label}] %(message)s"))
    handlers = [to_file, to_screen]
    for handler in handlers:
        logger.addHandler(handler)
    return logger, handlers


def _wait_or_acquire(store: Store, job: Job, log: logging.Logger):
    """Returns (lease, None) once we hold the lease, or (None, path) if someone else published the key.
    A holder that goes silent is taken over after its ttl, as this process's clock measures it."""
    lease = store.lease(job.key)
    delay, announced = 0.05, False
    while not lease.try_acquire():
        path = store.lookup(job.key)
        if path is not None:
            return None, path
        if not announced:
            holder = lease.holder()
            who = f"{holder.host} pid {holder.pid}" if holder else "another process"
            log.info("waiting for lease on %s held by %s", job.key[:12], who)
            announced = True
        time.sleep(delay)
        delay = min(delay * 1.5, 1.0)
    if lease.took_over is not None:
        former, silence = lease.took_over
        why = "its process is dead" if former.dead_here() else f"no heartbeat for {silence:.1f} s on this host's clock"
        log.info("took over the lease on %s from %s pid %d (%s)", job.key[:12], former.host, former.pid, why)
    return lease, None


# How many times a step goes back to waiting after losing its lease mid-step (paused past it) before failing.
LEASE_ATTEMPTS = 3


class InputChangedError(UserError):
    pass


class EnvironmentMismatchError(UserError):
    pass


def _environment_here(stage_cls: type, params: Any, job: Job) -> tuple[dict[str, Any], list[str]]:
    """This process's stage version and environment fingerprint (pipeline.keys), and how they differ from
    what the job's key was computed for ('path: key computed for X, this worker has Y' lines)."""
    from pipeline.canonical import canonical_value
    from pipeline.keys import environment_differences, environment_fingerprint

    actual = canonical_value({"version": str(stage_cls.version),
                              "environment": environment_fingerprint(stage_cls, params)}, where=job.label)
    expected = {"version": job.key_inputs.get("version"), "environment": job.key_inputs.get("environment", {})}
    return actual, environment_differences(expected, actual)


def _check_environment(stage_cls: type, params: Any, job: Job) -> dict[str, Any]:
    """This process's stage version and environment fingerprint, which must be what the key was computed
    for: a worker with other packages, other stage code or other numerical code paths would file a result
    under a key that does not describe it. Returns them for the manifest."""
    actual, differences = _environment_here(stage_cls, params, job)
    if differences:
        raise EnvironmentMismatchError(
            f"step '{job.label}' was not computed on {socket.gethostname()} (pid {os.getpid()}): its key "
            f"{job.key[:12]} was computed for another environment than this worker's ({'; '.join(differences)}). "
            f"A result computed here would be filed under a key that does not describe it, so nothing was "
            f"computed or published. Run the step where the environment matches (same package versions and "
            f"code, a CPU of the same kind), or start the run from a machine like this worker.")
    return actual


def environment_problems(job: Job) -> list[str]:
    """What `_check_environment` would refuse `job` for in this process, without computing anything (the
    Ray executor's start-up probe asks every node this before any step runs: pipeline.probe)."""
    stage_cls = load_ref(job.stage_ref)
    params = build_params(stage_cls.Params, job.params, f"step '{job.label}'")
    return _environment_here(stage_cls, params, job)[1]


def _check_inputs_unchanged(store: Store, job: Job) -> None:
    """Re-hash the user's files after the stage ran (cheap: memoised by size and mtime). A mismatch
    means the stage wrote into a user folder, or the user edited it mid-run: either way the result
    would be filed under a key that does not describe it, so it is not published."""
    expected = job.key_inputs.get("external", {})
    try:
        for name, digest in expected.items():
            if store.hasher.hash_path(Path(job.inputs[name]), what=f"input '{name}'") != digest:
                raise InputChangedError(
                    f"input '{name}' ({job.inputs[name]}) changed while step '{job.label}' ran: either the "
                    f"stage modified the user's files (a bug: stages must write only to their output and "
                    f"scratch folders) or the files were edited during the run. Nothing was published; "
                    f"rerun once the input is final.")
    finally:
        store.hasher.save()


def execute_job(job: Job, placement: dict[str, Any] | None = None) -> Outcome:
    """Produce the published result of `job.key`. Stage exceptions become a failed Outcome (traceback
    in the log file); KeyboardInterrupt propagates after cleanup (lease released, checkpoints kept).
    A writer that loses its lease mid-step (paused or cut off past it, so another worker took over)
    discards its output, publishes nothing, and waits for the new holder's result like any other waiter.
    `placement`: where the executor ran the step (Ray node, assigned GPUs), recorded in the manifest."""
    started = time.time()
    store = Store(job.cache_root, lease_ttl_s=job.lease_ttl_s)
    path = store.lookup(job.key)
    if path is not None:
        return Outcome(job.key, "cached", str(path), started=started, finished=time.time())
    log, handlers = step_logger(job)
    lease = None
    try:
        for _ in range(LEASE_ATTEMPTS):
            lease, path = _wait_or_acquire(store, job, log)
            if path is None:
                path = store.lookup(job.key)      # published between our first look and the lease
            if path is not None:
                return Outcome(job.key, "cached", str(path), started=started, finished=time.time())
            try:
                return _compute(store, job, lease, log, started, placement)
            except LeaseLost as lost:
                log.warning("%s: this attempt's output is discarded, nothing was published; waiting for the "
                            "worker that holds the lease now", lost)
                lease.release()
                lease = None
        raise LeaseLost(f"step '{job.label}' lost its lease {LEASE_ATTEMPTS} times (this worker keeps being "
                        f"paused or cut off from the cache for longer than the lease ttl, {job.lease_ttl_s} s)")
    except Exception as exc:  # noqa: BLE001 - a failed step is data for the run record, not a crash
        log.error("step failed: %s\n%s", describe(exc), traceback.format_exc(), extra={"file_only": True})
        log.error("failed: %s (log: %s)", describe(exc), job.log_path)
        return Outcome(job.key, "failed", error=describe(exc), user_error=is_user_error(exc),
                       started=started, finished=time.time(), duration_s=time.time() - started)
    finally:
        if lease is not None:
            lease.release()
        for handler in handlers:
            log.removeHandler(handler)
            handler.close()


def _compute(store: Store, job: Job, lease, log: logging.Logger, started: float,
             placement: dict[str, Any] | None) -> Outcome:
    """Run the stage under `lease` into tmp/<key>.<token> and publish it (LeaseLost if the lease is lost)."""
    # Folders of former holders of this key: they lost the lease (dead, or fenced), so nobody publishes them.
    store.remove_orphan_tmp(job.key)
    log.info("=== computing %s (%s) on %s pid %d", job.label, job.key, socket.gethostname(), os.getpid())
    stage_cls = load_ref(job.stage_ref)
    params = build_params(stage_cls.Params, job.params, f"step '{job.label}'")
    worker = _check_environment(stage_cls, params, job)
    tmp = store.new_tmp(job.key, lease.token)
    try:
        from pipeline.context import StepContext

        ctx = StepContext(key=job.key, params=params, inputs={k: Path(v) for k, v in job.inputs.items()},
                          out_dir=tmp, scratch_dir=store.scratch_path(job.key), log=log, threads=job.threads,
                          quiet=job.quiet, label=job.label, fence=lease)
        resumed = ctx.latest_checkpoint()
        if resumed is not None:
            log.info("resuming from checkpoint %d", resumed[0])
        stage_cls().run(ctx)
        _check_inputs_unchanged(store, job)
        finished = time.time()
        manifest = {
            "stage": stage_cls.name, "label": job.label, "key_inputs": job.key_inputs,
            "packages": worker["environment"].get("packages", {}), "stage_version": worker["version"],
            "runtime": worker["environment"].get("runtime", {}), "provenance": stage_cls.provenance(),
            "params": {k: v for k, v in job.params.items()}, "inputs": dict(job.inputs), "git_commit": code_commit(),
            "host": socket.gethostname(), "pid": os.getpid(), "python": sys.version.split()[0],
            "started": started, "finished": finished, "duration_s": round(finished - started, 6),
            "resumed_from_checkpoint": resumed[0] if resumed else None, "record": ctx.records,
        }
        if placement:
            manifest["placement"] = placement
        path = store.publish(job.key, tmp, manifest, fence=lambda: lease.ensure_held("publish"))
        tmp = None
        store.remove_scratch(job.key)
        log.info("published %s in %.2fs", job.key[:12], finished - started)
        return Outcome(job.key, "done", str(path), duration_s=finished - started, started=started,
                       finished=time.time())
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
