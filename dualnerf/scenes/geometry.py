"""Analytic primitives for the procedural ray caster: ray-surface hits, vectorised over rays.

Each primitive lives in a local frame (rotation `R`: local -> world columns, centre `c`); rays are moved
into that frame, intersected with a canonical shape and the normal is moved back. `hit(o, d)` returns
(t, normal) with t = inf where the ray misses; only hits with t > EPS count (no self-shadowing).
Convex shapes (polyhedra, cylinders, ellipsoids) cover every prop: a box, a tent prism and a pyramid
are all convex polyhedra given as half-spaces n.x <= d.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

EPS = 1e-4


def rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@dataclass(frozen=True)
class Primitive:
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))

    def hit(self, o: np.ndarray, d: np.ndarray, candidates: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
        """`candidates`: indices of the rays that may hit (the caller's bounding-sphere test); the
        others get t = inf without being traced."""
        if candidates is None:
            return self.hit_rays(o, d)
        t = np.full(len(o), np.inf)
        n = np.zeros_like(o)
        t[candidates], n[candidates] = self.hit_rays(o[candidates], d[candidates])
        return t, n

    def hit_rays(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(t, world normal) for every ray given."""
        o_local = (o - np.asarray(self.centre)) @ self.rotation
        d_local = d @ self.rotation
        t, n_local = self._hit_local(o_local, d_local)
        return t, n_local @ self.rotation.T

    def bound(self) -> tuple[np.ndarray, float] | None:
        """A world-space bounding sphere (centre, radius), or None for unbounded shapes."""
        return None

    def _hit_local(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError


def _first_positive(t_enter: np.ndarray, t_exit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of an interval [t_enter, t_exit] along the ray seen from outside; inf on a miss."""
    ok = (t_enter <= t_exit) & (t_enter > EPS)
    return np.where(ok, t_enter, np.inf), ok


@dataclass(frozen=True)
class Disk(Primitive):
    """The ground: the plane z = 0 (local) up to `radius`, facing +z."""

    radius: float = 1.0

    def _hit_local(self, o, d):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -o[:, 2] / d[:, 2]
        p = o + t[:, None] * d
        ok = (d[:, 2] < 0) & (t > EPS) & (p[:, 0] ** 2 + p[:, 1] ** 2 <= self.radius ** 2)
        n = np.zeros_like(o)
        n[:, 2] = 1.0
        return np.where(ok, t, np.inf), n


@dataclass(frozen=True)
class Polyhedron(Primitive):
    """Convex polyhedron {x : normals @ x <= offsets} (normals need not be unit)."""

    normals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    offsets: np.ndarray = field(default_factory=lambda: np.zeros(0))
    bound_radius: float = np.inf     # radius around `centre` that contains the solid

    def bound(self):
        if not np.isfinite(self.bound_radius):
            return None
        return np.asarray(self.centre, float), self.bound_radius

    def _hit_local(self, o, d):
        n_rays = len(o)
        t_enter = np.full(n_rays, -np.inf)
        t_exit = np.full(n_rays, np.inf)
        enter_face = np.zeros(n_rays, dtype=np.int64)
        for k, (normal, offset) in enumerate(zip(self.normals, self.offsets)):
            denom = d @ normal
            num = offset - o @ normal
            with np.errstate(divide="ignore", invalid="ignore"):
                t = num / denom
            entering = denom < 0
            leaving = denom > 0
            parallel_out = (denom == 0) & (num < 0)
            better = entering & (t > t_enter)
            t_enter = np.where(better, t, t_enter)
            enter_face = np.where(better, k, enter_face)
            t_exit = np.where(leaving, np.minimum(t_exit, t), t_exit)
            t_exit = np.where(parallel_out, -np.inf, t_exit)
        t, _ = _first_positive(t_enter, t_exit)
        unit = self.normals / np.linalg.norm(self.normals, axis=1, keepdims=True)
        return t, unit[enter_face]


def box(centre, half_extent, angle: float = 0.0) -> Polyhedron:
    """An axis-aligned box in its frame (turned by `angle` about z), resting where `centre` says."""
    hx, hy, hz = half_extent
    normals = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    offsets = np.array([hx, hx, hy, hy, hz, hz], float)
    return Polyhedron(centre=tuple(centre), rotation=rotation_z(angle), normals=normals, offsets=offsets,
                      bound_radius=float(np.linalg.norm(half_extent)))


def prism_tent(centre, length: float, width: float, height: float, angle: float = 0.0) -> Polyhedron:
    """A ridge tent: a triangular prism on the ground, ridge along local x at `height`."""
    half_w, half_l = width / 2.0, length / 2.0
    # Sloped sides pass through (y=+-half_w, z=0) and the ridge (y=0, z=height).
    normals = np.array([[0, height, half_w], [0, -height, half_w], [0, 0, -1], [1, 0, 0], [-1, 0, 0]], float)
    offsets = np.array([height * half_w, height * half_w, 0.0, half_l, half_l], float)
    return Polyhedron(centre=tuple(centre), rotation=rotation_z(angle), normals=normals, offsets=offsets,
                      bound_radius=float(np.sqrt(half_l ** 2 + half_w ** 2 + height ** 2)))


def pyramid(centre, radius: float, height: float, sides: int = 8, angle: float = 0.0) -> Polyhedron:
    """A `sides`-sided pyramid (a faceted cone, e.g. a conifer crown) with its base at local z = 0."""
    phis = angle + 2 * np.pi * (np.arange(sides) + 0.5) / sides
    apothem = radius * np.cos(np.pi / sides)
    # Side k: through the base edge at distance `apothem` along (cos, sin) and the apex (0, 0, height).
    side = np.stack([height * np.cos(phis), height * np.sin(phis), np.full(sides, apothem)], axis=1)
    normals = np.concatenate([side, [[0.0, 0.0, -1.0]]])
    offsets = np.concatenate([np.full(sides, height * apothem), [0.0]])
    return Polyhedron(centre=tuple(centre), normals=normals, offsets=offsets,
                      bound_radius=float(np.hypot(radius, height)))


@dataclass(frozen=True)
class Ellipsoid(Primitive):
    radii: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def bound(self):
        return np.asarray(self.centre, float), float(max(self.radii))

    def _hit_local(self, o, d):
        r = np.asarray(self.radii)
        os_, ds = o / r, d / r
        a = np.einsum("ij,ij->i", ds, ds)
        b = 2.0 * np.einsum("ij,ij->i", os_, ds)
        c = np.einsum("ij,ij->i", os_, os_) - 1.0
        disc = b * b - 4 * a * c
        root = np.sqrt(np.maximum(disc, 0.0))
        t_enter = np.where(disc >= 0, (-b - root) / (2 * a), np.inf)
        t_exit = np.where(disc >= 0, (-b + root) / (2 * a), -np.inf)
        t, _ = _first_positive(t_enter, t_exit)
        p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        n = p / (r * r)
        return t, n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


@dataclass(frozen=True)
class Cylinder(Primitive):
    """A capped cylinder along local z from 0 to `height` (rotate it to lay a log down)."""

    radius: float = 1.0
    height: float = 1.0

    def bound(self):
        middle = np.asarray(self.centre, float) + self.rotation[:, 2] * self.height / 2
        return middle, float(np.hypot(self.radius, self.height / 2))

    def _hit_local(self, o, d):
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = 2.0 * (o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1])
        c = o[:, 0] ** 2 + o[:, 1] ** 2 - self.radius ** 2
        disc = b * b - 4 * a * c
        axial = a < 1e-12
        root = np.sqrt(np.maximum(disc, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            side_in = np.where(axial, np.where(c <= 0, -np.inf, np.inf), (-b - root) / (2 * a))
            side_out = np.where(axial, np.where(c <= 0, np.inf, -np.inf), (-b + root) / (2 * a))
            side_in = np.where(~axial & (disc < 0), np.inf, side_in)
            side_out = np.where(~axial & (disc < 0), -np.inf, side_out)
            ta = (0.0 - o[:, 2]) / d[:, 2]
            tb = (self.height - o[:, 2]) / d[:, 2]
        flat = np.abs(d[:, 2]) < 1e-12
        inside_slab = (o[:, 2] >= 0) & (o[:, 2] <= self.height)
        slab_in = np.where(flat, np.where(inside_slab, -np.inf, np.inf), np.minimum(ta, tb))
        slab_out = np.where(flat, np.where(inside_slab, np.inf, -np.inf), np.maximum(ta, tb))
        t_enter = np.maximum(side_in, slab_in)
        t_exit = np.minimum(side_out, slab_out)
        t, _ = _first_positive(t_enter, t_exit)
        p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        from_side = side_in >= slab_in
        n = np.zeros_like(o)
        n[:, 0] = np.where(from_side, p[:, 0] / self.radius, 0.0)
        n[:, 1] = np.where(from_side, p[:, 1] / self.radius, 0.0)
        n[:, 2] = np.where(from_side, 0.0, -np.sign(d[:, 2]))
        return t, n


@dataclass(frozen=True)
class Dome(Primitive):
    """The background: the inside of a sphere of `radius` around the centre (always hit from inside)."""

    radius: float = 10.0

    def _hit_local(self, o, d):
        a = np.einsum("ij,ij->i", d, d)
        b = 2.0 * np.einsum("ij,ij->i", o, d)
        c = np.einsum("ij,ij->i", o, o) - self.radius ** 2
        disc = np.maximum(b * b - 4 * a * c, 0.0)
        t = (-b + np.sqrt(disc)) / (2 * a)
        t = np.where(t > EPS, t, np.inf)
        p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        return t, -p / self.radius
