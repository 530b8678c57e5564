"""`dualnerf report WORKFLOW [--out DIR]`: the report of a finished workflow (tables, grid, curves, HTML).

It expands the workflow exactly as `dualnerf run` does, looks each evaluate/edit step's result up in the
store by its key (computing nothing), and hands the folders to `experiments.report.build_report`.
`report_workflow` is the same thing for callers that already hold a workflow and a store (`run`).
"""
from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "report", help="build the report of a finished workflow",
        description="Build tables (Markdown/CSV/JSON), an image grid, training curves and index.html from "
                    "the cached results of a workflow. Runs nothing: missing results are an error.")
    parser.add_argument("workflow", help="workflow TOML file")
    parser.add_argument("--out", type=Path, default=None, metavar="DIR",
                        help="report folder (default: the workflow's report_dir, e.g. reports/<scene>)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="the same overrides as `dualnerf run` (repeatable)")
    parser.add_argument("--reference", default=None, metavar="LABEL",
                        help="row that every other row's paired difference (with bootstrap CI) is taken "
                             "to (default: the row labelled 'baseline', Instruct-NeRF2NeRF)")
    parser.set_defaults(handler=_report)


def _report(args: argparse.Namespace) -> int:
    from experiments.cli import open_store
    from experiments.workflow import load_workflow

    workflow = load_workflow(args.workflow, args.overrides)
    index = report_workflow(workflow, open_store(args), args.out, reference=args.reference)
    print(f"report: {index}")
    return 0


def workflow_rows(workflow, store) -> list:
    """One ReportRow per workflow cell, from the store; a ReportError lists cells without results."""
    from experiments.report import ReportError, ReportRow
    from pipeline.dag import resolve_results
    from stages import STAGES

    steps = [c.evaluate for c in workflow.cells] + [c.edit for c in workflow.cells if c.edit is not None]
    found = resolve_results(steps, registry=STAGES, store=store)
    missing = [c.evaluate.label or c.label for c in workflow.cells if found[c.evaluate] is None]
    if missing:
        raise ReportError(f"workflow {workflow.path}: no result yet for {', '.join(missing)}; run "
                          f"`dualnerf run {workflow.path}` (with the same --set overrides) first.")
    rows = []
    for cell in workflow.cells:
        rows.append(ReportRow(
            method=cell.method, seed=cell.seed, evaluate_dir=Path(found[cell.evaluate]),
            edit_dir=None if cell.edit is None else found.get(cell.edit),
            scene=cell.scene, edit=cell.edit_id, params=tuple(cell.params)))
    return rows


def report_workflow(workflow, store, out_dir: Path | None = None, *, reference: str | None = None) -> Path:
    """Build the report of `workflow` from `store` into `out_dir` (default workflow.report_dir)."""
    from experiments.report import build_report

    title_info = {"workflow": f"{workflow.name} ({workflow.path})",
                  "scene": f"{workflow.scene_name} ({workflow.scene_origin})",
                  "edit": workflow.edit_id, "instruction": workflow.instruction,
                  "source caption": workflow.source_caption, "target caption": workflow.target_caption}
    if len(workflow.scenes) > 1 or len({c.edit_id for c in workflow.cells}) > 1:
        title_info = {"workflow": title_info["workflow"], "scenes": ", ".join(workflow.scenes),
                      "scene edits": ", ".join(sorted({f"{c.scene}/{c.edit_id}" for c in workflow.cells}))}
    return build_report(workflow_rows(workflow, store), Path(out_dir or workflow.report_dir),
                        title_info=title_info, reference=reference)
