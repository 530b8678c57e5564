"""Reading a scene folder: its edit vocabulary (scene.toml) and, for procedural scenes, its ground-truth
edited views. A folder of one's own photos needs only images/ and a scene.toml with [scene] name and its
[[edits]] (docs/tutorial.md); the ground truth exists for procedural scenes only.

Scene folder layout (a contract other stages code against):
    images/<name>.png                      original views, 8-bit RGB
    scene.toml                             [scene] name, generator, seed, width, height
                                           [[edits]] id, instruction, source_caption, target_caption,
                                                     kind (optional: recolour | global | geometry),
                                                     modes (optional: ids of alternative modes)
    gt/transforms.json                     ground-truth cameras, nerfstudio convention
    gt/edits/<edit_id>/images/<name>.png   ground-truth edited views (same cameras, edited materials)
    gt/edits/<edit_id>/masks/<name>.png    8-bit masks, 255 where the edit changes the colour
    gt/edits/<edit_id>.<mode>/...          the same for each alternative mode of the edit (another plausible
                                           appearance of the instruction; NOT ground truth: the InstructPix2Pix
                                           emulator's mode lock-in draws from them)
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dualnerf.confine import check_file_name, check_plain_name, confine

SCENE_FILE = "scene.toml"
GT_EDITS_DIR = Path("gt") / "edits"


class SceneSpecError(ValueError):
    """A scene folder whose scene.toml or ground truth cannot be used; the message says what to fix."""

    user_error = True        # the CLI prints the message and exits 2 (see pipeline.errors)


@dataclass(frozen=True)
class EditSpec:
    id: str
    instruction: str
    source_caption: str
    target_caption: str
    kind: str = ""           # recolour | global | geometry ("" in folders written before kinds existed)
    modes: tuple[str, ...] = ()   # alternative modes (gt/edits/<id>.<mode>/); () in folders written before them


@dataclass(frozen=True)
class SceneSpec:
    name: str
    edits: tuple[EditSpec, ...]
    generator: str = ""
    seed: int = 0
    width: int = 0
    height: int = 0

    def edit(self, id: str) -> EditSpec:
        for spec in self.edits:
            if spec.id == id:
                return spec
        known = ", ".join(e.id for e in self.edits) or "none"
        raise SceneSpecError(f"scene '{self.name}' has no edit '{id}'; its edits are: {known}.")


def load_scene_spec(folder: Path) -> SceneSpec:
    path = Path(folder) / SCENE_FILE
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise SceneSpecError(
            f"{path} is missing: a scene folder needs a scene.toml naming the scene and its edits, e.g. "
            f"[scene] name = \"{Path(folder).name}\" and an [[edits]] table with id, instruction, "
            f"source_caption and target_caption (docs/tutorial.md)."
        ) from None
    except tomllib.TOMLDecodeError as err:
        raise SceneSpecError(f"{path} is not valid TOML ({err}); fix the file at that line.") from None
    scene = doc.get("scene")
    if not isinstance(scene, dict):
        raise SceneSpecError(f"{path}: the [scene] table is missing; it needs name = \"...\" (procedural scenes "
                             f"also record generator, seed, width and height there).")
    name = _field(scene, "name", str, path, "[scene]")
    edits = []
    for i, entry in enumerate(doc.get("edits", [])):
        where = f"[[edits]] entry {i + 1}"
        if not isinstance(entry, dict):
            raise SceneSpecError(f"{path}: {where} must be a table.")
        fields = {key: _field(entry, key, str, path, where)
                  for key in ("id", "instruction", "source_caption", "target_caption")}
        if "kind" in entry:
            fields["kind"] = _field(entry, "kind", str, path, where)
        if "modes" in entry:
            modes = entry["modes"]
            if not isinstance(modes, list) or not all(isinstance(m, str) for m in modes):
                raise SceneSpecError(f"{path}: {where} field 'modes' must be a list of mode ids, got {modes!r}.")
            for mode in modes:
                check_plain_name(mode, error=SceneSpecError, where=f"{path}: {where}", field="mode")
            fields["modes"] = tuple(modes)
        edits.append(EditSpec(**fields))
    for i, edit in enumerate(edits):
        check_plain_name(edit.id, error=SceneSpecError, where=f"{path}: [[edits]] entry {i + 1}", field="id")
    check_file_name(name, error=SceneSpecError, where=f"{path}: [scene]", field="name")
    ids = [e.id for e in edits]
    if len(set(ids)) != len(ids):
        raise SceneSpecError(f"{path}: edit ids must be unique, got {ids}.")
    return SceneSpec(
        name=name, edits=tuple(edits),
        generator=str(scene.get("generator", "")), seed=int(scene.get("seed", 0)),
        width=int(scene.get("width", 0)), height=int(scene.get("height", 0)),
    )


def _field(table: dict, key: str, kind: type, path: Path, where: str):
    if key not in table:
        raise SceneSpecError(f"{path}: {where} is missing the field '{key}'.")
    value = table[key]
    if not isinstance(value, kind) or (kind is str and not value.strip()):
        raise SceneSpecError(f"{path}: {where} field '{key}' must be a non-empty {kind.__name__}, "
                             f"got {value!r}.")
    return value


def mode_edit_id(edit_id: str, mode: str) -> str:
    """The gt/edits/ folder name of alternative mode `mode` of edit `edit_id`."""
    return f"{edit_id}.{mode}"


def load_gt_edit(folder: Path, edit_id: str, name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """The ground-truth edited view and its mask for image `name`, or None when the folder has none.

    `name` is the original image file name (e.g. "view_003.png"); returns (uint8 HxWx3 RGB, bool HxW).
    """
    import cv2

    check_plain_name(edit_id, error=SceneSpecError, where=str(folder), field="edit id")
    check_file_name(name, error=SceneSpecError, where=str(folder), field="view name")
    base = Path(folder) / GT_EDITS_DIR / edit_id
    image_path, mask_path = base / "images" / name, base / "masks" / name
    for path in (image_path, mask_path):
        confine(path, folder, error=SceneSpecError, where=str(folder), field="ground-truth file",
                value=path.relative_to(folder).as_posix())
    if not image_path.exists():
        return None
    image = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
    mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise SceneSpecError(f"{image_path} is unreadable; regenerate the scene's ground truth.")
    if mask is None:
        raise SceneSpecError(f"{mask_path} is missing or unreadable; every ground-truth edited view needs "
                             f"its mask, regenerate the scene's ground truth.")
    if mask.shape != image.shape[:2]:
        raise SceneSpecError(f"{mask_path} is {mask.shape[1]}x{mask.shape[0]} but its image is "
                             f"{image.shape[1]}x{image.shape[0]}; regenerate the scene's ground truth.")
    return np.ascontiguousarray(image[..., ::-1]), mask > 127
