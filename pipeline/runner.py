"""run_steps: key the DAG, record the run, feed ready steps to an executor until all are settled.

A step whose upstream failed is `skipped`; independent steps keep going. Ctrl-C stops cleanly:
running steps are interrupted (their checkpoints stay in scratch, leases are released), the run
record says `interrupted`, and KeyboardInterrupt is re-raised for the CLI.
"""
from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.dag import KeyedStep, Step, compute_keys, params_dict
from pipeline.engine import Job, Outcome
from pipeline.executors import Executor
from pipeline.runrecord import RunRecord, safe_name
from pipeline.store import Store


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


def run_steps(steps: Sequence[Step], *, registry: Mapping[str, str], store: Store, executor: Executor,
              run_dir: Path, quiet: bool = False) -> RunResult:
    """Run `steps` (and everything upstream of them) and return where each result was published.
    Raises a UserError before anything runs if a step is invalid. Shuts the executor down at the end."""
    keyed = compute_keys(steps, registry=registry, store=store)
    record = RunRecord(run_dir, store.root)
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
                        threads=executor.threads, quiet=quiet, lease_ttl_s=store.lease_ttl_s)
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
    interrupted = False
    try:
        while True:
            changed = False
            for key, job in jobs.items():
                if len(in_flight) >= executor.slots:
                    break
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
                        continue
                    state[key] = "running"
                    record.update_key(key, status="running", started=time.time())
                    handle = executor.submit(job, by_key[key][0].stage_cls.resources)
                    in_flight[handle] = key
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
                outcomes[key] = outcome
                state[key] = outcome.status
                record.update_key(key, status=outcome.status, error=outcome.error,
                                  user_error=outcome.user_error, finished=outcome.finished or time.time(),
                                  duration_s=round(outcome.duration_s, 3))
            record.save()
    except KeyboardInterrupt:
        interrupted = True
        executor.shutdown(interrupted=True)
        for key in in_flight.values():
            record.update_key(key, status="interrupted", error="interrupted (Ctrl-C); rerun to resume")
        record.data.update(status="interrupted", finished=time.time())
        record.save()
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
