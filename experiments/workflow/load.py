"""Reading a workflow: the TOML file, its checks, `--set` overrides and the older `variants` syntax, then
the expansion (experiments.workflow.expand)."""
from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from experiments.methods import MethodError, names_from_variants
from experiments.workflow import grid
from experiments.workflow.cells import Workflow, WorkflowError

STAGE_SECTIONS = grid.GRID_STAGES
WORKFLOW_KEYS = {"name", "scene", "scenes", "edit", "edits", "seeds", "variants", "methods", "instruction",
                 "source_caption", "target_caption", "scenes_dir", "report_dir", "include", "exclude", "original"}
SYNONYMS = {"scene": "scenes", "scenes": "scene", "edit": "edits", "edits": "edit", "variants": "methods",
            "methods": "variants"}


def load_workflow(path: Path | str, overrides: list[str] | tuple[str, ...] = ()) -> Workflow:
    from experiments.workflow.expand import expand

    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise WorkflowError(f"workflow file {path} does not exist; the shipped ones are in workflows/") from None
    except tomllib.TOMLDecodeError as err:
        raise WorkflowError(f"{path}: invalid TOML: {err}. Fix the file at that line.") from None
    settings = dict(doc.get("workflow", {}))
    stage_params = {name: dict(doc.get("stages", {}).get(name, {})) for name in STAGE_SECTIONS}
    axes_doc = dict(doc.get("axes", {}))
    _check_known(path, doc, settings, stage_params)
    for override in overrides:
        _apply_override(path, override, settings, stage_params, axes_doc)
    _variants_to_methods(path, settings)
    return expand(path, settings, stage_params, axes_doc)


def _variants_to_methods(path: Path, settings: dict) -> None:
    """The older `variants = [[DF, SA, CCI], ...]` becomes `methods` (same labels, same keys): the one
    place that syntax is read."""
    if "variants" in settings:
        try:
            settings["methods"] = names_from_variants(settings.pop("variants"))
        except MethodError as err:
            raise WorkflowError(f"{path}: {err}") from None


def _check_known(path: Path, doc: dict, settings: dict, stage_params: dict) -> None:
    unknown_top = sorted(set(doc) - {"workflow", "stages", "axes"})
    if unknown_top:
        raise WorkflowError(f"{path}: unknown section(s) {unknown_top}; expected [workflow], [stages.<name>] "
                            f"and [axes].")
    unknown = sorted(set(settings) - WORKFLOW_KEYS)
    if unknown:
        raise WorkflowError(f"{path}: unknown [workflow] key(s) {unknown}; known: {sorted(WORKFLOW_KEYS)}.")
    unknown_stages = sorted(set(doc.get("stages", {})) - set(STAGE_SECTIONS))
    if unknown_stages:
        raise WorkflowError(f"{path}: unknown stage section(s) {unknown_stages}; stages are {STAGE_SECTIONS}.")
    for key, other in SYNONYMS.items():
        if key in settings and other in settings:
            raise WorkflowError(f"{path}: [workflow] has both '{key}' and '{other}'; give one.")


def _parse_value(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _apply_override(path: Path, override: str, settings: dict, stage_params: dict, axes_doc: dict) -> None:
    key, sep, raw = override.partition("=")
    key = key.strip()
    if not sep or not key:
        raise WorkflowError(f"--set {override!r}: expected key=value, e.g. --set fit.iterations=500.")
    value = _parse_value(raw.strip())
    stage, dot, param = key.partition(".")
    if key in axes_doc:
        entry = axes_doc[key]
        axes_doc[key] = {**entry, "values": value} if isinstance(entry, dict) else value
    elif dot:
        if stage not in STAGE_SECTIONS:
            raise WorkflowError(f"--set {override!r}: unknown stage '{stage}'; stages are {STAGE_SECTIONS}.")
        grid.check_param(WorkflowError, stage, param, f"--set {override!r}")
        for name, entry in list(axes_doc.items()):
            targets = entry.get("params", []) if isinstance(entry, dict) else [name]
            if key in targets and len(targets) > 1:
                raise WorkflowError(f"--set {override!r}: '{key}' is set by the grouped axis '{name}' "
                                    f"({', '.join(targets)}); override that: --set {name}=[...].")
            if key in targets:
                del axes_doc[name]                  # the --set replaces the [axes] entry
        stage_params[stage][param] = value
    elif key in WORKFLOW_KEYS:
        settings.pop(SYNONYMS.get(key, ""), None)   # --set scene=x replaces the file's scenes, etc.
        settings[key] = value
    else:
        raise WorkflowError(f"--set {override!r}: unknown key '{key}'; workflow keys are "
                            f"{sorted(WORKFLOW_KEYS)}, stage parameters are <stage>.<param>, axes are "
                            f"{sorted(axes_doc) or 'none'}.")
