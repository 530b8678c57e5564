"""Render a procedural scene and its ground-truth edits into a scene folder (layout in `spec.py`)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from dualnerf.scenes.cameras import OPENCV_TO_OPENGL, orbit
from dualnerf.scenes.library import BUILDERS, SCENES, SceneConfig
from dualnerf.scenes.render import camera_rays, pattern_fields, retrace_edit, shade, to_image, trace
from dualnerf.scenes.spec import mode_edit_id

GENERATOR = "dualnerf.scenes procedural ray caster (synthetic scene, not a photograph)"
POINTS_PER_VIEW = 200


class SceneConfigError(ValueError):
    """An unknown scene name or override; the message lists what is allowed."""

    user_error = True        # the CLI prints the message and exits 2 (see pipeline.errors)


def scene_config(name: str, **overrides) -> SceneConfig:
    if name not in SCENES:
        raise SceneConfigError(f"unknown scene '{name}'; available scenes: {', '.join(sorted(SCENES))}.")
    config = SCENES[name]
    allowed = {f.name for f in dataclasses.fields(SceneConfig)} - {"name"}
    unknown = sorted(set(overrides) - allowed)
    if unknown:
        raise SceneConfigError(f"scene '{name}': unknown override(s) {', '.join(unknown)}; "
                               f"allowed: {', '.join(sorted(allowed))}.")
    config = dataclasses.replace(config, **overrides)
    if config.width < 16 or config.height < 16 or config.n_views < 3 or config.supersample < 1:
        raise SceneConfigError(f"scene '{name}': need width, height >= 16, n_views >= 3 and "
                               f"supersample >= 1, got {config.width}x{config.height}, "
                               f"{config.n_views} views, supersample {config.supersample}.")
    return config


def scene_cameras(config: SceneConfig) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """OpenCV c2w (N, 4, 4) and pinhole intrinsics (fx, fy, cx, cy) of the scene's views."""
    c2w = orbit(config.n_views, config.camera_radius, config.camera_height, config.arc_degrees,
                target=(0.0, 0.0, config.target_height), height_wobble=config.height_wobble)
    f = config.focal
    return c2w, (f, f, config.width / 2.0, config.height / 2.0)


def view_name(i: int) -> str:
    return f"view_{i:03d}.png"


def render_view(config: SceneConfig, world, c2w: np.ndarray, variants) -> tuple[dict, object]:
    """8-bit images of one view for each variant (None = original), plus the traced geometry."""
    s = config.supersample
    f = config.focal * s
    o, d = camera_rays(c2w, f, f, config.width * s / 2.0, config.height * s / 2.0,
                       config.width * s, config.height * s)
    geometry = trace(world, o, d, pixel_angle=1.0 / f)
    fields = pattern_fields(world, geometry)
    images = {}
    for variant in variants:
        colour = shade(world, geometry, variant, fields)
        if variant is not None and variant.changes_geometry:
            # Objects added or removed: re-trace the rays whose hit or shadow can change.
            edited = variant.apply(world)
            rays, edited_geometry = retrace_edit(world, edited, geometry, o, d, pixel_angle=1.0 / f)
            if edited_geometry is not None:
                colour[rays] = shade(edited, edited_geometry, variant)
        images[variant.id if variant else None] = to_image(colour, config.width, config.height, s)
    return images, geometry


def generate_scene(name: str, out: Path, *, seed: int = 0, format: str = "scene", workers: int = 1,
                   progress=None, **overrides) -> Path:
    """Render scene `name` into folder `out` (created) and return it.

    format "scene" writes the scene-folder layout; "nerfstudio" adds a top-level transforms.json
    (file paths relative to it), so the same views can be imported as a nerfstudio dataset.
    `overrides` replace SceneConfig fields (width, height, n_views, arc_degrees, supersample ...).
    `workers` > 1 renders views in that many processes (same result). `progress(done, total)` is
    called after each view.
    """
    if format not in ("scene", "nerfstudio"):
        raise SceneConfigError(f"unknown scene format '{format}'; use 'scene' or 'nerfstudio'.")
    config = scene_config(name, **overrides)
    _, edits = BUILDERS[name]
    c2w_all, intrinsics = scene_cameras(config)
    out = Path(out)
    folders = [e.id for e in edits] + [mode_edit_id(e.id, m.id) for e in edits for m in e.modes]
    for sub in ["images", "gt"] + [f"gt/edits/{f}/{k}" for f in folders for k in ("images", "masks")]:
        (out / sub).mkdir(parents=True, exist_ok=True)
    n = len(c2w_all)
    results = [None] * n
    if workers > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        # spawn, not fork: the caller may hold threads (torch, a progress bar) that fork would copy.
        with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(_render_and_write, name, seed, overrides, str(out), i): i for i in range(n)}
            for done, future in enumerate(as_completed(futures), 1):
                results[futures[future]] = future.result()
                if progress is not None:
                    progress(done, n)
    else:
        for i in range(n):
            results[i] = _render_and_write(name, seed, overrides, str(out), i)
            if progress is not None:
                progress(i + 1, n)
    points = np.concatenate([r[0] for r in results])
    colours = np.concatenate([r[1] for r in results])
    write_ply(out / "gt" / "sparse_pc.ply", points, colours)
    _write_transforms(out / "gt" / "transforms.json", c2w_all, intrinsics, config, prefix="../images/",
                      ply="sparse_pc.ply")
    if format == "nerfstudio":
        write_ply(out / "sparse_pc.ply", points, colours)
        _write_transforms(out / "transforms.json", c2w_all, intrinsics, config, prefix="images/",
                          ply="sparse_pc.ply")
    _write_scene_toml(out / "scene.toml", config, seed, edits)
    return out


