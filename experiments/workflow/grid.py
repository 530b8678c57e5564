"""The axes of a workflow grid: scenes x edits x methods x seeds x parameter axes (the syntax, for users:
docs/workflows.md; the generic product, filters and labels: `pipeline.grid`).

Here: which stage parameters a workflow may set and which it sets itself (MANAGED), the method and seed
axes, the parameter axes (a LIST value for a parameter whose declared type is a scalar is an axis, in
`[stages.<stage>]`, `--set` or `[axes]`, where one entry may set several parameters), every
`<stage>.<param>` checked against the stage's Params before anything runs, and GridBuilder, which makes
identical invocations one Step (one key), so preprocess and fit run once per scene and setting.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from experiments.methods import EDIT_PARAMS, Method, MethodError
from pipeline.dag import Step
from pipeline.grid import Axis, expand, format_value

GRID_STAGES = ("scene", "preprocess", "fit", "edit", "perframe", "evaluate")
SCALAR_TYPES = {"int", "float", "str", "bool"}
# Parameters the workflow sets from its own axes and vocabulary (never a user axis or value).
MANAGED = {"edit": {**{param: "methods" for param in EDIT_PARAMS}, "seed": "seeds", "edit_id": "edits",
                    "instruction": "[workflow] instruction"},
           "perframe": {"seed": "seeds", "edit_id": "edits", "instruction": "[workflow] instruction"},
           "evaluate": {"edit_id": "edits", "source_caption": "[workflow] source_caption",
                        "target_caption": "[workflow] target_caption"},
           "scene": {"name": "scenes"}}
# The per-frame baseline uses the same editor as the IDU rows: these edit parameters reach it too.
PERFRAME_FROM_EDIT = ("editor", "editor_model", "device")


@dataclass(frozen=True)
class ParamAxis:
    name: str
    targets: tuple[tuple[str, str], ...]           # (stage, param) pairs it sets
    values: tuple


def stage_fields(stage: str) -> dict[str, str]:
    """{param: declared type name} of a stage's Params dataclass."""
    from pipeline.registry import load_stage
    from stages import STAGES

    params = load_stage(STAGES, stage).Params
    return {f.name: (f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type)))
            for f in dataclasses.fields(params)}


def check_param(error, stage: str, param: str, where: str) -> str:
    """The declared type of `<stage>.<param>`, or a WorkflowError naming the key and the known ones."""
    if stage not in GRID_STAGES:
        raise error(f"{where}: unknown stage '{stage}' in '{stage}.{param}'; stages are {', '.join(GRID_STAGES)}.")
    fields = stage_fields(stage)
    if param not in fields:
        raise error(f"{where}: unknown parameter '{stage}.{param}'; known {stage} parameters: "
                    f"{', '.join(sorted(fields))}.")
    if param in MANAGED.get(stage, {}):
        raise error(f"{where}: '{stage}.{param}' is set by the workflow from {MANAGED[stage][param]}; set it "
                    f"there instead.")
    return fields[param]


def parse_methods(error, path: Path, settings: dict) -> list[Method]:
    """The method axis: `methods = [...]` names (experiments.methods), distinct. An empty list (with the
    unedited rows kept: `original`, the default) runs no edit: the scene's reconstruction only."""
    raw = settings.get("methods")
    if raw is None:
        raise error(f"{path}: [workflow] needs methods, e.g. methods = [\"per-frame\", \"IN2N\", \"DualNeRF\"].")
    raw = [raw] if isinstance(raw, str) else raw
    if raw == [] and settings.get("original", True):
        return []
    if not isinstance(raw, list) or not raw or not all(isinstance(m, str) for m in raw):
        raise error(f"{path}: [workflow] methods must be a list of method names (empty only with the unedited "
                    f"rows, original = true), got {raw!r}.")
    try:
        methods = [Method.parse(name) for name in raw]
    except MethodError as err:
        raise error(f"{path}: {err}") from None
    labels = [m.label for m in methods]
    if len(set(labels)) != len(labels):
        raise error(f"{path}: methods must be distinct, got {labels}.")
    return methods


def parse_seeds(error, path: Path, raw: Any) -> list[int]:
    seeds = raw if isinstance(raw, list) else [raw]
    if not seeds or not all(isinstance(s, int) and not isinstance(s, bool) for s in seeds):
        raise error(f"{path}: [workflow] seeds must be an integer or a list of integers, got {raw!r}.")
    if len(set(seeds)) != len(seeds):
        raise error(f"{path}: [workflow] seeds must be distinct, got {seeds}.")
    return seeds


