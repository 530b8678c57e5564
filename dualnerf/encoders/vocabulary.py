"""The proxy encoder's vocabulary for a scene folder: which images define each caption's embedding.

For a folder carrying scene.toml (a procedural scene, or a dataset preprocessed from one), from the
views the caller passes (the edit stage and evaluate pass the TRAINING views only, never the held-out
views the evaluation scores):
    source_caption                 <- the original views
    target_caption and instruction <- caption images: the original views edited in image space the way the
                                      edit's specification in the scene library reads (dualnerf.scenes.captions;
                                      no ground-truth render is used), where the specification allows it
                                   <- else (geometry edits, scenes outside the library) the ground-truth
                                      edited views: then the proxy's text embedding SEES THE GROUND TRUTH,
                                      and `vocabulary_source` says so.
Used only with the PROXY encoder (weight-free, not CLIP); CLIP needs no vocabulary.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dualnerf.encoders.base import EncoderError

SPEC = "edit specification (caption images from the original training views)"
GROUND_TRUTH = "ground-truth edited training views (SEES THE GROUND TRUTH)"


def proxy_vocabulary(folder: Path, edit_id: str, names: Sequence[str], originals: np.ndarray
                     ) -> dict[str, np.ndarray]:
    """`names`/`originals`: the views (file names, (N,H,W,3) uint8 images) to define the captions with."""
    return proxy_vocabulary_with_source(folder, edit_id, names, originals)[0]


def proxy_vocabulary_with_source(folder: Path, edit_id: str, names: Sequence[str], originals: np.ndarray
                                 ) -> tuple[dict[str, np.ndarray], str]:
    """The vocabulary and where its target caption comes from (SPEC or GROUND_TRUTH)."""
    from dualnerf.scenes.captions import caption_images
    from dualnerf.scenes.spec import load_scene_spec

    spec = load_scene_spec(Path(folder))
    edit = spec.edit(edit_id)
    originals = np.asarray(originals)
    edited = caption_images(spec.name, edit_id, originals)
    source = SPEC
    if edited is None:
        edited, source = _ground_truth_views(folder, edit_id, names, originals), GROUND_TRUTH
    return {edit.source_caption: originals, edit.target_caption: edited, edit.instruction: edited}, source


def _ground_truth_views(folder: Path, edit_id: str, names: Sequence[str], originals: np.ndarray) -> np.ndarray:
    from dualnerf.scenes.spec import load_gt_edit

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
    return np.stack(edited)
