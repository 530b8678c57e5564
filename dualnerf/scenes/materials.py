"""Procedural surface colours (albedo) from 3D noise in world coordinates.

A material is a palette of three colours and a pattern; the edits of a scene swap palettes of tagged
materials (a local recolouring such as "turn the tent blue") or lay snow on upward-facing surfaces.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualnerf.scenes.noise import _hash01, fbm

Palette = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]


def _smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


@dataclass(frozen=True)
class Material:
    """`pattern`: "mottled" (base/second colour blend with patches of the third), "planks" (wood boards
    across `plank_axis`), or "sky" (emissive background: distant hills below a noisy horizon, clouds above).
    `frequency` is in cycles per metre for the coarsest octave; `tag` names it for edits."""

    tag: str
    palette: Palette
    pattern: str = "mottled"
    frequency: float = 1.0
    octaves: int = 6
    patch_amount: float = 0.3
    detail: float = 0.35
    speckle: float = 0.3            # light and dark spots (pebbles, knots, lichen): blobs SIFT can match
    plank_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    plank_width: float = 0.12
    emissive: bool = False

    def albedo(self, p: np.ndarray, footprint: np.ndarray, seed: int, palette: Palette | None = None
               ) -> np.ndarray:
        return self.colour(self.pattern_fields(p, footprint, seed), palette)

    def pattern_fields(self, p: np.ndarray, footprint: np.ndarray, seed: int) -> dict[str, np.ndarray]:
        """The palette-independent part of the texture (noise fields), reusable across recolourings."""
        if self.pattern == "sky":
            return self._sky_fields(p, footprint, seed)
        blend = fbm(p, self.frequency, self.octaves, seed, footprint)
        patches = fbm(p, self.frequency * 0.7, self.octaves - 1, seed + 1, footprint)
        fine = fbm(p, self.frequency * 6.0, 4, seed + 2, footprint)
        mix = _smoothstep(-0.12, 0.12, blend)
        patch = _smoothstep(0.1 - self.patch_amount * 0.3, 0.14 - self.patch_amount * 0.3, patches)
        spots = fbm(p, self.frequency * 16.0, 3, seed + 3, footprint)
        speckle = _smoothstep(0.07, 0.15, spots) - _smoothstep(0.07, 0.15, -spots)
        shade = (1.0 + self.detail * 4.0 * fine) * (1.0 + self.speckle * speckle)
        if self.pattern == "planks":
            u = p @ np.asarray(self.plank_axis) / self.plank_width
            board = np.floor(u)
            zeros = np.zeros_like(board, dtype=np.int64)
            jitter = _hash01(board.astype(np.int64), zeros, zeros, seed) - 0.5
            gap = _smoothstep(0.0, 0.08, u - board) * _smoothstep(1.0, 0.92, u - board)
            shade = shade * (1.0 + 0.35 * jitter) * (0.45 + 0.55 * gap)
        return {"mix": mix, "patch": patch, "shade": shade}

    def colour(self, fields: dict[str, np.ndarray], palette: Palette | None = None) -> np.ndarray:
        colours = np.asarray(palette if palette is not None else self.palette, dtype=np.float32)
        if self.pattern == "sky":
            return self._sky_colour(fields, colours)
        mix, patch = fields["mix"][:, None], fields["patch"][:, None]
        colour = colours[0] * (1 - mix) + colours[1] * mix
        colour = colour * (1 - patch) + colours[2] * patch
        return np.clip(colour * fields["shade"][:, None], 0.0, 1.0).astype(np.float32)

    def _sky_fields(self, p: np.ndarray, footprint: np.ndarray, seed: int) -> dict[str, np.ndarray]:
        # Directions from the dome centre: elevation picks hills (palette[0]) or sky (palette[1]),
        # with clouds (palette[2]) in the sky.
        direction = p / np.linalg.norm(p, axis=1, keepdims=True)
        elevation = np.arcsin(np.clip(direction[:, 2], -1.0, 1.0))
        flat = direction * np.array([1.0, 1.0, 0.0])
        ridge = 0.10 + 0.5 * fbm(flat * 3.0, 1.0, 5, seed + 3)
        ground = fbm(p, self.frequency, self.octaves, seed + 4, footprint)
        cloud = fbm(direction * np.array([1.0, 1.0, 2.5]) * 2.0, 1.5, 6, seed + 5)
        return {"hills": (elevation < ridge).astype(np.float32), "ground": ground,
                "cloud": _smoothstep(-0.02, 0.12, cloud),
                "height": np.clip(elevation / (np.pi / 2), 0.0, 1.0).astype(np.float32)}

    def _sky_colour(self, fields: dict[str, np.ndarray], colours: np.ndarray) -> np.ndarray:
        hill_colour = colours[0] * (1.0 + 2.2 * fields["ground"])[:, None]
        height, cloud = fields["height"][:, None], fields["cloud"][:, None]
        sky = colours[1] * (1.0 - 0.35 * height) + 0.2 * (1 - height)
        sky = sky * (1 - cloud) + colours[2] * cloud
        hills = fields["hills"][:, None] > 0
        return np.clip(np.where(hills, hill_colour, sky), 0.0, 1.0).astype(np.float32)


SNOW = ((0.93, 0.94, 0.97), (0.86, 0.88, 0.93), (0.97, 0.97, 0.98))


def snow_cover(p: np.ndarray, normals: np.ndarray, footprint: np.ndarray, seed: int) -> np.ndarray:
    """Fraction of snow on a surface: fresh snow settles on upward-facing surfaces, patchily."""
    patchiness = fbm(p, 1.3, 5, seed + 11, footprint)
    return _smoothstep(0.35, 0.7, normals[:, 2] + 0.8 * patchiness).astype(np.float32)


def snow_albedo(p: np.ndarray, footprint: np.ndarray, seed: int,
                colour: tuple[float, float, float] | None = None) -> np.ndarray:
    """Snow's albedo: `colour` (default SNOW[0], fresh white snow) with fine sparkle."""
    sparkle = fbm(p, 4.0, 5, seed + 12, footprint)
    base = np.asarray(SNOW[0] if colour is None else colour, dtype=np.float32)
    return np.clip(base * (1.0 + 0.6 * sparkle)[:, None], 0.0, 1.0).astype(np.float32)