def _render_and_write(name: str, seed: int, overrides: dict, out: str, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Render view `i` with its edits, write its files; return sparse points sampled from its hits."""
    from threadpoolctl import threadpool_limits

    # The ray caster's matrix products are (rays, 3) @ (3, 3): a threaded BLAS only adds contention
    # there (measured: campsite 10 s single-threaded vs 53 s with 2 OpenBLAS threads in each of 2
    # render processes). Parallelism comes from render processes, one per core.
    with threadpool_limits(limits=1, user_api="blas"):
        return _render_and_write_view(name, seed, overrides, Path(out), i)


def _render_and_write_view(name: str, seed: int, overrides: dict, out: Path, i: int
                           ) -> tuple[np.ndarray, np.ndarray]:
    import cv2

    config = scene_config(name, **overrides)
    builder, edits = BUILDERS[name]
    world = builder(config, seed)
    c2w = scene_cameras(config)[0][i]
    # Alternative modes render as variants named by their gt/edits/ folder (edit id "." mode id).
    modes = [dataclasses.replace(m, id=mode_edit_id(e.id, m.id)) for e in edits for m in e.modes]
    images, geometry = render_view(config, world, c2w, [None] + [e.variant for e in edits] + modes)
    original = images[None]
    _write_png(cv2, out / "images" / view_name(i), original)
    for folder in [e.id for e in edits] + [m.id for m in modes]:
        edited, mask = edit_ground_truth(original, images[folder], config.mask_threshold)
        _write_png(cv2, out / "gt/edits" / folder / "images" / view_name(i), edited)
        if not cv2.imwrite(str(out / "gt/edits" / folder / "masks" / view_name(i)), mask.astype(np.uint8) * 255):
            raise OSError(f"could not write a mask into {out}")
    rng = np.random.default_rng([seed, 7, i])   # sparse-point sampling only
    pick = rng.choice(len(geometry.points), size=min(POINTS_PER_VIEW, len(geometry.points)), replace=False)
    s = config.supersample
    rows, cols = (pick // (config.width * s)) // s, (pick % (config.width * s)) // s
    return geometry.points[pick], original[rows, cols]


def edit_ground_truth(original: np.ndarray, edited: np.ndarray, threshold: int) -> tuple[np.ndarray, np.ndarray]:
    """The edit mask (pixels changed by more than `threshold` in some channel) and the edited view with
    every unmasked pixel equal to the original, so 'outside the mask' means exactly unchanged."""
    diff = np.abs(edited.astype(np.int16) - original.astype(np.int16)).max(axis=-1)
    mask = diff > threshold
    return np.where(mask[..., None], edited, original), mask


def _write_png(cv2, path: Path, rgb: np.ndarray) -> None:
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise OSError(f"could not write {path}")


def _write_transforms(path: Path, c2w_all, intrinsics, config: SceneConfig, prefix: str, ply: str) -> None:
    fx, fy, cx, cy = intrinsics
    doc = {
        "camera_model": "PINHOLE", "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy,
        "w": config.width, "h": config.height, "ply_file_path": ply,
        "frames": [{"file_path": prefix + view_name(i), "transform_matrix": (c2w @ OPENCV_TO_OPENGL).tolist()}
                   for i, c2w in enumerate(c2w_all)],
    }
    path.write_text(json.dumps(doc, indent=1))


def _write_scene_toml(path: Path, config: SceneConfig, seed: int, edits) -> None:
    def q(text: str) -> str:
        return json.dumps(text)   # a JSON string literal is a valid TOML basic string

    lines = ["[scene]", f"name = {q(config.name)}", f"generator = {q(GENERATOR)}", f"seed = {seed}",
             f"width = {config.width}", f"height = {config.height}", f"n_views = {config.n_views}",
             f"camera_radius = {config.camera_radius}", ""]
    for e in edits:
        lines += ["[[edits]]", f"id = {q(e.id)}", f"instruction = {q(e.instruction)}",
                  f"source_caption = {q(e.source_caption)}", f"target_caption = {q(e.target_caption)}",
                  f"kind = {q(e.kind)}", f"modes = [{', '.join(q(m.id) for m in e.modes)}]", ""]
    path.write_text("\n".join(lines))


def write_ply(path: Path, points: np.ndarray, colours: np.ndarray) -> None:
    """ASCII PLY point cloud (x y z float, red green blue uchar), as nerfstudio's sparse_pc.ply."""
    header = ["ply", "format ascii 1.0", f"element vertex {len(points)}", "property float x",
              "property float y", "property float z", "property uchar red", "property uchar green",
              "property uchar blue", "end_header"]
    rows = [f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {c[0]} {c[1]} {c[2]}" for p, c in zip(points, colours)]
    path.write_text("\n".join(header + rows) + "\n")
