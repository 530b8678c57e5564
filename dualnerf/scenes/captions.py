"""Caption images: what an edit's target caption looks like, made from the ORIGINAL views and the edit's
specification in the scene library (palettes, snow, light), never from its ground-truth renders.

The weight-free proxy encoder has no text model; it embeds a caption as the mean image feature of a
stack of images (dualnerf.encoders.vocabulary). Defining the target caption by the ground-truth edited
views would hand the consistency indicator (CCI) and the C_t2i metric the answer. Instead each original
view is edited in image space the way the specification reads, as a text model would know it ("blue"
is this palette, "snow" is white on the ground) without knowing where exactly the edit lands:

  - every pixel is assigned to the scene material (and palette colour) nearest in chromaticity, from
    the materials the scene library lists (the renderer's shading scales brightness, not chromaticity);
  - recolour: pixels of a recoloured material are scaled channel-wise by new / old palette colour;
  - snow: every non-emissive pixel is mixed half-way (SNOW_CAPTION_COVER) toward the snow colour at
    the pixel's estimated shading (its luminance over its palette colour's);
  - light: every pixel is multiplied by the light colour.
Geometry edits (objects added or removed) have no image-space reading without the object's position:
`caption_images` returns None for them, and the caller falls back to something else (and says so).
"""
from __future__ import annotations

import numpy as np

from dualnerf.scenes.library import BUILDERS, SCENES
from dualnerf.scenes.materials import SNOW

SNOW_CAPTION_COVER = 0.5        # the share of each surface a caption's "snow" paints (a reading, not the render)


def _chroma(rgb: np.ndarray) -> np.ndarray:
    return rgb / np.maximum(rgb.sum(axis=-1, keepdims=True), 1e-3)


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.299, 0.587, 0.114], np.float32)


def scene_materials(scene: str, seed: int = 0) -> dict:
    """{tag: (palette (3,3) float32, emissive)} of the materials scene `scene` is made of."""
    if scene not in BUILDERS:
        raise KeyError(scene)
    builder, _ = BUILDERS[scene]
    world = builder(SCENES[scene], seed)
    return {o.material.tag: (np.asarray(o.material.palette, np.float32), o.material.emissive)
            for o in world.objects}


def caption_images(scene: str, edit_id: str, originals: np.ndarray) -> np.ndarray | None:
    """(N,H,W,3) uint8 images standing for edit `edit_id`'s target caption, made from `originals` (N,H,W,3)
    uint8 and the edit's specification; None for scenes outside the library and for geometry edits."""
    if scene not in BUILDERS:
        return None
    edit = next((e for e in BUILDERS[scene][1] if e.id == edit_id), None)
    if edit is None:
        return None
    variant = edit.variant
    if not (variant.recolour or variant.snow or variant.light is not None):
        return None
    materials = scene_materials(scene)
    tags = list(materials)
    palettes = np.stack([materials[t][0] for t in tags])                  # (M, 3 colours, 3)
    emissive = np.array([materials[t][1] for t in tags])
    if np.asarray(originals).dtype != np.uint8:
        raise TypeError(f"caption_images: originals must be uint8 images, got {np.asarray(originals).dtype}")
    originals = np.asarray(originals)
    # Every step below maps a pixel's colour to an output colour, pixel by pixel: compute it once per
    # distinct colour (campsite's 48 views: ~70k of 2.4M pixels) and scatter back. Same bits, ~30x less
    # work and memory than the (pixels, materials, 3) distance array.
    packed = originals.reshape(-1, 3).astype(np.int32) @ np.array([65536, 256, 1], np.int32)
    colours, pixel_colour = np.unique(packed, return_inverse=True)
    rgb = np.stack([colours >> 16, (colours >> 8) & 255, colours & 255], axis=-1).astype(np.uint8)
    flat = rgb.astype(np.float32) / 255.0
    distance = np.linalg.norm(_chroma(flat)[:, None, None, :] - _chroma(palettes)[None], axis=-1)   # (P, M, 3)
    best = distance.reshape(len(flat), -1).argmin(axis=1)
    material, entry = best // 3, best % 3
    own = palettes[material, entry]                                       # (P, 3) the pixel's palette colour
    out = flat.copy()
    for tag, palette in variant.recolour.items():
        if tag not in materials:
            continue
        sel = material == tags.index(tag)
        new = np.asarray(palette, np.float32)[entry[sel]]
        out[sel] = flat[sel] * new / np.maximum(own[sel], 0.02)
    if variant.snow:
        solid = ~emissive[material]
        shading = np.clip(_luminance(flat[solid]) / np.maximum(_luminance(own[solid]), 1e-3), 0.2, 1.5)
        snow = np.asarray(variant.snow_colour or SNOW[0], np.float32)[None] * shading[:, None]
        out[solid] = (1.0 - SNOW_CAPTION_COVER) * out[solid] + SNOW_CAPTION_COVER * snow
    if variant.light is not None:
        out = out * np.asarray(variant.light, np.float32)
    per_colour = (np.clip(out, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return per_colour[pixel_colour.reshape(-1)].reshape(originals.shape)
