"""The proxy encoder's vocabulary for a scene folder: which images define each caption's embedding.

For a folder carrying scene.toml and gt/edits/ (a procedural scene, or a dataset preprocessed from one):
    source_caption                 <- the original views
    target_caption and instruction <- the ground-truth edited views of that edit
Used only with the PROXY encoder (weight-free, not CLIP); CLIP needs no vocabulary.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dualnerf.encoders.base import EncoderError


def proxy_vocabulary(folder: Path, edit_id: str, names: Sequence[str], originals: np.ndarray
                     ) -> dict[str, np.ndarray]:
    """`names`/`originals`: the views (file names, (N,H,W,3) uint8 images) to define the captions with."""
    from dualnerf.scenes.spec import load_gt_edit, load_scene_spec

    spec = load_scene_spec(Path(folder))
    edit = spec.edit(edit_id)
    edited = []
    for name, original in zip(names, originals):
        loaded = load_gt_edit(folder, edit_id, name)
        if loaded is None:
            continue
        gt = loaded[0]
        if gt.shape != original.shape:
            raise EncoderError(f"{folder}/gt/edits/{edit_id}/images/{name} is {gt.shape[1]}x{gt.shape[0]} but the "
                               f"view is {original.shape[1]}x{original.shape[0]}; rerun preprocess.")
        edited.append(gt)
    if not edited:
        raise EncoderError(f"{folder}/gt/edits/{edit_id}/ has no ground-truth edited views, so the proxy encoder "
                           f"cannot define the edit's captions; use encoder 'clip' with a CLIP model folder.")
    edited = np.stack(edited)
    return {edit.source_caption: np.asarray(originals), edit.target_caption: edited, edit.instruction: edited}
