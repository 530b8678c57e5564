"""Saving and loading radiance-field models (static field, single-field baseline or dual field).

API:
    save_model(folder: Path, model: RadianceField | DualField, *, extra: dict | None = None) -> None
    load_model(folder: Path, device: str | torch.device = "cpu") -> RadianceField | DualField
    saved_blend(model) -> (w_density, w_color) | None   the blend to render a loaded model with

Folder layout: `model.json` (format name, format version, kind "field" | "dual", the FieldConfig,
`render_blend` for dual fields, free-form `extra`) and `weights.pt` (a plain state dict of tensors,
occupancy grid included), read back with torch.load(weights_only=True). A DualField's `render_blend`
(set by the edit stage to its final blend weights) is what `saved_blend` returns, so an evaluator can
render any saved model with `render_view(model, ..., blend=saved_blend(model))`.
"""
from __future__ import annotations

import json
from pathlib import Path

import torch

from dualnerf.dual_field import DualField
from dualnerf.fields import FieldConfig, FieldConfigError, RadianceField

MODEL_FORMAT = "dualnerf-model"
MODEL_VERSION = 1


class ModelFileError(ValueError):
    """A model folder that cannot be loaded; the message names the file and what to do."""


def save_model(folder: Path, model, *, extra: dict | None = None) -> None:
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if isinstance(model, DualField):
        kind = "dual"
        blend = None if model.render_blend is None else [float(w) for w in model.render_blend]
    elif isinstance(model, RadianceField):
        kind, blend = "field", None
    else:
        raise TypeError(f"save_model: expected a RadianceField or DualField, got {type(model).__name__}")
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    torch.save(state, folder / "weights.pt")
    doc = {"format": MODEL_FORMAT, "version": MODEL_VERSION, "kind": kind,
           "field_config": model.config.to_dict(), "render_blend": blend, "extra": extra or {}}
    (folder / "model.json").write_text(json.dumps(doc, indent=1))


def load_model(folder: Path, device: str | torch.device = "cpu"):
    folder = Path(folder)
    meta_path, weights_path = folder / "model.json", folder / "weights.pt"
    try:
        doc = json.loads(meta_path.read_text())
    except FileNotFoundError:
        raise ModelFileError(f"{meta_path} is missing: {folder} is not a saved model folder "
                             "(point to the fit or edit result's model/ folder)") from None
    except json.JSONDecodeError as err:
        raise ModelFileError(f"{meta_path} is not valid JSON ({err}); rerun the stage that wrote it") from None
    if doc.get("format") != MODEL_FORMAT or doc.get("version") != MODEL_VERSION:
        raise ModelFileError(f"{meta_path}: expected {MODEL_FORMAT} v{MODEL_VERSION}, got "
                             f"{doc.get('format')} v{doc.get('version')}; refit with this version of dualnerf")
    try:
        config = FieldConfig.from_dict(doc["field_config"])
    except (KeyError, TypeError, FieldConfigError) as err:
        raise ModelFileError(f"{meta_path}: bad field_config ({err}); rerun the stage that wrote it") from None
    if doc.get("kind") == "dual":
        model = DualField(RadianceField(config), RadianceField(config))
        blend = doc.get("render_blend")
        model.render_blend = None if blend is None else (float(blend[0]), float(blend[1]))
    elif doc.get("kind") == "field":
        model = RadianceField(config)
    else:
        raise ModelFileError(f"{meta_path}: unknown kind {doc.get('kind')!r} (expected 'field' or 'dual')")
    try:
        state = torch.load(weights_path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise ModelFileError(f"{weights_path} is missing; rerun the stage that wrote {folder}") from None
    try:
        model.load_state_dict(state)
    except RuntimeError as err:
        raise ModelFileError(f"{weights_path} does not match {meta_path} ({err}); rerun the stage") from None
    return model.to(device)


def saved_blend(model) -> tuple[float, float] | None:
    return model.render_blend if isinstance(model, DualField) else None
