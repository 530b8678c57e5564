"""run_steps: key the DAG, record the run, feed ready steps to an executor until all are settled.

A step whose upstream failed is `skipped`; independent steps keep going. Ctrl-C stops cleanly:
running steps are interrupted (their checkpoints stay in scratch, leases are released), the run
record says `interrupted`, and KeyboardInterrupt is re-raised for the CLI. Inside
`terminate_as_interrupt()` SIGTERM does the same (it raises `Terminated`, a KeyboardInterrupt).

With more than one step in flight, steps report progress as log lines every ~10% instead of tqdm
bars (several processes redrawing one terminal line overwrite each other).
"""
from __future__ import annotations

import dataclasses
import itertools
import os
import signal
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.dag import KeyedStep, Step, compute_keys, params_dict
from pipeline.engine import Job, Outcome
from pipeline.errors import UserError
from pipeline.executors import Executor
from pipeline.runrecord import RUN_FILE, RunRecord, safe_name
from pipeline.store import Store


class Terminated(KeyboardInterrupt):
    """SIGTERM turned into an exception in the main thread, so a run unwinds exactly as after Ctrl-C."""

    exit_status = 143           # 128 + SIGTERM, what shells report for a process killed by SIGTERM


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within this block (main thread only) SIGTERM raises `Terminated`. Without it Python dies on
    SIGTERM at once: no clean-up, and the process-pool workers would compute on as orphans."""
    def handler(signum, frame):
        # The clean-up (interrupting workers, saving the run record) must not be cut short by a second
        # SIGTERM; SIGKILL still ends everything, and workers follow their parent (executors.exit_with_parent).
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        raise Terminated("SIGTERM")

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextmanager
def _sigterm_ignored() -> Iterator[None]:
    """While interrupted steps are wound up: the SIGTERM that often follows the first interrupt (a
    group signal reaches the workers and the runner) must not cut the clean-up short."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def claim_run_dir(run_dir: Path) -> Path:
    """`run_dir`, or `run_dir-2`, `-3`... if another run already owns it (two runs started within the
    same second get the same timestamped name). Owning means having created its run.json (O_EXCL)."""
    run_dir = Path(run_dir)
    for n in itertools.count(1):
        candidate = run_dir if n == 1 else run_dir.with_name(f"{run_dir.name}-{n}")
        candidate.mkdir(parents=True, exist_ok=True)
        try:
            os.close(os.open(candidate / RUN_FILE, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        except FileExistsError:
            continue
        return candidate
    raise AssertionError("unreachable")


@dataclass(frozen=True)
class FailedStep:
    step: Step
    label: str
    key: str
    error: str
    user_error: bool
    log_path: Path
    skipped: bool = False      # not run because an upstream step failed


@dataclass
class RunResult:
    results: dict[Step, Path] = field(default_factory=dict)
    failed: list[FailedStep] = field(default_factory=list)
    status: dict[Step, str] = field(default_factory=dict)     # done / cached / failed / skipped
    run_file: Path | None = None

    @property
    def ok(self) -> bool:
        return not self.failed

    def summary(self) -> str:
        """Counts per status, then one line per failed step with its error and log file."""
        counts: dict[str, int] = {}
        for status in self.status.values():
            counts[status] = counts.get(status, 0) + 1
        lines = [", ".join(f"{n} {status}" for status, n in sorted(counts.items()))]
        for f in self.failed:
            if f.skipped:
                lines.append(f"  skipped {f.label}: an upstream step failed")
            else:
                lines.append(f"  FAILED {f.label}: {f.error} (log: {f.log_path})")
        if self.run_file is not None:
            lines.append(f"run record: {self.run_file}")
        return "\n".join(lines)

    def first_error(self) -> str | None:
        """One line naming the first step that failed (in execution order), its error and its log."""
        failed = [f for f in self.failed if not f.skipped]
        if not failed:
            return None
        first = failed[0]
        error = first.error.strip().splitlines()[-1] if first.error.strip() else "failed"
        more = f" ({len(failed) - 1} more failed)" if len(failed) > 1 else ""
        return f"first error: {first.label}: {error.rstrip('.')}{more}; full log: {first.log_path}"


def run_steps(steps: Sequence[Step], *, registry: Mapping[str, str], store: Store, executor: Executor,
              run_dir: Path, quiet: bool = False) -> RunResult:
    """Run `steps` (and everything upstream of them) and return where each result was published.
    Raises a UserError before anything runs if a step is invalid. Shuts the executor down at the end.
    The record goes to `run_dir` (or `run_dir-N` if another run owns that folder; see result.run_file)."""
    keyed = compute_keys(steps, registry=registry, store=store)
    run_dir = Path(run_dir).absolute()     # step logs are written where the step runs: no relative paths
    store.remove_orphan_tmp()           # what killed earlier runs left half-written
    record = RunRecord(claim_run_dir(run_dir), store.root)
    # Several steps at once: periodic log lines, not tqdm bars fighting over one terminal line.
    step_quiet = quiet or executor.slots > 1
    by_key: dict[str, list[KeyedStep]] = {}
    for k in keyed.values():
        by_key.setdefault(k.key, []).append(k)

    # One job per distinct key; its log is named after the first label that asked for it.
    jobs: dict[str, Job] = {}
    deps: dict[str, set[str]] = {}
    used_logs: set[str] = set()
    for key, group in by_key.items():
        first = group[0]
        log_name = safe_name(first.label)
        if log_name in used_logs:
            log_name = f"{log_name}-{key[:8]}"
        used_logs.add(log_name)
        log_path = record.logs / f"{log_name}.log"
        inputs = {name: str(store.object_path(keyed[up].key)) for name, up in first.upstream.items()}
        inputs.update({name: str(path) for name, path in first.external.items()})
        jobs[key] = Job(key=key, stage_ref=registry[first.step.stage],
                        params=params_dict(first.params), inputs=inputs, key_inputs=first.key_inputs,
                        label=first.label, log_path=str(log_path), cache_root=str(store.root),
                        threads=executor.threads, quiet=step_quiet, lease_ttl_s=store.lease_ttl_s)
        deps[key] = {keyed[up].key for up in first.upstream.values()}
        for k in group:
            described = {name: {"step": keyed[up].label, "key": keyed[up].key} for name, up in k.upstream.items()}
            described.update({name: {"external": str(path)} for name, path in k.external.items()})
            record.add_step(label=k.label, stage=k.stage_cls.name, key=key, inputs=described,
                            params=params_dict(k.params), log=log_path)
    record.save()
    store.register_run(record.path)

    state: dict[str, str] = {key: "pending" for key in jobs}
    outcomes: dict[str, Outcome] = {}
    in_flight: dict[object, str] = {}
    threads_of: dict[object, int] = {}
    busy = 0                                   # threads of the jobs in flight
    interrupted = False
    try:
        try:
            executor.prepare(store=store, run_dir=record.dir, jobs=[j for k, j in jobs.items() if not store.has(k)])
        except UserError as exc:
            record.data.update(status="failed", error=str(exc), finished=time.time())
            record.save()
            raise
        while True:
            changed = False
            runnable = []
            for key in jobs:
                if state[key] != "pending":
                    continue
                if any(state[d] in ("failed", "skipped") for d in deps[key]):
                    state[key], changed = "skipped", True
                    record.update_key(key, status="skipped", error="an upstream step failed")
                elif all(state[d] in ("done", "cached") for d in deps[key]):
                    changed = True
                    cached = store.lookup(key)    # cheap path: no worker round trip for cached steps
                    if cached is not None:
                        state[key] = "cached"
                        outcomes[key] = Outcome(key, "cached", str(cached))
                        record.update_key(key, status="cached")
                    else:
                        runnable.append(key)
            # A job runs on its stage's CPU hint (at most the executor's cores): the same thread count
            # however the steps happen to be scheduled, so a result does not depend on what ran beside
            # it (float sums differ between thread counts). Jobs start while their hints fit the cores.
            for key in runnable:
                resources = by_key[key][0].stage_cls.resources_for(by_key[key][0].params)
                threads = executor.threads_for(resources)
                if len(in_flight) >= executor.slots or (in_flight and busy + threads > executor.cores):
                    break
                state[key] = "running"
                record.update_key(key, status="running", started=time.time())
                handle = executor.submit(dataclasses.replace(jobs[key], threads=threads), resources)
                in_flight[handle] = key
                busy += threads
                threads_of[handle] = threads
            if changed:
                record.save()
            if not in_flight:
                if not any(s == "pending" for s in state.values()):
                    break
                if not changed:
                    raise RuntimeError(f"scheduler stalled with pending steps: {state}")
                continue
            for handle, outcome in executor.wait():
                key = in_flight.pop(handle)
                busy -= threads_of.pop(handle)
                outcomes[key] = outcome
                state[key] = outcome.status
                record.update_key(key, status=outcome.status, error=outcome.error,
                                  user_error=outcome.user_error, finished=outcome.finished or time.time(),
                                  duration_s=round(outcome.duration_s, 3))
            record.save()
    except KeyboardInterrupt as exc:
        interrupted = True
        # A worker's KeyboardInterrupt("SIGTERM") (executors._terminate_as_interrupt) can arrive before
        # the runner's own: a signal to the process group reaches everyone.
        why = "SIGTERM" if exc.args[:1] == ("SIGTERM",) else "Ctrl-C"
        with _sigterm_ignored():
            executor.shutdown(interrupted=True)
            for key in in_flight.values():
                record.update_key(key, status="interrupted", error=f"interrupted ({why}); rerun to resume")
            record.data.update(status="interrupted", finished=time.time())
            record.save()
        if why == "SIGTERM" and not isinstance(exc, Terminated):
            raise Terminated("SIGTERM") from None
        raise
    finally:
        if not interrupted:
            executor.shutdown()

    result = RunResult(run_file=record.path)
    for step, k in keyed.items():
        status = state[k.key]
        result.status[step] = status
        if status in ("done", "cached"):
            result.results[step] = Path(outcomes[k.key].path)
        else:
            outcome = outcomes.get(k.key)
            result.failed.append(FailedStep(
                step=step, label=k.label, key=k.key, skipped=status == "skipped",
                error=outcome.error if outcome else "skipped: an upstream step failed",
                user_error=bool(outcome and outcome.user_error), log_path=Path(jobs[k.key].log_path)))
    record.data.update(status="failed" if result.failed else "done", finished=time.time())
    record.save()
    return result
