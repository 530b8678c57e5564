"""Executors run `Job`s and report `Outcome`s; the runner (pipeline.runner) decides what is ready.

    SerialExecutor()                 in this process, one at a time (tests, debugging)
    ProcessPoolExecutor(jobs)        spawn-context worker processes, up to `jobs` at once while
                                     their stages' CPU hints fit the cores; each job
                                     gets threads = its stage's hint (at most the cores)
    RayExecutor(address=None)        one ray task per step with the stage's resource hints; joins
                                     `address` or starts a local instance; ray imported lazily
All of them read and write the shared cache folder; only Jobs (keys, params, paths) cross over.
"""
from __future__ import annotations

import dataclasses
import functools
import os
import signal
import sys
import time
from abc import ABC, abstractmethod
from typing import Any

from pipeline.engine import Job, Outcome, execute_job
from pipeline.errors import UserError
from pipeline.stage import Resources


def cpu_count() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


class Executor(ABC):
    name: str = "?"
    slots: int = 1              # how many jobs the runner may have in flight
    threads: int = 1            # ctx.threads for each job

    cores: int = 1              # threads the executor's jobs may use at once (the runner packs by hints)

    def threads_for(self, resources: Resources) -> int:
        """ctx.threads for a job of a stage with these hints: its `cpus`, at most this executor's cores."""
        return max(1, min(resources.cpus, self.cores))

    @abstractmethod
    def submit(self, job: Job, resources: Resources) -> Any:
        """Start (or queue) a job; returns a handle."""

    @abstractmethod
    def wait(self) -> list[tuple[Any, Outcome]]:
        """Block until at least one submitted job finished; return (handle, outcome) pairs."""

    def shutdown(self, interrupted: bool = False) -> None:
        pass


class SerialExecutor(Executor):
    name = "serial"

    def __init__(self, threads: int | None = None):
        self.threads = self.cores = threads or cpu_count()
        self._queue: list[tuple[int, Job]] = []
        self._next = 0

    def submit(self, job: Job, resources: Resources) -> int:
        self._next += 1
        self._queue.append((self._next, job))
        return self._next

    def wait(self) -> list[tuple[Any, Outcome]]:
        handle, job = self._queue.pop(0)
        return [(handle, execute_job(job))]


def _worker_init(threads: int, parent_pid: int) -> None:
    # Before any stage imports torch/numpy: keep BLAS pools to this job's share of the cores.
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[name] = str(threads)
    # A SIGTERM sent to the whole process group (a job scheduler, `kill -TERM -PGID`) unwinds the step
    # like Ctrl-C does (lease released, checkpoints kept). A stage that imports a native library which
    # takes SIGTERM over (glog in pycolmap, unless imported through a helper that gives SIGTERM back)
    # loses this, which is why the runner itself uses SIGINT.
    signal.signal(signal.SIGTERM, _terminate_as_interrupt)
    exit_with_parent(parent_pid)


def _terminate_as_interrupt(signum, frame):
    raise KeyboardInterrupt("SIGTERM")          # the runner words its record and exit status by this


# Linux prctl option: the kernel sends the given signal to this process when its parent dies.
PR_SET_PDEATHSIG = 1


def exit_with_parent(parent_pid: int, poll_s: float = 1.0) -> None:
    """Make this worker die when the runner does (even by SIGKILL), instead of computing on as an orphan.
    SIGKILL is safe here: checkpoints are renamed into place whole, results are published by one rename,
    and the lease of a dead process is recognised as stale. Linux: prctl(PR_SET_PDEATHSIG); elsewhere a
    daemon thread polls the parent pid."""
    if sys.platform.startswith("linux"):
        import ctypes

        try:
            libc = ctypes.CDLL(None, use_errno=True)
            armed = libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
        except (OSError, AttributeError):
            armed = False
        if armed:
            if os.getppid() != parent_pid:          # the parent died before prctl took effect
                os.kill(os.getpid(), signal.SIGKILL)
            return
    import threading

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(poll_s)
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


# After Ctrl-C, how long workers get to unwind from the terminal's own SIGINT before the runner sends
# them one (needed when only the runner was signalled, e.g. `kill -INT`).
INTERRUPT_GRACE_S = 1.0


