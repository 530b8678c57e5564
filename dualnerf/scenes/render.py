"""A vectorised ray caster: primary hits, a shadow ray toward the sun, Lambert shading plus ambient.

Geometry (hits, normals, shadows) is traced once per view and shared by every material variant, so
ground-truth edited views cost only the recolouring. Pixels are supersampled `supersample`^2 times and
box-averaged, which equals integrating over the pixel area (pixel centres at integer + 0.5).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from dualnerf.scenes.geometry import Dome, Primitive
from dualnerf.scenes.materials import Material, Palette, snow_albedo, snow_cover


@dataclass(frozen=True)
class SceneObject:
    name: str
    primitive: Primitive
    material: Material


@dataclass(frozen=True)
class Variant:
    """A variant of the scene: palettes swapped by material tag, optionally snow on top (of colour
    `snow_colour`, default fresh white snow), a light colour
    (a global tint of every surface and the sky, e.g. sunset), and objects added or removed (by name).

    Added objects go after the world's own, and removed ones are hidden rather than dropped, so every
    other object keeps its index and hence its texture seed: outside what the edit touches, the
    variant renders exactly like the original.
    """

    id: str
    recolour: dict[str, Palette] = field(default_factory=dict)
    snow: bool = False
    snow_colour: tuple[float, float, float] | None = None
    light: tuple[float, float, float] | None = None
    add: tuple[SceneObject, ...] = ()
    remove: tuple[str, ...] = ()

    @property
    def changes_geometry(self) -> bool:
        return bool(self.add or self.remove)

    def apply(self, world: World) -> World:
        """The world this variant renders: the original plus `add`, with `remove` hidden."""
        if not self.changes_geometry:
            return world
        names = {o.name for o in world.objects}
        unknown = sorted(set(self.remove) - names)
        if unknown:
            raise ValueError(f"variant '{self.id}' removes unknown object(s) {', '.join(unknown)}")
        return dataclasses.replace(world, objects=world.objects + tuple(self.add),
                                   hidden=world.hidden | frozenset(self.remove))


@dataclass(frozen=True)
class World:
    objects: tuple[SceneObject, ...]
    sun_direction: tuple[float, float, float] = (0.45, -0.35, 0.82)   # toward the sun
    sun_strength: float = 0.85
    ambient: float = 0.38
    seed: int = 0
    hidden: frozenset[str] = frozenset()     # objects left out of the render (removed by an edit)


@dataclass
class Geometry:
    """What one view's rays hit, at supersampled resolution (flattened)."""

    object_index: np.ndarray    # (R,) index into World.objects
    points: np.ndarray          # (R, 3)
    normals: np.ndarray         # (R, 3) facing the camera
    footprint: np.ndarray       # (R,) world size of one (sub)pixel at the hit
    lit: np.ndarray             # (R,) 1 where the sun is visible from the hit, 0 in shadow


