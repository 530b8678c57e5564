"""DualNeRF workflows: a TOML grid (scenes x edits x methods x seeds x parameter axes) expanded into steps.

    scene -> preprocess -> fit -> edit[method, seed, params] -> evaluate[...]
                              |                     perframe[seed] -> evaluate[per-frame, ...]
                              \\-> evaluate[original]

Identical invocations share one Step (and one key in the store), so preprocess and the static fit run
once per scene and fit setting. The axes and their syntax are documented in `stages.workflow_grid`; the
generic product and filters are `pipeline.grid`. A workflow file looks like `workflows/comparison.toml`:

    [workflow]
    name = "comparison"
    scenes = "procedural"     # or a list; a user folder data/scenes/<name>/ wins over a procedural scene
    edits = "all"             # or a list of edit ids, or {scene = ids} per scene
    methods = ["per-frame", "IN2N", "DualNeRF"]
    seeds = [0, 1, 2]
    exclude = [{scene = "tiny"}]
    [stages.fit]              # parameters per stage; anything omitted takes the stage's default
    iterations = 2000         # a list here (for a scalar parameter) is an axis
    [axes]
    w_max = {params = ["edit.w_max_density", "edit.w_max_color"], values = [0.03, 0.1, 0.3]}

`scene`, `edit` and `variants` (one scene, one edit, [DF, SA, CCI] rows) are the older single-scene
spelling and keep their step keys. `--set key=value` overrides a [workflow] key (scene(s)=, edit(s)=,
methods=, seeds=[0,1], include=/exclude=, instruction=, ...), a parameter `<stage>.<param>=...` (a list
value for a scalar parameter makes it an axis, a single value fixes it), or an [axes] entry's values
`<axis>=[...]`; values are parsed as TOML, else taken as a string.
"""
from __future__ import annotations

import functools
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.dag import External, Step
from pipeline.errors import UserError
from pipeline.grid import GridError
from pipeline.paths import check_plain_name, confined
from stages import workflow_grid as grid

STAGE_SECTIONS = grid.GRID_STAGES
WORKFLOW_KEYS = {"name", "scene", "scenes", "edit", "edits", "seeds", "variants", "methods", "instruction",
                 "source_caption", "target_caption", "scenes_dir", "report_dir", "include", "exclude", "original"}
SYNONYMS = {"scene": "scenes", "scenes": "scene", "edit": "edits", "edits": "edit", "variants": "methods",
            "methods": "variants"}
PROCEDURAL = "procedural"          # scenes = "procedural": every scene of dualnerf.scenes.library
DEFAULT_SCENES_DIR = "data/scenes"