class ProcessPoolExecutor(Executor):
    name = "process"

    def __init__(self, jobs: int):
        import concurrent.futures
        import multiprocessing

        self.slots = max(1, jobs)
        self.cores = cpu_count()
        self.threads = max(1, self.cores // self.slots)
        # Workers start with every core's BLAS threads; each job then sets its own (threads_for).
        self._new_pool = lambda: concurrent.futures.ProcessPoolExecutor(
            max_workers=self.slots, mp_context=multiprocessing.get_context("spawn"),
            initializer=_worker_init, initargs=(cpu_count(), os.getpid()))
        self._pool = self._new_pool()
        self._futures: set = set()

    def submit(self, job: Job, resources: Resources):
        from concurrent.futures.process import BrokenProcessPool

        try:
            future = self._pool.submit(execute_job, job)
        except BrokenProcessPool:
            # A worker was killed (SIGKILL, out of memory): the steps it and its siblings were running
            # are reported failed; later steps get a fresh pool.
            self._pool.shutdown(wait=False)
            self._pool = self._new_pool()
            future = self._pool.submit(execute_job, job)
        self._futures.add(future)
        return future

    def wait(self) -> list[tuple[Any, Outcome]]:
        import concurrent.futures

        done, _ = concurrent.futures.wait(self._futures, return_when=concurrent.futures.FIRST_COMPLETED)
        out = []
        for future in done:
            self._futures.discard(future)
            out.append((future, _outcome_of(future.result)))
        return out

    def shutdown(self, interrupted: bool = False) -> None:
        if interrupted:
            import concurrent.futures

            # SIGINT, not SIGTERM: native libraries (glog via pycolmap) take over SIGTERM and abort
            # without unwinding; SIGINT reaches Python as KeyboardInterrupt, so leases are released
            # and temp output removed.
            concurrent.futures.wait(self._futures, timeout=INTERRUPT_GRACE_S)
            if not all(f.done() for f in self._futures):
                for process in list(getattr(self._pool, "_processes", {}).values()):
                    if process.is_alive():
                        os.kill(process.pid, signal.SIGINT)
        self._pool.shutdown(wait=True, cancel_futures=True)


def _outcome_of(get_result) -> Outcome:
    """A worker that died (killed, out of memory) is a failed step, not a crashed run."""
    try:
        return get_result()
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # noqa: BLE001
        return Outcome(key="?", status="failed",
                       error=f"worker process died while this step (or one running beside it) ran: "
                             f"{type(exc).__name__}: {exc}. Rerun to retry; checkpoints are kept.")


class RayExecutor(Executor):
    name = "ray"

    def __init__(self, address: str | None = None, max_retries: int = 1, num_cpus: int | None = None):
        try:
            import ray
        except ModuleNotFoundError:
            raise UserError("the ray executor needs the 'ray' package: pip install 'dualnerf-pipeline[ray]'.")
        self._ray = ray
        if not ray.is_initialized():
            if address:
                ray.init(address=address, include_dashboard=False, log_to_driver=True)
            else:
                ray.init(num_cpus=num_cpus or cpu_count(), include_dashboard=False)
        self.cluster_cpus = int(ray.cluster_resources().get("CPU", 1))
        self.slots = 1 << 16          # ray itself queues tasks by resources
        self.cores = 1 << 30          # ... and packs them onto nodes: the runner submits whatever is ready
        self.threads = 1
        self.max_retries = max_retries
        self._remote = ray.remote(_ray_execute)
        self._refs: dict = {}

    def threads_for(self, resources: Resources) -> int:
        # A stage asking for more CPUs than the cluster has would never be scheduled: clamp.
        return max(1, min(resources.cpus, self.cluster_cpus))

    def submit(self, job: Job, resources: Resources):
        cpus = self.threads_for(resources)
        job = dataclasses.replace(job, threads=cpus)
        ref = self._remote.options(num_cpus=cpus, num_gpus=resources.gpus,
                                   max_retries=self.max_retries).remote(job)
        self._refs[ref] = job
        return ref

    def wait(self) -> list[tuple[Any, Outcome]]:
        ready, _ = self._ray.wait(list(self._refs), num_returns=1)
        out = []
        for ref in ready:
            job = self._refs.pop(ref)
            outcome = _outcome_of(functools.partial(self._ray.get, ref))
            if outcome.key == "?":
                outcome = Outcome(job.key, "failed", error=outcome.error)
            out.append((ref, outcome))
        return out

    def shutdown(self, interrupted: bool = False) -> None:
        if interrupted:
            for ref in self._refs:
                self._ray.cancel(ref)


def _ray_execute(job: Job) -> Outcome:
    os.environ["OMP_NUM_THREADS"] = str(job.threads)
    return execute_job(job)


def make_executor(kind: str, *, jobs: int = 1, address: str | None = None) -> Executor:
    """'serial' | 'process' | 'ray' (the CLI's --executor). `jobs` sizes the process pool only."""
    if kind == "serial":
        return SerialExecutor()
    if kind == "process":
        return ProcessPoolExecutor(jobs)
    if kind == "ray":
        return RayExecutor(address=address)
    raise UserError(f"unknown executor '{kind}'; choose serial, process or ray.")
