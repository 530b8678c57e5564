"""How long a workflow takes on N nodes of C cores, by simulating the scheduler, against its DAG's critical path.

    python -m benchmarks.simulate_cluster                          # workflows/comparison.toml, full-scale costs
    python -m benchmarks.simulate_cluster --run RUNS/.../run.json  # a finished run: its DAG and the durations
                                                                   # its manifests recorded, vs what it took

The model is the engine's: the runner submits every step whose inputs exist, in DAG order; Ray starts a
submitted step on the first node with enough free CPUs for the step's hint (`Stage.resources_for`), skipping
over steps that do not fit yet (no head-of-line blocking); a step holds its CPUs for its duration. Not
modelled: Ray's start-up and placement latency (~0.1-1 s per step), the per-run probe (~1-10 s), slowdown
of steps sharing a node's memory bandwidth, and the driver's keying and report (seconds).

Per-step costs at full scale (the 2800-iteration CPU preset, `--costs readme`) are the stage times the
README measured in the campsite ablation runs on this 2-core host (a quiet day; steps side by side on one
thread each, the fit on two): scene 17 s, SfM 15 s, fit 110 s (2 CPUs), DualNeRF edit 455 s, IN2N edit 355 s,
their evaluations 19 / 12 s, the original evaluation 12 s, gtviews 132 s ("~2.2 min per scene edit"), and
per-frame 45 s (the README says "well under a minute": an assumption, not a measurement). All scenes are
given campsite's costs (bear and portrait render at similar sizes).
"""
from __future__ import annotations

import argparse
import heapq
import json
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Seconds per step at the full-scale CPU preset (see the module docstring for where each comes from).
README_COSTS = {"scene": 17.0, "preprocess": 15.0, "fit": 110.0, "gtviews": 132.0, "perframe": 45.0,
                "edit:dual": 455.0, "edit:single": 355.0,
                "evaluate:original": 12.0, "evaluate:dual": 19.0, "evaluate:single": 12.0, "evaluate:perframe": 12.0}


@dataclass
class SimStep:
    key: str
    label: str
    stage: str
    cpus: int
    duration_s: float
    upstream: list[str] = field(default_factory=list)


def _cost_class(stage: str, params: dict, upstream: dict) -> str:
    if stage == "edit":
        return "edit:dual" if params.get("dual_field") else "edit:single"
    if stage == "evaluate":
        if "perframe" in upstream:
            return "evaluate:perframe"
        if "edit" not in upstream:
            return "evaluate:original"
        return "evaluate:dual" if upstream["edit"].get("dual", False) else "evaluate:single"
    return stage


def workflow_steps(workflow: str, overrides: list[str]) -> list[SimStep]:
    """The workflow's DAG (one step per key, as the runner runs it) with README costs."""
    from experiments.workflow import load_workflow
    from pipeline.dag import compute_keys, params_dict
    from pipeline.store import Store
    from stages import STAGES

    loaded = load_workflow(workflow, overrides)
    with tempfile.TemporaryDirectory() as cache:
        keyed = compute_keys(loaded.steps, registry=STAGES, store=Store(cache))
    out: dict[str, SimStep] = {}
    for k in keyed.values():
        if k.key in out:
            continue
        params = params_dict(k.params)
        upstream = {name: keyed[up] for name, up in k.upstream.items()}
        dual = {name: {"dual": bool(getattr(u.params, "dual_field", False))} for name, u in upstream.items()}
        cost = README_COSTS[_cost_class(k.stage_cls.name, params, dual)]
        out[k.key] = SimStep(k.key, k.label, k.stage_cls.name, k.stage_cls.resources_for(k.params).cpus, cost,
                             [u.key for u in upstream.values()])
    return list(out.values())


def run_steps_from_record(run_file: Path) -> tuple[list[SimStep], float]:
    """A finished run's DAG and the durations its manifests recorded; and the run's measured wall time."""
    from pipeline.registry import load_stage
    from pipeline.stage import build_params
    from stages import STAGES

    record = json.loads(Path(run_file).read_text())
    cache = Path(record["cache"])
    out: dict[str, SimStep] = {}
    for step in record["steps"]:
        key = step["key"]
        manifest = json.loads((cache / "objects" / key[:2] / key / "manifest.json").read_text())
        stage_cls = load_stage(STAGES, manifest["stage"])
        params = build_params(stage_cls.Params, manifest["params"], step["label"])
        upstream = list(manifest["key_inputs"].get("upstream", {}).values())
        out[key] = SimStep(key, step["label"], stage_cls.name, stage_cls.resources_for(params).cpus,
                           float(manifest["duration_s"]), upstream)
    return list(out.values()), float(record["finished"] - record["started"])