def camera_rays(c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int, height: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """World-space ray origins and unit directions for every pixel centre, OpenCV camera axes."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    d_cam = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
    d = d_cam @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.broadcast_to(c2w[:3, 3], d.shape).copy(), d


def _cone_candidates(origin: np.ndarray, d: np.ndarray, bound) -> np.ndarray | None:
    """Rays from one shared origin that pass through a bounding sphere: one dot product per ray."""
    if bound is None:
        return None
    centre, radius = bound
    v = centre - origin
    dist = float(np.linalg.norm(v))
    if dist <= radius:
        return None
    return np.nonzero(d @ (v / dist) >= np.sqrt(1.0 - (radius / dist) ** 2))[0]


def _parallel_candidates(o_plane: np.ndarray, o_along: np.ndarray, basis: np.ndarray, bound
                         ) -> np.ndarray | None:
    """Parallel rays (origins projected on the plane across the direction) that pass through a sphere
    in front of their origin."""
    if bound is None:
        return None
    centre, radius = bound
    offset = o_plane - centre @ basis[:, :2]
    near_axis = np.einsum("ij,ij->i", offset, offset) <= radius * radius
    return np.nonzero(near_axis & (o_along < centre @ basis[:, 2] + radius))[0]


def trace(world: World, o: np.ndarray, d: np.ndarray, pixel_angle: float) -> Geometry:
    """Primary hits of rays that share one origin (a pinhole camera)."""
    t_best = np.full(len(o), np.inf)
    index = np.full(len(o), -1, dtype=np.int64)
    normals = np.zeros_like(o)
    for k, obj in enumerate(world.objects):
        if obj.name in world.hidden:
            continue
        rays = _cone_candidates(o[0], d, obj.primitive.bound())
        if rays is None:
            rays = np.arange(len(o))
        t, n = obj.primitive.hit_rays(o[rays], d[rays])
        closer = t < t_best[rays]
        nearer = rays[closer]
        t_best[nearer], index[nearer], normals[nearer] = t[closer], k, n[closer]
    if np.any(index < 0):
        raise RuntimeError("some camera rays hit nothing; the scene needs a background dome around the cameras")
    points = o + t_best[:, None] * d
    cosine = np.abs(np.einsum("ij,ij->i", normals, d))
    # A grazing view stretches the pixel over more surface: widen the footprint (capped) so the
    # noise prefilter removes detail that would alias.
    footprint = t_best * pixel_angle / np.maximum(cosine, 0.25)
    normals = np.where((np.einsum("ij,ij->i", normals, d) > 0)[:, None], -normals, normals)
    lit = _sun_visibility(world, points, normals, index)
    return Geometry(index, points.astype(np.float64), normals, footprint.astype(np.float32), lit)


def _sun_visibility(world: World, points, normals, index) -> np.ndarray:
    sun = np.asarray(world.sun_direction, dtype=np.float64)
    sun = sun / np.linalg.norm(sun)
    emissive = np.array([o.material.emissive for o in world.objects])[index]
    lit = np.ones(len(points), dtype=np.float32)
    todo = ~emissive
    o = points[todo] + 1e-3 * normals[todo]
    d = np.broadcast_to(sun, o.shape)
    basis = _sun_basis(sun)
    o_projected = o @ basis
    blocked = np.zeros(len(o), dtype=bool)
    for obj in world.objects:
        if isinstance(obj.primitive, Dome) or obj.name in world.hidden:
            continue
        rays = _parallel_candidates(o_projected[:, :2], o_projected[:, 2], basis, obj.primitive.bound())
        rays = np.nonzero(~blocked)[0] if rays is None else rays[~blocked[rays]]
        t, _ = obj.primitive.hit_rays(o[rays], d[rays])
        blocked[rays[np.isfinite(t)]] = True
    lit[todo] = np.where(blocked, 0.0, 1.0)
    return lit


def _sun_basis(sun: np.ndarray) -> np.ndarray:
    """An orthonormal basis whose third axis is the (unit) sun direction, for parallel-ray culling."""
    basis = np.linalg.qr(np.stack([sun, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], axis=1))[0]
    return np.roll(basis, -1, axis=1) * np.sign(basis[:, 0] @ sun)


def retrace_edit(world: World, edited: World, base: Geometry, o: np.ndarray, d: np.ndarray,
                 pixel_angle: float) -> tuple[np.ndarray, Geometry | None]:
    """Rays whose hit or shadow a geometry edit can change, and their geometry in the `edited` world.

    A ray is affected when it passes through the bounding sphere of an added or removed object, hit a
    removed object, or its hit's shadow ray passes through such a sphere. Every other ray sees exactly
    what it saw in `world`, so re-tracing only the affected ones renders the edited view exactly, at
    a fraction of a full trace. Returns (ray indices, their Geometry), or (empty, None) if none.
    """
    everything = np.arange(len(o))
    own = len(world.objects)
    added = list(edited.objects[own:])
    removed = [k for k, obj in enumerate(world.objects) if obj.name in edited.hidden - world.hidden]
    sun = np.asarray(world.sun_direction, dtype=np.float64)
    sun = sun / np.linalg.norm(sun)
    basis = _sun_basis(sun)
    projected = (base.points + 1e-3 * base.normals) @ basis
    affected = np.zeros(len(o), dtype=bool)
    for obj in added + [world.objects[k] for k in removed]:
        bound = obj.primitive.bound()
        rays = _cone_candidates(o[0], d, bound)
        if bound is None or rays is None:            # unbounded, or the camera is inside its sphere
            return everything, trace(edited, o, d, pixel_angle)
        affected[rays] = True
        affected[_parallel_candidates(projected[:, :2], projected[:, 2], basis, bound)] = True
    for k in removed:
        affected |= base.object_index == k
    rays = np.nonzero(affected)[0]
    if len(rays) == 0:
        return rays, None
    return rays, trace(edited, o[rays], d[rays], pixel_angle)


def shade(world: World, geometry: Geometry, variant: Variant | None = None,
          fields: dict[int, dict] | None = None) -> np.ndarray:
    """Display RGB colours (R, 3) in [0, 1] of the traced hits under a material variant."""
    variant = variant or Variant("original")
    sun = np.asarray(world.sun_direction, dtype=np.float64)
    sun = sun / np.linalg.norm(sun)
    colour = np.zeros((len(geometry.points), 3), dtype=np.float32)
    for k, obj in enumerate(world.objects):
        sel = np.nonzero(geometry.object_index == k)[0]
        if len(sel) == 0:
            continue
        material = obj.material
        p, fp = geometry.points[sel], geometry.footprint[sel]
        seed = _material_seed(world.seed, k)
        palette = variant.recolour.get(material.tag)
        pattern = fields[k] if fields is not None and k in fields else material.pattern_fields(p, fp, seed)
        albedo = material.colour(pattern, palette)
        if material.emissive:
            colour[sel] = albedo
            continue
        n = geometry.normals[sel]
        if variant.snow:
            cover = snow_cover(p, n, fp, world.seed)[:, None]
            albedo = albedo * (1 - cover) + snow_albedo(p, fp, world.seed, variant.snow_colour) * cover
        lambert = np.maximum(n @ sun, 0.0).astype(np.float32) * geometry.lit[sel]
        # Ambient light comes from the sky above: surfaces facing down get less of it.
        ambient = world.ambient * (0.75 + 0.25 * n[:, 2]).astype(np.float32)
        colour[sel] = albedo * (ambient + world.sun_strength * lambert)[:, None]
    if variant.light is not None:
        colour = colour * np.asarray(variant.light, dtype=np.float32)
    return np.clip(colour, 0.0, 1.0)


def _material_seed(world_seed: int, k: int) -> int:
    return int(np.random.default_rng([world_seed, k]).integers(0, 2**31))


def pattern_fields(world: World, geometry: Geometry) -> dict[int, dict]:
    """Texture noise fields per visible object, shared by every material variant of the view."""
    out = {}
    for k, obj in enumerate(world.objects):
        sel = np.nonzero(geometry.object_index == k)[0]
        if len(sel):
            out[k] = obj.material.pattern_fields(geometry.points[sel], geometry.footprint[sel],
                                                 _material_seed(world.seed, k))
    return out


def to_image(colour: np.ndarray, width: int, height: int, supersample: int) -> np.ndarray:
    """Box-average supersampled colours into an 8-bit (H, W, 3) image."""
    s = supersample
    img = colour.reshape(height, s, width, s, 3).mean(axis=(1, 3))
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)

