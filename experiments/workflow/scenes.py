"""Where a workflow's scenes and edits come from: a user folder <scenes_dir>/<name>/ (which wins) or a
procedural scene of dualnerf.scenes; the edits of each scene and their instruction and captions."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from experiments.workflow.cells import WorkflowError
from pipeline.dag import External, Step
from pipeline.paths import check_plain_name

PROCEDURAL = "procedural"          # scenes = "procedural": every scene of dualnerf.scenes.library
DEFAULT_SCENES_DIR = "data/scenes"


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


def _edit_vocabulary(name: str, user_folder: Path | None):
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
class Scene:
    name: str
    inputs: dict                  # {"scene": Step} (procedural) or {"source": External} (user folder)
    origin: str
    spec: Any                     # SceneSpec or None (a user folder without scene.toml)
    edit_ids: tuple[str, ...]

    @property
    def procedural(self) -> bool:
        return "scene" in self.inputs


def scene_names(path: Path, settings: dict) -> list[str]:
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


def load_scene(path: Path, settings: dict, name: str, scenes_dir: Path) -> Scene:
    inputs, origin, user_folder = resolve_scene(name, scenes_dir)
    spec = _edit_vocabulary(name, user_folder)
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
    return Scene(name, inputs, origin, spec, ids)


def captions(path: Path, settings: dict, scene: Scene, edit_id: str, required: bool = True) -> dict:
    """The edit's instruction and source/target captions: the scene's scene.toml, overridden by [workflow].
    Not `required` (no edited rows), missing ones are "": the evaluation then says C_t2i has no captions."""
    found = {"instruction": None, "source_caption": None, "target_caption": None}
    if scene.spec is not None and edit_id in scene.edit_ids and any(e.id == edit_id for e in scene.spec.edits):
        edit = scene.spec.edit(edit_id)
        found = {"instruction": edit.instruction, "source_caption": edit.source_caption,
                 "target_caption": edit.target_caption}
    for key in found:
        if key in settings:
            found[key] = settings[key]
    missing = [k for k, v in found.items() if not v]
    if not required:
        return {k: v or "" for k, v in found.items()}
    if missing:
        raise WorkflowError(f"{path}: scene '{scene.name}' has no scene.toml edit vocabulary; set "
                            f"{', '.join(missing)} in [workflow] or with --set.")
    return found
