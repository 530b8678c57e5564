"""Executors run `Job`s and report `Outcome`s; the runner (pipeline.runner) decides what is ready.

    SerialExecutor()                 in this process, one at a time (tests, debugging)
    ProcessPoolExecutor(jobs)        spawn-context worker processes, up to `jobs` at once while
                                     their threads fit the cores; each job gets its stage's
                                     CPU hint or its share of the cores (cores // jobs),
                                     whichever is larger (`jobs=1`: every step gets them all)
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

    def prepare(self, *, store, run_dir, jobs: list[Job]) -> None:
        """Called by the runner once, before any job is submitted, with the jobs it may submit (the Ray
        executor probes its nodes for them)."""

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

    def threads_for(self, resources: Resources) -> int:
        """The stage's hint, or this job's share of the cores when that is larger: with fewer jobs than
        cores a step uses what would otherwise sit idle. Safe because results do not depend on threads."""
        return max(1, min(max(resources.cpus, self.threads), self.cores))

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


GIB = 2 ** 30
# While nothing finishes, how often the Ray executor checks that every step in flight can still be placed
# on a live node (a step whose only large-enough node died would otherwise wait forever).
STRANDED_CHECK_S = 10.0


class RayExecutor(Executor):
    """One Ray task per step, reserving the step's hints on one node (num_cpus, num_gpus, memory in bytes),
    retried once by Ray if its node dies (the retry resumes from the step's checkpoints in the shared cache).
    With `address` it joins that cluster and runs the start-up probe (pipeline.probe) before any step;
    without, it starts a local instance on this machine."""

    name = "ray"

    def __init__(self, address: str | None = None, max_retries: int = 1, num_cpus: int | None = None,
                 probe: bool | None = None):
        try:
            import ray
        except ModuleNotFoundError:
            raise UserError("the ray executor needs the 'ray' package: pip install 'dualnerf-pipeline[ray]'.")
        self._ray = ray
        self.local = not address
        if not ray.is_initialized():
            if address:
                _join_cluster(ray, address)
            else:
                # "local": a new instance even when a cluster started by `ray start` runs on this machine.
                ray.init(address="local", num_cpus=num_cpus or cpu_count(), include_dashboard=False)
        self.probe = (not self.local) if probe is None else probe
        self.slots = 1 << 16          # ray itself queues tasks by resources
        self.cores = 1 << 30          # ... and packs them onto nodes: the runner submits whatever is ready
        self.threads = 1
        self.max_retries = max_retries
        self.probe_reports: list = []
        self._remote = ray.remote(_ray_execute)
        self._refs: dict = {}
        self._requests: dict = {}
        self._refused: list[tuple[Any, Outcome]] = []

    def nodes(self) -> list[dict[str, Any]]:
        from pipeline.probe import step_nodes

        return step_nodes(self._ray)

    def threads_for(self, resources: Resources) -> int:
        if self.local:
            # One machine: like the process pool, a hint above its cores runs on all of them.
            largest = max((n["Resources"].get("CPU", 0) for n in self.nodes()), default=1)
            return max(1, min(resources.cpus, int(largest)))
        return max(1, resources.cpus)     # a cluster: a request no node can hold fails at once (submit)

    def prepare(self, *, store, run_dir, jobs: list[Job]) -> None:
        if not self.probe:
            return
        from pipeline.probe import CLOCK_WARN_S, clock_summary, probe_cluster

        started = time.perf_counter()
        self.probe_reports = probe_cluster(self._ray, cache_root=store.root, run_dir=run_dir,
                                           jobs=jobs)
        for report in self.probe_reports:
            if report.offset_s is not None and abs(report.offset_s) - report.uncertainty_s > CLOCK_WARN_S:
                print(f"cluster: warning: the clock of node {report.name} is {report.offset_s:+.1f} s off the "
                      f"driver's; synchronise it (NTP / chrony): run records and logs carry wall-clock times",
                      file=sys.stderr)
        print(f"cluster: {len(self.probe_reports)} step node(s) checked in {time.perf_counter() - started:.1f} s: "
              f"same cache and runs folder, same environment; {clock_summary(self.probe_reports)}", file=sys.stderr)

    def submit(self, job: Job, resources: Resources):
        cpus = self.threads_for(resources)
        job = dataclasses.replace(job, threads=cpus)
        request = {"CPU": float(cpus), "GPU": float(resources.gpus), "memory": float(int(resources.memory_gb * GIB))}
        problem = self._unplaceable(job, request)
        if problem:
            handle = ("refused", job.key)
            self._refused.append((handle, Outcome(job.key, "failed", error=problem, user_error=True,
                                                  started=time.time(), finished=time.time())))
            return handle
        options = {"num_cpus": cpus, "max_retries": self.max_retries}
        if resources.gpus > 0:
            options["num_gpus"] = resources.gpus
        if request["memory"] > 0:
            options["memory"] = int(request["memory"])
        ref = self._remote.options(**options).remote(job)
        self._refs[ref] = job
        self._requests[ref] = request
        return ref

    def _unplaceable(self, job: Job, request: dict[str, float]) -> str | None:
        """Why no live node can ever hold `request` (None if one can): named stage, request, largest node."""
        nodes = self.nodes()

        def fits(node) -> list[bool]:
            have = node.get("Resources", {})
            return [have.get(name, 0.0) >= amount for name, amount in request.items() if amount > 0]

        if any(all(fits(n)) for n in nodes):
            return None
        stage = job.stage_ref.rpartition(":")[2]
        try:
            from pipeline.registry import load_ref

            stage = load_ref(job.stage_ref).name
        except (ImportError, AttributeError, TypeError):
            pass
        asked = (f"{int(request['CPU'])} CPU(s), {request['GPU']:g} GPU(s), "
                 f"{request['memory'] / GIB:.1f} GiB memory")
        if nodes:
            largest = max(nodes, key=lambda n: (sum(fits(n)), n["Resources"].get("GPU", 0),
                                                n["Resources"].get("CPU", 0), n["Resources"].get("memory", 0)))
            have = largest["Resources"]
            where = (f"the largest node, {largest.get('NodeManagerAddress', '?')} (Ray node {largest['NodeID'][:8]}), "
                     f"has {int(have.get('CPU', 0))} CPU(s), {have.get('GPU', 0):g} GPU(s), "
                     f"{have.get('memory', 0) / GIB:.1f} GiB memory")
        else:
            where = "the cluster has no live node with CPUs or GPUs"
        return (f"step '{job.label}' (stage {stage}) asks for {asked} on one node, and no node of the Ray "
                f"cluster has that much ({where}), so it could never start. Add a node that large, or lower "
                f"the step's request (e.g. --set {stage}.device=cpu, --set {stage}.num_threads=N).")

    def wait(self) -> list[tuple[Any, Outcome]]:
        if self._refused:
            return [self._refused.pop(0)]
        while True:
            ready, _ = self._ray.wait(list(self._refs), num_returns=1, timeout=STRANDED_CHECK_S)
            if ready:
                break
            stranded = self._stranded()
            if stranded:
                return stranded
        out = []
        for ref in ready:
            job = self._refs.pop(ref)
            self._requests.pop(ref, None)
            outcome = _outcome_of(functools.partial(self._ray.get, ref))
            if outcome.key == "?":
                outcome = Outcome(job.key, "failed", error=outcome.error)
            out.append((ref, outcome))
        return out

    def _stranded(self) -> list[tuple[Any, Outcome]]:
        """Steps in flight that no live node can hold any more (their node died, and no other is large
        enough): cancelled and failed, instead of waiting forever."""
        out = []
        for ref, job in list(self._refs.items()):
            problem = self._unplaceable(job, self._requests[ref])
            if problem:
                self._ray.cancel(ref, force=True)
                del self._refs[ref], self._requests[ref]
                out.append((ref, Outcome(job.key, "failed", error=problem, user_error=True, finished=time.time())))
        return out

    def shutdown(self, interrupted: bool = False) -> None:
        if interrupted:
            for ref in self._refs:
                self._ray.cancel(ref)


def _join_cluster(ray, address: str) -> None:
    """ray.init(address), with the cluster's token authentication spelled out when it refuses us."""
    try:
        ray.init(address=address, include_dashboard=False, log_to_driver=True)
    except Exception as exc:            # reworded below when it is the authentication
        text = str(exc)
        if "InvalidAuthToken" in text or "uthentication" in text:
            raise UserError(
                f"the Ray cluster at {address} refused this driver: it uses token authentication (Ray 2.60 "
                f"turns it on at the head when a token exists). Set RAY_AUTH_MODE=token and give the "
                f"cluster's token (RAY_AUTH_TOKEN_PATH=FILE, RAY_AUTH_TOKEN=..., or ~/.ray/auth_token) here, "
                f"as on every node (see docs/cluster.md). Ray said: {text.strip().splitlines()[0]}") from None
        raise


def _ray_execute(job: Job) -> Outcome:
    import ray

    os.environ["OMP_NUM_THREADS"] = str(job.threads)
    context = ray.get_runtime_context()
    placement = {"executor": "ray", "node_id": context.get_node_id(), "node_ip": ray.util.get_node_ip_address(),
                 "assigned": context.get_assigned_resources(), "gpu_ids": [str(g) for g in ray.get_gpu_ids()],
                 "cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES")}
    return execute_job(job, placement=placement)


def make_executor(kind: str, *, jobs: int = 1, address: str | None = None) -> Executor:
    """'serial' | 'process' | 'ray' (the CLI's --executor). `jobs` sizes the process pool only."""
    if kind == "serial":
        return SerialExecutor()
    if kind == "process":
        return ProcessPoolExecutor(jobs)
    if kind == "ray":
        return RayExecutor(address=address)
    raise UserError(f"unknown executor '{kind}'; choose serial, process or ray.")
