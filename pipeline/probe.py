"""The Ray executor's start-up probe: before any step runs, every node that can run steps is asked, by a task
pinned to it, whether it

- sees the cache at the driver's absolute path, and it is the same folder (a probe file with a random
  token, written there by the driver a moment before, must be readable), and can write to it;
- sees the run's folder the same way (a remote step writes its log there) and can write to it;
- runs the environment the run's keys were computed for: for one step of each distinct (stage,
  environment) among the steps to compute, the node runs the worker's own check
  (pipeline.engine.environment_problems: the stage's version, its packages' versions, its device and
  its runtime_environment, e.g. the numerical code paths the CPU takes), the check every step repeats
  before computing. Ray itself refuses a node with another Ray or Python version;
- has a clock close to the driver's (measured with a second, warm round trip: offset +- half the round
  trip). Nothing in the cache depends on clocks any more (leases are judged by heartbeat counters), but
  run records, logs and manifests carry wall-clock times, and an offset above a minute means a host
  without time synchronisation: above CLOCK_WARN_S the run warns, above CLOCK_STOP_S it stops.

A problem stops the run before anything is computed, with one paragraph per node naming it, what is
wrong and what to do. Only plain data crosses to the nodes.
"""
from __future__ import annotations

import json
import os
import socket
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.errors import UserError

CLOCK_WARN_S = 2.0
CLOCK_STOP_S = 60.0
PROBE_TIMEOUT_S = 120.0
PROBE_FOLDER = "probes"          # under the cache root; emptied after each probe
GUIDE = "docs/cluster.md"


class ClusterProbeError(UserError):
    pass


# ---- on the node ----------------------------------------------------------------------------------------
def check_folder(folder: str, token: str, what: str) -> list[str]:
    """Problems with `folder` as this process sees it: missing, not the driver's (no probe file with
    `token`), not writable."""
    path = Path(folder)
    if not path.is_dir():
        return [f"the {what} folder {path} does not exist here"]
    marker = path / f".probe-{token}" if what == "runs" else path / PROBE_FOLDER / token
    try:
        seen = json.loads(marker.read_text(encoding="utf-8")).get("token")
    except (OSError, ValueError):
        seen = None
    problems = []
    if seen != token:
        problems.append(f"the {what} folder {path} exists here but is not the driver's: the probe file the "
                        f"driver had just written there is missing (a different disk mounted at the same path?)")
    trial = marker.parent / f".write-test-{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
    try:
        trial.write_text("ok", encoding="utf-8")
        trial.unlink()
    except OSError as exc:
        problems.append(f"the {what} folder {path} is not writable here ({exc.strerror or exc})")
    return problems


def check_environment(jobs: Sequence[Any]) -> list[str]:
    """Problems of this process's environment for `jobs` (pipeline.engine.Job): the engine's own check,
    one line per distinct set of differences, naming the steps that have it."""
    from pipeline.engine import environment_problems

    found: dict[tuple[str, ...], list[str]] = {}
    for job in jobs:
        try:
            differences = environment_problems(job)
        except Exception as exc:  # noqa: BLE001 - a stage that cannot even load here is the node's problem
            differences = [f"the stage cannot be loaded here ({type(exc).__name__}: {exc})"]
        if differences:
            found.setdefault(tuple(differences), []).append(f"'{job.label}'")
    return [f"its environment differs from the one step{'s' if len(labels) > 1 else ''} {', '.join(labels)} "
            f"{'were' if len(labels) > 1 else 'was'} keyed for: " + "; ".join(differences)
            for differences, labels in found.items()]


def probe_here(cache_root: str, run_dir: str, token: str, jobs: list[Any]) -> dict[str, Any]:
    """Runs on a node (as a Ray task pinned to it)."""
    import ray

    return {"node_id": ray.get_runtime_context().get_node_id(), "hostname": socket.gethostname(),
            "pid": os.getpid(),
            "problems": (check_folder(cache_root, token, "cache") + check_folder(run_dir, token, "runs")
                         + check_environment(jobs))}


def clock_here() -> float:
    return time.time()


# ---- on the driver ----------------------------------------------------------------------------------------
@dataclass
class NodeProbe:
    node_id: str
    address: str
    hostname: str = "?"
    problems: list[str] = field(default_factory=list)
    offset_s: float | None = None         # node clock - driver clock
    uncertainty_s: float | None = None

    @property
    def name(self) -> str:
        return f"{self.address} (host {self.hostname}, Ray node {self.node_id[:8]})"


def step_nodes(ray) -> list[dict[str, Any]]:
    """The alive nodes that can run steps (they advertise CPUs or GPUs; a head started with --num-cpus=0
    only schedules)."""
    return [n for n in ray.nodes() if n.get("Alive") and
            (n.get("Resources", {}).get("CPU", 0) > 0 or n.get("Resources", {}).get("GPU", 0) > 0)]


def environment_samples(jobs: Sequence[Any]) -> list[Any]:
    """One job per distinct (stage, version and environment its key was computed for): checking it checks
    every job like it."""
    seen, out = set(), []
    for job in jobs:
        what = (job.stage_ref, json.dumps({"version": job.key_inputs.get("version"),
                                           "environment": job.key_inputs.get("environment", {})}, sort_keys=True))
        if what not in seen:
            seen.add(what)
            out.append(job)
    return out


