"""`dualnerf status WORKFLOW`: what is done, running (with progress), partial, failed or pending."""
from __future__ import annotations

import argparse


def register(subparsers) -> None:
    parser = subparsers.add_parser("status", help="show each step's state for a workflow",
                                   description="Compute the workflow's keys and show each step's state "
                                               "from the store, leases and run records (runs nothing).")
    parser.add_argument("workflow", help="workflow TOML file")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="the same overrides as `dualnerf run` (repeatable)")
    parser.set_defaults(handler=_status)


def _status(args: argparse.Namespace) -> int:
    from experiments.cli import open_store
    from experiments.workflow import load_workflow
    from pipeline.status import workflow_status
    from stages import STAGES

    workflow = load_workflow(args.workflow, args.overrides)
    rows = workflow_status(workflow.steps, registry=STAGES, store=open_store(args), runs_dir=args.runs)
    print_status(rows)
    return 1 if any(r.state == "failed" for r in rows) else 0


def print_status(rows) -> None:
    width = max([len(r.label) for r in rows] + [5])
    for r in rows:
        line = f"{r.label.ljust(width)}  {r.key[:12]}  {r.state:<8}"
        print(f"{line}  {r.detail}".rstrip())
    counts: dict[str, int] = {}
    for r in rows:
        counts[r.state] = counts.get(r.state, 0) + 1
    print(", ".join(f"{n} {state}" for state, n in sorted(counts.items())))
