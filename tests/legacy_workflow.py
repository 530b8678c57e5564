"""FROZEN reference: stages/workflow.py as it was before the grid model (issue 12), unchanged below this
paragraph. tests/test_workflow_keys.py expands the shipped single-scene workflows with it and with the
current stages.workflow and requires identical step keys, so a cached ablation stays cached. Never edit
it; it is not used by the product.

DualNeRF workflows: a TOML grid (DF/SA/CCI toggles x seeds on one scene and edit) expanded into steps.

    scene -> preprocess -> fit -> edit[variant, seed] -> evaluate[variant, seed]
                               \\-> evaluate[original]

Identical invocations share one key in the store, so preprocess and the static fit run once for the
whole grid. A workflow file looks like `workflows/ablation.toml`:

    [workflow]
    name = "ablation"
    scene = "campsite"        # procedural scene, or a user folder data/scenes/<name>/ (takes precedence)
    edit = "snow"             # edit id from the scene's vocabulary (scene.toml)
    seeds = [0]
    variants = [[false, false, false], [true, false, false], ...]   # [DF, SA, CCI] per grid row
    [stages.fit]              # parameters per stage; anything omitted takes the stage's default
    iterations = 2000

`--set key=value` overrides: `scene=...`, `edit=...`, `seeds=[0,1]`, `instruction=...`,
`source_caption=...`, `target_caption=...`, or `<stage>.<param>=...` (value parsed as TOML, else a string).
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.dag import External, Step
from pipeline.errors import UserError

STAGE_SECTIONS = ("scene", "preprocess", "fit", "edit", "evaluate")
WORKFLOW_KEYS = {"name", "scene", "edit", "seeds", "variants", "instruction", "source_caption",
                 "target_caption", "scenes_dir", "report_dir"}
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
    """One report row: the evaluate step and, for edited rows, the variant, seed and edit step."""

    label: str
    evaluate: Step
    variant: Variant | None = None
    seed: int | None = None
    edit: Step | None = None


@dataclass
class Workflow:
    name: str
    path: Path
    scene_name: str
    scene_origin: str             # "procedural" or the user folder used
    edit_id: str
    instruction: str
    source_caption: str
    target_caption: str
    steps: list[Step]
    cells: list[Cell]
    report_dir: Path
    settings: dict[str, Any] = field(default_factory=dict)


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
    _check_known(path, doc, settings, stage_params)
    for override in overrides:
        _apply_override(path, override, settings, stage_params)
    return _expand(path, settings, stage_params)


def _check_known(path: Path, doc: dict, settings: dict, stage_params: dict) -> None:
    unknown_top = sorted(set(doc) - {"workflow", "stages"})
    if unknown_top:
        raise WorkflowError(f"{path}: unknown section(s) {unknown_top}; expected [workflow] and [stages.<name>].")
    unknown = sorted(set(settings) - WORKFLOW_KEYS)
    if unknown:
        raise WorkflowError(f"{path}: unknown [workflow] key(s) {unknown}; known: {sorted(WORKFLOW_KEYS)}.")
    unknown_stages = sorted(set(doc.get("stages", {})) - set(STAGE_SECTIONS))
    if unknown_stages:
        raise WorkflowError(f"{path}: unknown stage section(s) {unknown_stages}; stages are {STAGE_SECTIONS}.")


def _parse_value(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _apply_override(path: Path, override: str, settings: dict, stage_params: dict) -> None:
    key, sep, raw = override.partition("=")
    key = key.strip()
    if not sep or not key:
        raise WorkflowError(f"--set {override!r}: expected key=value, e.g. --set fit.iterations=500.")
    value = _parse_value(raw.strip())
    stage, dot, param = key.partition(".")
    if dot:
        if stage not in STAGE_SECTIONS:
            raise WorkflowError(f"--set {override!r}: unknown stage '{stage}'; stages are {STAGE_SECTIONS}.")
        stage_params[stage][param] = value
    elif key in WORKFLOW_KEYS:
        settings[key] = value
    else:
        raise WorkflowError(f"--set {override!r}: unknown key '{key}'; workflow keys are "
                            f"{sorted(WORKFLOW_KEYS)}, stage parameters are <stage>.<param>.")


def _variants(path: Path, raw: Any) -> list[Variant]:
    if not isinstance(raw, list) or not raw:
        raise WorkflowError(f"{path}: [workflow] variants must be a non-empty list of [DF, SA, CCI] booleans.")
    variants = []
    for row in raw:
        if not (isinstance(row, list) and len(row) == 3 and all(isinstance(v, bool) for v in row)):
            raise WorkflowError(f"{path}: variant {row!r} must be three booleans [DF, SA, CCI].")
        variants.append(Variant(*row))
    return variants


def _seeds(path: Path, raw: Any) -> list[int]:
    seeds = raw if isinstance(raw, list) else [raw]
    if not seeds or not all(isinstance(s, int) and not isinstance(s, bool) for s in seeds):
        raise WorkflowError(f"{path}: [workflow] seeds must be an integer or a list of integers, got {raw!r}.")
    return seeds


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


def _expand(path: Path, settings: dict, stage_params: dict) -> Workflow:
    scene_name = settings.get("scene")
    if not isinstance(scene_name, str) or not scene_name:
        raise WorkflowError(f"{path}: [workflow] scene must name a scene, e.g. scene = \"campsite\".")
    scenes_dir = Path(settings.get("scenes_dir", DEFAULT_SCENES_DIR))
    scene_inputs, origin, user_folder = resolve_scene(scene_name, scenes_dir)
    spec = _edit_vocabulary(scene_name, user_folder, path)
    edit_id = settings.get("edit") or (spec.edits[0].id if spec and spec.edits else "custom")
    captions = {"instruction": None, "source_caption": None, "target_caption": None}
    if spec is not None and any(e.id == edit_id for e in spec.edits):
        edit = spec.edit(edit_id)
        captions = {"instruction": edit.instruction, "source_caption": edit.source_caption,
                    "target_caption": edit.target_caption}
    elif spec is not None and "instruction" not in settings:
        raise WorkflowError(f"{path}: edit '{edit_id}' is not in scene '{scene_name}' (its edits: "
                            f"{', '.join(e.id for e in spec.edits)}); pick one or set instruction and captions.")
    for key in captions:
        if key in settings:
            captions[key] = settings[key]
    missing = [k for k, v in captions.items() if not v]
    if missing:
        raise WorkflowError(f"{path}: scene '{scene_name}' has no scene.toml edit vocabulary; set "
                            f"{', '.join(missing)} in [workflow] or with --set.")

    scene_step = scene_inputs.get("scene")
    if isinstance(scene_step, Step) and stage_params["scene"]:
        scene_step = Step("scene", {"name": scene_name, **stage_params["scene"]}, label=scene_step.label)
        scene_inputs = {"scene": scene_step}
    preprocess = Step("preprocess", stage_params["preprocess"], scene_inputs, label=f"preprocess[{scene_name}]")
    fit = Step("fit", stage_params["fit"], {"dataset": preprocess}, label=f"fit[{scene_name}]")
    evaluate_common = {"edit_id": edit_id, "source_caption": captions["source_caption"],
                       "target_caption": captions["target_caption"], **stage_params["evaluate"]}
    original = Step("evaluate", evaluate_common, {"dataset": preprocess, "fit": fit},
                    label=f"evaluate[{scene_name}, original]")
    cells = [Cell("Original scene", original)]
    steps = ([scene_step] if isinstance(scene_step, Step) else []) + [preprocess, fit, original]
    for seed in _seeds(path, settings.get("seeds", [0])):
        for variant in _variants(path, settings.get("variants")):
            edit_params = {**stage_params["edit"], "dual_field": variant.dual_field,
                           "annealing": variant.annealing, "consistency": variant.consistency,
                           "instruction": captions["instruction"], "edit_id": edit_id, "seed": seed}
            tag = f"{variant.label}, seed {seed}"
            edit = Step("edit", edit_params, {"dataset": preprocess, "fit": fit}, label=f"edit[{tag}]")
            evaluate = Step("evaluate", evaluate_common,
                            {"dataset": preprocess, "fit": fit, "edit": edit, "original": original},
                            label=f"evaluate[{tag}]")
            steps += [edit, evaluate]
            cells.append(Cell(variant.label, evaluate, variant, seed, edit))
    report_dir = Path(str(settings.get("report_dir", "reports/{scene}")).format(scene=scene_name))
    return Workflow(name=str(settings.get("name", path.stem)), path=path, scene_name=scene_name,
                    scene_origin=origin, edit_id=edit_id, steps=steps, cells=cells, report_dir=report_dir,
                    settings=settings, **captions)
