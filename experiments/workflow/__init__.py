"""Workflows: a TOML grid (scenes x edits x methods x seeds x parameter axes) expanded into steps.

    load_workflow(path, overrides) -> Workflow(steps, cells, report_dir, ...)

Modules: `load` (the file, its checks, `--set` overrides), `scenes` (user folders and procedural scenes,
their edits and captions), `grid` (the axes: methods, seeds, parameter axes, shared steps), `expand` (grid
cells -> steps, wired from the stages' declared inputs), `cells` (Workflow, Cell, WorkflowError). The
syntax is documented in docs/workflows.md; the generic product and filters are `pipeline.grid`.
"""
from experiments.workflow.cells import Cell, Workflow, WorkflowError
from experiments.workflow.load import load_workflow
from experiments.workflow.scenes import resolve_scene

__all__ = ["Cell", "Workflow", "WorkflowError", "load_workflow", "resolve_scene"]