def probe_cluster(ray, *, cache_root: Path, run_dir: Path, jobs: Sequence[Any],
                  timeout_s: float = PROBE_TIMEOUT_S) -> list[NodeProbe]:
    """Probe every step node for the `jobs` (pipeline.engine.Job) the run is about to compute; raise
    ClusterProbeError (one paragraph per node) if any node cannot run them. Returns the reports (with
    clock offsets) otherwise."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    nodes = step_nodes(ray)
    if not nodes:
        raise ClusterProbeError(
            "the Ray cluster has no node that can run steps (no node advertises CPUs or GPUs; a head started "
            "with --num-cpus=0 only schedules): start worker nodes with `ray start --address=HEAD:PORT` "
            f"(see {GUIDE}), then rerun.")
    token = uuid.uuid4().hex
    samples = environment_samples(jobs)
    markers = [Path(cache_root) / PROBE_FOLDER / token, Path(run_dir) / f".probe-{token}"]
    for marker in markers:
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.write_text(json.dumps({"token": token, "host": socket.gethostname(), "time": time.time()}),
                          encoding="utf-8")
    reports = {n["NodeID"]: NodeProbe(n["NodeID"], n.get("NodeManagerAddress", "?"), n.get("NodeManagerHostname", "?"))
               for n in nodes}
    try:
        def pinned(function, node_id):
            return ray.remote(function).options(
                num_cpus=0, max_retries=0,
                scheduling_strategy=NodeAffinitySchedulingStrategy(node_id=node_id, soft=False))

        refs = {pinned(probe_here, node_id).remote(str(cache_root), str(run_dir), token, samples): node_id
                for node_id in reports}
        ready, pending = ray.wait(list(refs), num_returns=len(refs), timeout=timeout_s)
        for ref in pending:
            reports[refs[ref]].problems.append(f"did not answer the start-up probe within {timeout_s:.0f} s")
            ray.cancel(ref, force=True)
        answered = []
        for ref in ready:
            report = reports[refs[ref]]
            try:
                answer = ray.get(ref)
            except Exception as exc:  # noqa: BLE001 - an answer we cannot read is the node's problem
                report.problems.append(f"the start-up probe failed there: {type(exc).__name__}: "
                                       f"{str(exc).strip().splitlines()[-1] if str(exc).strip() else ''}")
                continue
            answered.append(refs[ref])
            report.hostname = answer["hostname"]
            report.problems += answer["problems"]
        for node_id in answered:
            _measure_clock(ray, pinned(clock_here, node_id), reports[node_id])
    finally:
        for marker in markers:
            marker.unlink(missing_ok=True)
    failed = [r for r in reports.values() if r.problems]
    if failed:
        raise ClusterProbeError(probe_message(failed, len(reports), Path(cache_root), Path(run_dir)))
    return list(reports.values())


def _measure_clock(ray, remote, report: NodeProbe, rounds: int = 3) -> None:
    """Offset of the node's wall clock from the driver's, from the fastest of a few round trips (a warm
    worker answers in milliseconds): offset = node time - midpoint, +- half the round trip."""
    best = None
    for _ in range(rounds):
        sent = time.time()
        node_time = ray.get(remote.remote())
        received = time.time()
        if best is None or received - sent < best[1]:
            best = (node_time - (sent + received) / 2, received - sent)
    report.offset_s, report.uncertainty_s = best[0], best[1] / 2
    at_least = abs(report.offset_s) - report.uncertainty_s
    if at_least > CLOCK_STOP_S:
        report.problems.append(
            f"its clock is {report.offset_s:+.1f} s (+-{report.uncertainty_s:.2f} s) off the driver's, more than "
            f"{CLOCK_STOP_S:.0f} s: results do not depend on clocks, but run records, logs and manifests "
            f"do, and an offset this large means the host has no time synchronisation")


def probe_message(failed: list[NodeProbe], total: int, cache_root: Path, run_dir: Path) -> str:
    paragraphs = [(f"the start-up probe found {len(failed)} of the Ray cluster's {total} step node(s) unable "
                   f"to run this run's steps; nothing was run.")]
    for report in failed:
        fixes = []
        text = " ".join(report.problems)
        if "cache folder" in text:
            fixes.append(f"every node must see the cache at the same absolute path ({cache_root}) on one shared "
                         f"file system, writable by the user running Ray there")
        if "runs folder" in text:
            fixes.append(f"step logs are written by the node that runs the step: put --runs on the shared file "
                         f"system too (this run's folder is {run_dir})")
        if "environment" in text:
            fixes.append("install the same code and packages on every node (`pip install -e '.[ray]'` from the "
                         "same checkout) and restart Ray there (`ray stop`, then the node's `ray start`)")
        if "clock" in text:
            fixes.append("synchronise the node's clock (NTP / chrony)")
        if "did not answer" in text or "failed there" in text:
            fixes.append("check that the node is healthy (`ray status`, its logs under the Ray temp folder)")
        paragraphs.append(f"Node {report.name}: " + "; ".join(report.problems) + ". What to do: "
                          + "; ".join(fixes) + f" (see {GUIDE}).")
    return "\n".join(paragraphs)


def clock_summary(reports: list[NodeProbe]) -> str:
    offsets = [r for r in reports if r.offset_s is not None]
    if not offsets:
        return ""
    worst = max(offsets, key=lambda r: abs(r.offset_s))
    return f"largest clock offset {worst.offset_s:+.3f} s (+-{worst.uncertainty_s:.3f} s) on {worst.name}"