def critical_path(steps: list[SimStep]) -> tuple[float, list[str]]:
    by_key = {s.key: s for s in steps}
    finish: dict[str, tuple[float, list[str]]] = {}

    def visit(key: str) -> tuple[float, list[str]]:
        if key not in finish:
            step = by_key[key]
            before = max((visit(u) for u in step.upstream if u in by_key), default=(0.0, []), key=lambda f: f[0])
            finish[key] = (before[0] + step.duration_s, [*before[1], step.label])
        return finish[key]

    return max((visit(s.key) for s in steps), key=lambda f: f[0])


def simulate(steps: list[SimStep], nodes: int, cores: int) -> float:
    """Makespan of list scheduling as described in the module docstring."""
    by_key = {s.key: s for s in steps}
    if any(s.cpus > cores for s in steps):
        raise ValueError(f"a step asks for more than {cores} CPUs: it could never start")
    order = {s.key: i for i, s in enumerate(steps)}                # DAG (submission) order
    waiting = {s.key: {u for u in s.upstream if u in by_key} for s in steps}
    free = [cores] * nodes
    queue = sorted((k for k, deps in waiting.items() if not deps), key=order.get)
    running: list[tuple[float, int, str, int]] = []            # (end, order, key, node)
    now, done = 0.0, 0
    while done < len(steps):
        still = []
        for key in queue:
            cpus = by_key[key].cpus
            node = next((n for n in range(nodes) if free[n] >= cpus), None)
            if node is None:
                still.append(key)
                continue
            free[node] -= cpus
            heapq.heappush(running, (now + by_key[key].duration_s, order[key], key, node))
        queue = still
        now, _, key, node = heapq.heappop(running)
        free[node] += by_key[key].cpus
        done += 1
        for other, deps in waiting.items():
            if key in deps:
                deps.discard(key)
                if not deps:
                    queue.append(other)
        queue.sort(key=order.get)
    return now


def table(steps: list[SimStep], node_counts: list[int], cores: list[int]) -> str:
    path, chain = critical_path(steps)
    work = sum(s.duration_s * s.cpus for s in steps)
    lines = [(f"{len(steps)} steps, {work / 3600:.2f} core-hours of work; critical path {fmt(path)} "
             f"({' -> '.join(chain)})"), "",
             "| nodes x cores | simulated makespan | lower bound max(path, work/cores) | makespan / critical path |",
             "|---|---|---|---|"]
    for c in cores:
        for n in node_counts:
            makespan = simulate(steps, n, c)
            bound = max(path, work / (n * c))
            lines.append(f"| {n} x {c} | {fmt(makespan)} | {fmt(bound)} | {makespan / path:.2f} |")
    return "\n".join(lines)


def fmt(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.2f} h"
    if seconds >= 120:
        return f"{seconds / 60:.1f} min"
    return f"{seconds:.1f} s"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.simulate_cluster", description=__doc__.split("\n")[0])
    parser.add_argument("--workflow", default=str(ROOT / "workflows" / "comparison.toml"))
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--run", type=Path, help="a finished run's run.json: simulate its DAG with the "
                                                 "durations its manifests recorded")
    parser.add_argument("--nodes", default="1,4,16,64")
    parser.add_argument("--cores", default="2,8")
    args = parser.parse_args(argv)
    nodes = [int(n) for n in args.nodes.split(",")]
    cores = [int(c) for c in args.cores.split(",")]
    if args.run:
        steps, measured = run_steps_from_record(args.run)
        print(f"run {args.run}: measured wall time {fmt(measured)} (driver start to end, probe included)")
    else:
        steps = workflow_steps(args.workflow, args.overrides)
        print(f"{Path(args.workflow).name}, full-scale CPU preset, README stage costs")
    print(table(steps, nodes, cores))
    return 0


if __name__ == "__main__":
    sys.exit(main())
