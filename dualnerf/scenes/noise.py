"""Multi-octave 3D value noise in world coordinates, so a surface's texture is the same in every view.

Each octave uses its own random rotation and offset of the lattice (drawn from the seed), so octaves do
not line up and the pattern never repeats. Octaves finer than about two pixel footprints are faded
out (a cheap analytic prefilter): aliased texture would differ between views and defeat SIFT matching.
"""
from __future__ import annotations

import functools

import numpy as np

_PRIMES = np.array([0x8DA6B343, 0xD8163841, 0xCB1AB31F], dtype=np.uint32)


def _hash01(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, salt: int) -> np.ndarray:
    """A deterministic pseudo-random value in [0, 1) per integer lattice point (integer mixing hash)."""
    return _mix01((ix.astype(np.uint32) * _PRIMES[0]) ^ (iy.astype(np.uint32) * _PRIMES[1])
                  ^ (iz.astype(np.uint32) * _PRIMES[2]), salt)


def _mix01(h: np.ndarray, salt: int) -> np.ndarray:
    h = h ^ np.uint32(salt & 0xFFFFFFFF)
    h ^= h >> np.uint32(13)
    h *= np.uint32(0x5BD1E995)
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x27D4EB2D)
    h ^= h >> np.uint32(16)
    return h.astype(np.float32) * np.float32(1.0 / 4294967296.0)


def value_noise(p: np.ndarray, salt: int) -> np.ndarray:
    """Smoothly interpolated lattice noise at points p (N, 3) in lattice units; values in [0, 1)."""
    cell = np.floor(p)
    f = (p - cell).astype(np.float32)
    w = f * f * (3.0 - 2.0 * f)          # smoothstep weights give a C1 pattern (no lattice creases)
    # Per-axis hash terms i * prime (mod 2^32); the neighbour's is one prime more, so each corner
    # costs two XORs instead of three multiplications (same values as _hash01).
    i = cell.astype(np.int64).astype(np.uint32)
    hx0, hy0, hz0 = i[:, 0] * _PRIMES[0], i[:, 1] * _PRIMES[1], i[:, 2] * _PRIMES[2]
    hx1, hy1, hz1 = hx0 + _PRIMES[0], hy0 + _PRIMES[1], hz0 + _PRIMES[2]
    wx, wy, wz = w[:, 0], w[:, 1], w[:, 2]

    def lerp(a, b, t):
        return a + (b - a) * t

    def edge(hy, hz):
        yz = hy ^ hz
        return lerp(_mix01(hx0 ^ yz, salt), _mix01(hx1 ^ yz, salt), wx)

    return lerp(lerp(edge(hy0, hz0), edge(hy1, hz0), wy), lerp(edge(hy0, hz1), edge(hy1, hz1), wy), wz)


@functools.lru_cache(maxsize=1024)
def _octave_frames(seed: int, octaves: int) -> tuple[tuple[np.ndarray, np.ndarray, int], ...]:
    """Per-octave lattice rotation, offset and hash salt (cached: every view reuses them)."""
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(octaves):
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        rotation = q * np.sign(np.diag(r))     # a uniformly random orthogonal frame per octave
        offset = rng.uniform(-1000.0, 1000.0, size=3)
        frames.append((rotation, offset, int(rng.integers(0, 2**32))))
    return tuple(frames)


def fbm(points: np.ndarray, frequency: float, octaves: int, seed: int,
        footprint: np.ndarray | None = None, gain: float = 0.55, lacunarity: float = 2.03) -> np.ndarray:
    """Fractal sum of value-noise octaves at world points (N, 3); zero-mean, roughly in [-0.5, 0.5].

    `frequency` is in cycles per world unit for the first octave; `footprint` (N,) is the world size of
    one pixel at each point, used to fade out octaves the image cannot resolve.
    """
    total = np.zeros(len(points), dtype=np.float32)
    norm = 0.0
    amplitude = 1.0
    freq = frequency
    smallest = float(np.min(footprint)) if footprint is not None and len(footprint) else 0.0
    for rotation, offset, salt in _octave_frames(seed, octaves):
        # Fade from full weight at 4 pixels per cycle to zero at 2 pixels per cycle.
        if freq * smallest < 0.5:                 # skip octaves no pixel can resolve
            p = (points @ rotation.T + offset) * freq
            octave = value_noise(p, salt) - 0.5
            if footprint is not None:
                octave *= np.clip(2.0 - 4.0 * freq * footprint, 0.0, 1.0).astype(np.float32)
            total += np.float32(amplitude) * octave
        norm += amplitude
        amplitude *= gain
        freq *= lacunarity
    return total / np.float32(norm)
