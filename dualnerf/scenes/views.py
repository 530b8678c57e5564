"""Ground truth at new cameras: render a procedural scene (original and edited) from cameras given in a
preprocessed dataset's normalised frame.

A dataset's cameras are the scene's cameras up to a similarity: preprocess normalises them into
[-1, 1]^3 (isotropic scale + offset) and, with SfM, recovers them in an arbitrary frame of its own. The
similarity is fitted (Umeyama) between the dataset's camera centres and the scene's true centres of the
same views (matched by file name), then checked on the camera orientations, so a camera path through
the dataset's cameras maps to the scene cameras it stands for.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dualnerf.scenes.generate import edit_ground_truth, render_view, scene_cameras, scene_config, view_name
from dualnerf.scenes.library import BUILDERS
from dualnerf.scenes.spec import SceneSpecError, load_scene_spec

MAX_ROTATION_RESIDUAL_DEGREES = 2.0     # SfM recovers rotations to well under a degree on these scenes
MAX_CENTRE_RESIDUAL = 0.02              # ... and centres to ~1% of the camera-ring radius


@dataclass(frozen=True)
class Similarity:
    """x_scene = scale * rotation @ x_dataset + translation; camera axes rotate by `rotation`."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    rotation_residual_degrees: float     # largest angle between mapped and true camera orientations
    centre_residual: float               # largest mapped-centre error / camera-ring radius

    def apply(self, c2w: np.ndarray) -> np.ndarray:
        out = np.array(c2w, dtype=np.float64, copy=True)
        out[..., :3, :3] = self.rotation @ out[..., :3, :3]
        out[..., :3, 3] = self.scale * out[..., :3, 3] @ self.rotation.T + self.translation
        return out


def fit_similarity(dataset_c2w: np.ndarray, scene_c2w: np.ndarray, where: str) -> Similarity:
    """The similarity taking the dataset cameras onto the scene cameras (same views, same order)."""
    from dualnerf.io.align import umeyama

    if len(dataset_c2w) < 3:
        raise SceneSpecError(f"{where}: need at least 3 registered views to place the dataset in the scene "
                             f"frame, got {len(dataset_c2w)}.")
    scale, rotation, translation = umeyama(dataset_c2w[:, :3, 3], scene_c2w[:, :3, 3])
    mapped = Similarity(scale, rotation, translation, 0.0, 0.0).apply(dataset_c2w)
    relative = np.einsum("nji,njk->nik", mapped[:, :3, :3], scene_c2w[:, :3, :3])
    cos = np.clip((np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rotation_residual = float(np.degrees(np.arccos(cos)).max())
    radius = float(np.linalg.norm(scene_c2w[:, :3, 3] - scene_c2w[:, :3, 3].mean(0), axis=1).mean())
    centre_residual = float(np.linalg.norm(mapped[:, :3, 3] - scene_c2w[:, :3, 3], axis=1).max() / radius)
    if rotation_residual > MAX_ROTATION_RESIDUAL_DEGREES or centre_residual > MAX_CENTRE_RESIDUAL:
        raise SceneSpecError(
            f"{where}: the dataset's cameras do not match the scene's after a similarity (orientation error up "
            f"to {rotation_residual:.2f} deg, centre error up to {100 * centre_residual:.1f}% of the camera "
            f"radius); the dataset was not made from this scene, or its SfM failed. Rerun preprocess (method "
            f"'nerfstudio' uses the scene's true cameras).")
    return Similarity(scale, rotation, translation, rotation_residual, centre_residual)


class SceneViewRenderer:
    """Renders the scene a dataset folder was made from (its scene.toml names the procedural scene) at
    cameras in the dataset's normalised frame: the original view, and an edit's ground-truth view+mask."""

    def __init__(self, data_dir: Path, dataset, supersample: int = 0):
        data_dir = Path(data_dir)
        spec = load_scene_spec(data_dir)
        if spec.name not in BUILDERS:
            raise SceneSpecError(f"{data_dir / 'scene.toml'} names scene '{spec.name}', which is not a procedural "
                                 f"scene ({', '.join(sorted(BUILDERS))}); its views cannot be re-rendered.")
        overrides = {"width": spec.width, "height": spec.height}
        n_views = _scene_toml_int(data_dir, "n_views")
        if n_views:
            overrides["n_views"] = n_views
        if supersample:
            overrides["supersample"] = supersample
        self.config = scene_config(spec.name, **overrides)
        builder, edits = BUILDERS[spec.name]
        self.edits = {e.id: e for e in edits}
        self.world = builder(self.config, spec.seed)
        self.spec = spec
        scene_c2w, _ = scene_cameras(self.config)
        by_name = {view_name(i): c for i, c in enumerate(scene_c2w)}
        missing = [n for n in dataset.names if n not in by_name]
        if missing:
            raise SceneSpecError(f"{data_dir}: views {', '.join(missing[:5])} are not views of scene "
                                 f"'{spec.name}' with {self.config.n_views} views; rerun preprocess on the scene.")
        self.to_scene = fit_similarity(dataset.c2w, np.stack([by_name[n] for n in dataset.names]),
                                       where=str(data_dir))

    def render(self, c2w: np.ndarray, edit_id: str, size: tuple[int, int]
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(original, ground-truth edited, mask) at dataset-frame camera `c2w`, resized to (width, height)
        with the area filter as preprocess resizes the stored ground truth."""
        import cv2

        if edit_id not in self.edits:
            raise SceneSpecError(f"scene '{self.spec.name}' has no edit '{edit_id}'; its edits are: "
                                 f"{', '.join(self.edits)}.")
        images, _ = render_view(self.config, self.world, self.to_scene.apply(c2w),
                                [None, self.edits[edit_id].variant])
        original = images[None]
        edited, mask = edit_ground_truth(original, images[edit_id], self.config.mask_threshold)
        if (original.shape[1], original.shape[0]) != tuple(size):
            original = cv2.resize(original, size, interpolation=cv2.INTER_AREA)
            edited = cv2.resize(edited, size, interpolation=cv2.INTER_AREA)
            mask = cv2.resize(mask.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0
        return original, edited, mask


def _scene_toml_int(data_dir: Path, key: str) -> int:
    import tomllib

    doc = tomllib.loads((Path(data_dir) / "scene.toml").read_text())
    value = doc.get("scene", {}).get(key, 0)
    return int(value) if isinstance(value, int) else 0