def param_axes(error, path: Path, stage_params: dict, axes_doc: dict) -> tuple[list[ParamAxis], dict]:
    """The parameter axes (from [axes] and list values of scalar stage parameters) and the fixed stage
    parameters left; every key checked against its stage's Params."""
    axes: list[ParamAxis] = []
    fixed: dict[str, dict] = {}
    for stage, params in stage_params.items():
        fixed[stage] = {}
        for param, value in params.items():
            kind = check_param(error, stage, param, f"{path} [stages.{stage}]")
            if isinstance(value, list) and kind in SCALAR_TYPES:
                axes.append(ParamAxis(f"{stage}.{param}", ((stage, param),), _axis_values(error, path, f"{stage}.{param}", value)))
            else:
                fixed[stage][param] = value
    for name, entry in axes_doc.items():
        if isinstance(entry, dict):
            unknown = sorted(set(entry) - {"params", "values"})
            targets = entry.get("params")
            if unknown or not isinstance(targets, list) or not targets or not all(isinstance(t, str) for t in targets):
                raise error(f"{path} [axes] {name}: a grouped axis is {{params = [\"<stage>.<param>\", ...], "
                            f"values = [...]}}, got {entry!r}.")
            values = entry.get("values")
        else:
            targets, values = [name], entry
        pairs = []
        for target in targets:
            stage, dot, param = target.partition(".")
            if not dot:
                raise error(f"{path} [axes] {name}: '{target}' must be <stage>.<param>, e.g. edit.w_max_color.")
            check_param(error, stage, param, f"{path} [axes] {name}")
            pairs.append((stage, param))
        axes.append(ParamAxis(name, tuple(pairs), _axis_values(error, path, name, values)))
    claimed: dict[tuple[str, str], str] = {}
    for axis in axes:
        for target in axis.targets:
            other = claimed.get(target) or (axis.name if target[1] in fixed.get(target[0], {}) else None)
            if other is not None:
                raise error(f"{path}: '{target[0]}.{target[1]}' is set by axis '{axis.name}' and also by "
                            f"'{other}'; give it one value or one axis.")
            claimed[target] = axis.name
    names = [a.name for a in axes]
    reserved = {"scene", "edit", "method", "seed"} & set(names)
    if reserved or len(set(names)) != len(names):
        raise error(f"{path}: parameter axis names must be distinct and not {sorted(reserved)}, got {names}.")
    return axes, fixed


def _axis_values(error, path: Path, name: str, values: Any) -> tuple:
    if not isinstance(values, list) or not values:
        raise error(f"{path}: axis '{name}' needs a non-empty list of values, got {values!r}.")
    if len({json.dumps(v, sort_keys=True) for v in values}) != len(values):
        raise error(f"{path}: axis '{name}' lists a value twice: {values!r}.")
    return tuple(values)


class GridBuilder:
    """Turns grid cells into shared steps; `make` returns the same Step for the same invocation."""

    def __init__(self):
        self._steps: dict[tuple, Step] = {}

    @property
    def steps(self) -> list[Step]:
        return list(self._steps.values())

    def make(self, stage: str, params: dict, inputs: dict, label: str) -> Step:
        memo = (stage, json.dumps(params, sort_keys=True, default=str),
                tuple(sorted((name, id(source)) for name, source in inputs.items())))
        if memo not in self._steps:
            self._steps[memo] = Step(stage, params, inputs, label=label)
        return self._steps[memo]


def grid_axes(scenes: list[str], edits_of, methods: list[Method], seeds: list[int],
              axes: list[ParamAxis]) -> list[Axis]:
    return ([Axis("scene", tuple(scenes)), Axis("edit", lambda cell: edits_of(cell["scene"])),
             Axis("method", tuple(m.label for m in methods)), Axis("seed", tuple(seeds))]
            + [Axis(a.name, a.values) for a in axes])


def label_of(prefix: str, parts: list[str], read: dict[str, Any]) -> str:
    """"<prefix>, part, ..., axis=value, ..." (the prefix names the scene edit; may be empty)."""
    return ", ".join(([prefix] if prefix else []) + parts + [f"{k}={format_value(v)}" for k, v in read.items()])


__all__ = [
    "GRID_STAGES",
    "PERFRAME_FROM_EDIT",
    "GridBuilder",
    "ParamAxis",
    "expand",
    "grid_axes",
    "label_of",
    "param_axes",
    "parse_methods",
    "parse_seeds",
]
