"""`dualnerf run WORKFLOW`: expand the grid, compute every missing step once, then write the report.

Rerunning the same command after an interruption continues: finished steps come from the store,
interrupted ones resume from their newest in-stage checkpoint. `--force STAGE[,...]` recomputes the
steps of those stages and everything downstream of them: their cached results are moved aside to the
store's quarantine/ folder (`dualnerf cache gc` removes it), and the run computes them again.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "run", help="run a workflow grid (resumable; shared steps computed once)",
        description="Expand a workflow TOML into a DAG of stage steps, compute what the store lacks, and "
                    "write the report. Rerun the same command to continue after an interruption.")
    parser.add_argument("workflow", help="workflow TOML file, e.g. workflows/ablation.toml")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a workflow key (scene=, edit=, seeds=) or a stage parameter "
                             "(fit.iterations=500); repeatable")
    parser.add_argument("--dry-run", action="store_true",
                        help="print the DAG with each step's key and state (cached/partial/pending); run nothing")
    parser.add_argument("--executor", choices=["serial", "process", "ray"], default="process",
                        help="where steps run (default: a local process pool)")
    parser.add_argument("--jobs", type=int, default=None,
                        help="parallel steps for the process pool (default: one per core, as memory allows; "
                             "the cores are split among the steps running at once)")
    parser.add_argument("--ray-address", default=None,
                        help="Ray cluster to join (default: start a local Ray instance)")
    parser.add_argument("--out", type=Path, default=None, metavar="DIR",
                        help="report folder (default: the workflow's report_dir, e.g. reports/<scene>)")
    parser.add_argument("--reports", type=Path, dest="out", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    parser.add_argument("--no-report", action="store_true", help="skip the report at the end")
    parser.add_argument("--force", default=None, metavar="STAGE[,STAGE...]",
                        help="recompute the steps of these stages (e.g. --force edit,evaluate) and every step "
                             "downstream of them, although their results are cached")
    parser.set_defaults(handler=_run)


def default_jobs(steps) -> int:
    """One parallel step per core, as many as memory holds by the stages' hints. The pool starts steps
    while their stages' CPU hints fit the cores (fit: 2 threads, alone on 2 cores; edit and evaluate: 1
    each, two side by side: measured on 2 cores, 1.2x the throughput of one edit after the other on 2
    threads, since a step's Python work does not parallelise)."""
    from pipeline.executors import cpu_count
    from pipeline.registry import load_stage
    from stages import STAGES

    memory_gb = max(load_stage(STAGES, s.stage).resources.memory_gb for s in steps)
    try:
        total_gb = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2 ** 30
    except (ValueError, OSError, AttributeError):
        total_gb = memory_gb
    return max(1, min(cpu_count(), int(total_gb // max(memory_gb, 1e-9))))


def _run(args: argparse.Namespace) -> int:
    from experiments.cli import open_store
    from experiments.workflow import load_workflow
    from pipeline.dag import dry_run
    from pipeline.executors import make_executor
    from pipeline.paths import confined
    from pipeline.runner import run_steps
    from stages import STAGES

    workflow = load_workflow(args.workflow, args.overrides)
    store = open_store(args)
    _print_banner(workflow)
    forced = forced_keys(workflow, args.force, store) if args.force else set()
    if args.dry_run:
        rows = dry_run(workflow.steps, registry=STAGES, store=store)
        print_grid(workflow)
        print(f"steps ({len(rows)}, shared ones once):")
        width = max(len(label) for label, _, _ in rows)
        for label, key, state in rows:
            state = "cached, forced: recomputed" if state == "cached" and any(k.startswith(key) for k in forced) else state
            print(f"  {label.ljust(width)}  {key}  {state}")
        return 0
    if forced:
        moved = [key for key in sorted(forced) if store.object_path(key).is_dir()
                 and store.quarantine(key, [f"recomputed on request: dualnerf run --force {args.force}"])]
        print(f"force: {len(forced)} step(s) of {args.force} and downstream recompute; {len(moved)} cached "
              f"result(s) moved to {store.quarantine_dir}")

    jobs = args.jobs or default_jobs(workflow.steps)
    executor = make_executor(args.executor, jobs=jobs, address=args.ray_address)
    run_dir = confined(args.runs / f"{workflow.name}-{workflow.scene_name}" / time.strftime("%Y%m%d-%H%M%S"),
                       args.runs, "run folder")
    started = time.perf_counter()
    result = run_steps(workflow.steps, registry=STAGES, store=store, executor=executor, run_dir=run_dir,
                       quiet=args.quiet)
    elapsed = time.perf_counter() - started
    computed = sum(1 for s in result.status.values() if s == "done")
    print(f"run: {len(result.status)} steps ({computed} computed, "
          f"{sum(1 for s in result.status.values() if s == 'cached')} cached) in {elapsed:.1f} s; "
          f"record {result.run_file}")
    if result.failed:
        print("run: these steps did not finish:", file=sys.stderr)
        for failure in (f for f in result.failed if not f.skipped):
            print(f"  {failure.label}: {failure.error.splitlines()[-1]}\n    log: {failure.log_path}", file=sys.stderr)
        skipped = [f.label for f in result.failed if f.skipped]
        if skipped:
            print(f"  skipped, as an upstream step failed: {', '.join(skipped)}", file=sys.stderr)
    if not args.no_report:
        _write_report(workflow, store, args.out, partial=bool(result.failed))
    if result.first_error():
        print(f"run: {result.first_error()}", file=sys.stderr)     # the last line says what went wrong
    return 1 if result.failed else 0


class ForceError(ValueError):
    user_error = True


def forced_keys(workflow, stages_text: str, store) -> set[str]:
    """The keys of the steps of the named stages and of every step downstream of them."""
    from pipeline.dag import compute_keys
    from stages import STAGES

    names = [name.strip() for name in stages_text.split(",") if name.strip()]
    present = list(dict.fromkeys(step.stage for step in workflow.steps))
    unknown = [name for name in names if name not in present]
    if unknown or not names:
        raise ForceError(f"--force {stages_text!r}: {', '.join(unknown) or 'no stage'} names no stage of this "
                         f"workflow; its stages are {', '.join(present)} (e.g. --force edit,evaluate).")
    keyed = compute_keys(workflow.steps, registry=STAGES, store=store)     # upstream before downstream
    chosen: set = set()
    for step, k in keyed.items():
        if step.stage in names or any(up in chosen for up in k.upstream.values()):
            chosen.add(step)
    return {keyed[step].key for step in chosen}


def print_grid(workflow) -> None:
    """The grid's size per axis and every cell (one report row each)."""
    sizes = " x ".join(f"{n} {name}" for name, n in workflow.axes)
    print(f"grid: {len(workflow.cells)} cells ({sizes}; after filters, shared rows once):")
    for n, cell in enumerate(workflow.cells):
        print(f"  [{n}] {cell.describe()}")


def _print_banner(workflow) -> None:
    step = next((c.edit or c.perframe for c in reversed(workflow.cells) if (c.edit or c.perframe)), None)
    editor = step.params.get("editor", "synthetic") if step is not None else "-"
    encoder = workflow.cells[-1].evaluate.params.get("encoder", "proxy")
    edited = sum(1 for c in workflow.cells if not c.is_original)
    if len(workflow.scenes) <= 1 and len({c.edit_id for c in workflow.cells}) == 1:
        print(f"workflow {workflow.name}: scene '{workflow.scene_name}' ({workflow.scene_origin}), edit "
              f"'{workflow.edit_id}': \"{workflow.instruction}\"; {edited} edited cells + original")
    else:
        print(f"workflow {workflow.name}: {len(workflow.scenes)} scene(s) ({', '.join(workflow.scenes)}), "
              f"{len({(c.scene, c.edit_id) for c in workflow.cells})} scene edit(s); {edited} edited cells + "
              f"{len(workflow.cells) - edited} original")
    if editor == "synthetic":
        print("  editor: synthetic InstructPix2Pix EMULATOR (a simulator, not the diffusion model)")
    if encoder == "proxy":
        print("  encoder: proxy (weight-free colour/structure stand-in for CLIP; scores are not CLIP scores)")


def _write_report(workflow, store, out_dir: Path | None, partial: bool) -> None:
    from experiments.commands.report import report_workflow
    from experiments.report import ReportError

    try:
        index = report_workflow(workflow, store, out_dir)
    except ReportError as err:
        if partial:
            print(f"report: not written: {err}", file=sys.stderr)
            return
        raise
    print(f"report: {index}")