class WorkflowError(UserError):
    """A workflow file or override that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class Variant:
    dual_field: bool
    annealing: bool
    consistency: bool

    @property
    def label(self) -> str:
        on = [name for name, flag in (("DF", self.dual_field), ("SA", self.annealing),
                                       ("CCI", self.consistency)) if flag]
        return "+".join(on) if on else "baseline"


@dataclass(frozen=True)
class Cell:
    """One report row: the evaluate step and, for edited rows, the variant, seed and edit step.

    `label` is the method label ("Original scene" for the unedited row); `params` the parameter-axis
    values this row's steps read, as (axis name, value) pairs; `perframe` the per-frame baseline's step.
    Per-frame rows have variant (False, False, False) and method "per-frame"."""

    label: str
    evaluate: Step
    variant: Variant | None = None
    seed: int | None = None
    edit: Step | None = None
    scene: str = ""
    edit_id: str = ""
    params: tuple = ()
    perframe: Step | None = None

    def describe(self) -> str:
        parts = [f"scene={self.scene}", f"edit={self.edit_id}", f"method={self.label}"]
        parts += [] if self.seed is None else [f"seed={self.seed}"]
        parts += [f"{k}={grid.format_value(v)}" for k, v in self.params]
        return " ".join(parts)


@dataclass
class Workflow:
    name: str
    path: Path
    scene_name: str               # the scene, or "<n>-scenes" for a grid over several
    scene_origin: str             # "procedural" or the user folder used (first scene)
    edit_id: str                  # the edit of the first cell
    instruction: str
    source_caption: str
    target_caption: str
    steps: list[Step]
    cells: list[Cell]
    report_dir: Path
    settings: dict[str, Any] = field(default_factory=dict)
    scenes: list[str] = field(default_factory=list)
    axes: list[tuple[str, int]] = field(default_factory=list)    # (axis name, number of values)


def load_workflow(path: Path | str, overrides: list[str] | tuple[str, ...] = ()) -> Workflow:
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
    return _expand(path, settings, stage_params, axes_doc)


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


def resolve_scene(name: str, scenes_dir: Path) -> tuple[dict[str, Step | External], str, Path | None]:
    """Where a scene comes from: a user folder wins over a procedural scene of the same name."""
    from dualnerf.scenes import SCENES

    user_folder = scenes_dir / name
    if user_folder.is_dir():
        return {"source": External(user_folder.resolve())}, f"user folder {user_folder}", user_folder
    if name in SCENES:
        return {"scene": Step("scene", {"name": name}, label=f"scene[{name}]")}, "procedural", None
    available = sorted(SCENES) + sorted(p.name for p in scenes_dir.glob("*") if p.is_dir())
    raise WorkflowError(f"unknown scene '{name}': no folder {user_folder}/ and no procedural scene of that "
                        f"name. Available: {', '.join(available)}.")


def _edit_vocabulary(name: str, user_folder: Path | None, path: Path):
    from dualnerf.scenes import EditSpec, SceneSpec, load_scene_spec
    from dualnerf.scenes.library import BUILDERS

    if user_folder is not None:
        if not (user_folder / "scene.toml").exists():
            return None
        return load_scene_spec(user_folder)
    # A procedural scene's vocabulary is known without rendering it.
    edits = BUILDERS[name][1]
    return SceneSpec(name, tuple(EditSpec(e.id, e.instruction, e.source_caption, e.target_caption)
                                 for e in edits))




@dataclass
class _Scene:
    name: str
    inputs: dict
    origin: str
    spec: Any                     # SceneSpec or None (a user folder without scene.toml)
    edit_ids: tuple[str, ...]


def _scene_names(path: Path, settings: dict) -> list[str]:
    from dualnerf.scenes import SCENES

    raw = settings.get("scenes", settings.get("scene"))
    if raw == PROCEDURAL:
        return sorted(SCENES)
    names = [raw] if isinstance(raw, str) else raw
    if not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names):
        raise WorkflowError(f"{path}: [workflow] scenes must name scenes, e.g. scenes = [\"campsite\"] (or "
                            f"\"{PROCEDURAL}\" for every procedural scene), got {raw!r}.")
    if len(set(names)) != len(names):
        raise WorkflowError(f"{path}: [workflow] scenes lists a scene twice: {names}.")
    for name in names:                  # substituted into folder names (data/scenes/, runs/, reports/)
        check_plain_name(name, f"{path}: [workflow] scene")
    return names


def _scene(path: Path, settings: dict, name: str, scenes_dir: Path) -> _Scene:
    inputs, origin, user_folder = resolve_scene(name, scenes_dir)
    spec = _edit_vocabulary(name, user_folder, path)
    known = tuple(e.id for e in spec.edits) if spec is not None else ()
    raw = settings.get("edits", settings.get("edit"))
    if isinstance(raw, dict):
        if name not in raw:
            raise WorkflowError(f"{path}: [workflow] edits gives edits per scene but none for '{name}' "
                                f"(it names {', '.join(raw)}).")
        raw = raw[name]
    if raw is None or raw == "":
        ids = known[:1] or ("custom",)
    elif raw == "all":
        if not known:
            raise WorkflowError(f"{path}: edits = \"all\" but scene '{name}' has no scene.toml edit vocabulary; "
                                f"name the edit and set instruction and captions.")
        ids = known
    else:
        ids = tuple([raw] if isinstance(raw, str) else raw)
        if not ids or not all(isinstance(i, str) and i for i in ids):
            raise WorkflowError(f"{path}: [workflow] edits must be edit ids, \"all\" or a table per scene, "
                                f"got {raw!r}.")
    for edit_id in ids:
        check_plain_name(edit_id, f"{path}: [workflow] edit")
    if spec is not None and "instruction" not in settings:
        unknown = [i for i in ids if i not in known]
        if unknown:
            raise WorkflowError(f"{path}: edit '{unknown[0]}' is not in scene '{name}' (its edits: "
                                f"{', '.join(known)}); pick one or set instruction and captions.")
    return _Scene(name, inputs, origin, spec, ids)


def _captions(path: Path, settings: dict, scene: _Scene, edit_id: str) -> dict:
    captions = {"instruction": None, "source_caption": None, "target_caption": None}
    if scene.spec is not None and edit_id in scene.edit_ids and any(e.id == edit_id for e in scene.spec.edits):
        edit = scene.spec.edit(edit_id)
        captions = {"instruction": edit.instruction, "source_caption": edit.source_caption,
                    "target_caption": edit.target_caption}
    for key in captions:
        if key in settings:
            captions[key] = settings[key]
    missing = [k for k, v in captions.items() if not v]
    if missing:
        raise WorkflowError(f"{path}: scene '{scene.name}' has no scene.toml edit vocabulary; set "
                            f"{', '.join(missing)} in [workflow] or with --set.")
    return captions


def _filters(path: Path, settings: dict, key: str) -> list:
    raw = settings.get(key, [])
    raw = [raw] if isinstance(raw, dict) else raw
    if not isinstance(raw, list) or not all(isinstance(f, dict) for f in raw):
        raise WorkflowError(f"{path}: [workflow] {key} must be a list of tables, e.g. "
                            f"{key} = [{{scene = \"tiny\", method = \"IN2N\"}}], got {raw!r}.")
    return raw


def _expand(path: Path, settings: dict, stage_params: dict, axes_doc: dict) -> Workflow:
    names = _scene_names(path, settings)
    scenes_dir = Path(settings.get("scenes_dir", DEFAULT_SCENES_DIR))
    scenes = {name: _scene(path, settings, name, scenes_dir) for name in names}
    methods = {m.label: m for m in grid.parse_methods(WorkflowError, path, settings)}
    seeds = grid.parse_seeds(WorkflowError, path, settings.get("seeds", [0]))
    param_axes, fixed = grid.param_axes(WorkflowError, path, stage_params, axes_doc)
    axes = grid.grid_axes(names, lambda scene: scenes[scene].edit_ids, list(methods.values()), seeds, param_axes)
    try:
        grid_cells = grid.expand(axes, _filters(path, settings, "include"), _filters(path, settings, "exclude"),
                                 where=str(path))
    except GridError as err:
        raise WorkflowError(str(err)) from None
    builder = grid.GridBuilder()
    single = len({(p["scene"], p["edit"]) for p in grid_cells}) == 1
    cells: list[Cell] = []
    listed: set[int] = set()
    read_anywhere: set[str] = set()
    order = {a.name: i for i, a in enumerate(param_axes)}
    with_original = bool(settings.get("original", True))
    captions_cache: dict[tuple[str, str], dict] = {}

    for point in grid_cells:
        scene = scenes[point["scene"]]
        edit_id, method, seed = point["edit"], methods[point["method"]], point["seed"]
        read: dict[str, Any] = {}

        params_for = functools.partial(_params_for, fixed, param_axes, point, read)
        # One scene edit in the whole grid: the step labels of the single-scene workflows (run records
        # and logs keep reading "edit[DF+SA, seed 0]"); otherwise every label names its scene edit.
        prefix = "" if single else f"{scene.name}/{edit_id}"
        tag = functools.partial(_tag, prefix, read, order)

        key = (scene.name, edit_id)
        if key not in captions_cache:
            captions_cache[key] = _captions(path, settings, scene, edit_id)
        captions = captions_cache[key]
        inputs = scene.inputs
        scene_params = params_for("scene") if "scene" in inputs else {}
        if "scene" in inputs:
            inputs = {"scene": builder.make("scene", {"name": scene.name, **scene_params}, {},
                                            label=f"scene[{scene.name}]")}
        preprocess = builder.make("preprocess", params_for("preprocess"), inputs,
                                  label=f"preprocess[{scene.name}]")
        fit = builder.make("fit", params_for("fit"), {"dataset": preprocess}, label=f"fit[{scene.name}]")
        evaluate_common = {"edit_id": edit_id, "source_caption": captions["source_caption"],
                           "target_caption": captions["target_caption"], **params_for("evaluate")}
        original = builder.make("evaluate", evaluate_common, {"dataset": preprocess, "fit": fit},
                                label=f"evaluate[{tag(scene.name, 'original') if single else tag('original')}]")
        if with_original and id(original) not in listed:
            listed.add(id(original))
            cells.append(Cell("Original scene", original, scene=scene.name, edit_id=edit_id,
                              params=_ordered(read, order)))
        upstream = {"dataset": preprocess, "fit": fit}
        if method.toggles is None:
            perframe_params = {**params_for("perframe"), **params_for("edit", grid.PERFRAME_FROM_EDIT),
                               "instruction": captions["instruction"], "edit_id": edit_id, "seed": seed}
            perframe_inputs = {"dataset": preprocess, "original": original}
            if perframe_params.get("editor", "synthetic") == "synthetic":
                # The emulator's ground truth at the evaluation cameras: one render per scene edit.
                perframe_inputs["gtviews"] = builder.make(
                    "gtviews", {"edit_id": edit_id, "scene_supersample": int(scene_params.get("supersample", 0))},
                    {"dataset": preprocess, "original": original}, label=f"gtviews[{scene.name}/{edit_id}]")
            label = tag(method.label, f"seed {seed}")
            perframe = builder.make("perframe", perframe_params, perframe_inputs, label=f"perframe[{label}]")
            evaluate = builder.make("evaluate", evaluate_common, {**upstream, "original": original,
                                                                  "perframe": perframe},
                                    label=f"evaluate[{label}]")
            cell = Cell(method.label, evaluate, Variant(False, False, False), seed, None, scene.name, edit_id,
                        _ordered(read, order), perframe)
        else:
            df, sa, cci = method.toggles
            edit_params = {**params_for("edit"), "dual_field": df, "annealing": sa, "consistency": cci,
                           "instruction": captions["instruction"], "edit_id": edit_id, "seed": seed}
            label = tag(method.label, f"seed {seed}")
            edit = builder.make("edit", edit_params, upstream, label=f"edit[{label}]")
            evaluate = builder.make("evaluate", evaluate_common, {**upstream, "edit": edit, "original": original},
                                    label=f"evaluate[{label}]")
            cell = Cell(method.label, evaluate, Variant(df, sa, cci), seed, edit, scene.name, edit_id,
                        _ordered(read, order))
        read_anywhere |= set(read)
        if id(evaluate) not in listed:          # a per-frame row does not multiply over edit-only axes
            listed.add(id(evaluate))
            cells.append(cell)

    unread = [a for a in param_axes if a.name not in read_anywhere]
    if unread:
        axis = unread[0]
        raise WorkflowError(f"{path}: axis '{axis.name}' (sets {', '.join(f'{s}.{p}' for s, p in axis.targets)}) "
                            f"is read by no cell of the grid: methods {', '.join(methods)} never run that "
                            f"stage. Remove the axis or add a method that uses it.")
    first = cells[0]
    names = list(dict.fromkeys(c.scene for c in cells))        # the scenes left after the filters
    report_dir = _report_dir(path, settings, names)
    first_captions = captions_cache[(first.scene, first.edit_id)]
    sizes = [("scene", len(names)), ("edit", len({(c.scene, c.edit_id) for c in cells})),
             ("method", len({c.label for c in cells if c.label != 'Original scene'})), ("seed", len(seeds))]
    name = check_plain_name(settings["name"], f"{path}: [workflow] name") if "name" in settings else path.stem
    return Workflow(name=name, path=path,
                    scene_name=names[0] if len(names) == 1 else f"{len(names)}-scenes",
                    scene_origin=scenes[first.scene].origin, edit_id=first.edit_id, steps=builder.steps,
                    cells=cells, report_dir=report_dir, settings=settings, scenes=names,
                    axes=sizes + [(a.name, len(a.values)) for a in param_axes], **first_captions)


def _params_for(fixed: dict, param_axes: list, point, read: dict, stage: str, only: tuple = ()) -> dict:
    """The parameters of `stage` at grid point `point` (restricted to `only`); records in `read` which
    parameter axes they came from."""
    values = {k: v for k, v in fixed[stage].items() if not only or k in only}
    for axis in param_axes:
        for st, param in axis.targets:
            if st == stage and (not only or param in only):
                values[param] = point[axis.name]
                read[axis.name] = point[axis.name]
    return values


def _tag(prefix: str, read: dict, order: dict, *parts: str) -> str:
    return grid.label_of(prefix, list(parts), dict(_ordered(read, order)))


def _ordered(read: dict, order: dict) -> tuple:
    return tuple(sorted(read.items(), key=lambda kv: order[kv[0]]))


def _report_dir(path: Path, settings: dict, scenes: list[str]) -> Path:
    name = str(settings.get("name", path.stem))
    raw = str(settings.get("report_dir", "reports/{scene}" if len(scenes) == 1 else f"reports/{name}"))
    if "{scene}" in raw and len(scenes) > 1:
        raise WorkflowError(f"{path}: report_dir '{raw}' uses {{scene}} but the grid has {len(scenes)} scenes "
                            f"({', '.join(scenes)}); set report_dir without {{scene}} (e.g. reports/{name}).")
    # The scene name cannot lead the report elsewhere: it stays inside the folder before the placeholder.
    return confined(raw.replace("{scene}", scenes[0]), Path(raw.split("{")[0] + "x").parent,
                    f"{path}: [workflow] report_dir")
