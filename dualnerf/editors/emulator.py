"""An InstructPix2Pix EMULATOR (a simulator, not a diffusion model) for procedural scenes.

It knows each training view's ground-truth edited image and edit mask (from the scene's `gt/edits/`) and
reproduces the failure modes of IP2P that DualNeRF addresses, each with a knob and drawn per call from
a generator seeded by (seed, step):

  - noise level: a timestep fraction s ~ U[noise_range] as in Instruct-NeRF2NeRF. The output keeps the
    input render with weight (1 - s**render_dependence): at low noise the render's partial edit and its
    artefacts survive (this is how IDU locks into local optima; SA's retreated renders escape them).
  - inconsistency across views: per-call edit strength (multiplicative jitter), an RGB tint of the
    edited region, and a low-frequency random field modulating the strength spatially.
  - background drift and blur: a per-call colour gain/offset and a Gaussian blur outside the edit mask.
  - outright failures with probability `failure_rate`: the edit region painted a wrong colour, or a
    garbage image (the render washed over by random colour blobs).

The edited target is the original plus the (jittered) ground-truth change, so a render that already
carries the edit moves toward the ground truth and a render carrying garbage keeps part of it.
"""
from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from dualnerf.editors.base import EditorError, to_float_image, to_uint8_image

EMULATOR_VERSION = 1


@dataclass(frozen=True)
class EmulatorConfig:
    noise_range: tuple[float, float] = (0.02, 0.98)   # timestep fraction range (IN2N's lower/upper bound)
    render_dependence: float = 1.0      # weight of the render = 1 - s**render_dependence (0: ignore render)
    strength_jitter: float = 0.2        # std of the per-call multiplicative edit strength
    tint_jitter: float = 0.05           # std of a per-call RGB offset inside the edit region
    spatial_jitter: float = 0.3         # amplitude of the low-frequency strength field
    spatial_cells: int = 3              # resolution (cells per side) of that field
    background_drift: float = 0.04      # std of the per-call background colour gain and offset
    background_blur: float = 1.5        # the background blur sigma is drawn from U[0, this] pixels
    failure_rate: float = 0.15          # probability that a call fails outright
    mask_feather: float = 1.0           # Gaussian sigma (pixels) softening the ground-truth edit mask

    def __post_init__(self) -> None:
        lo, hi = self.noise_range
        if not 0.0 <= lo <= hi <= 1.0:
            raise EditorError(f"emulator noise_range must satisfy 0 <= low <= high <= 1, got {self.noise_range}.")
        if not 0.0 <= self.failure_rate <= 1.0:
            raise EditorError(f"emulator failure_rate must be in [0, 1], got {self.failure_rate}.")
        for name in ("render_dependence", "strength_jitter", "tint_jitter", "spatial_jitter",
                     "background_drift", "background_blur", "mask_feather"):
            if getattr(self, name) < 0:
                raise EditorError(f"emulator {name} must be >= 0, got {getattr(self, name)}.")


@dataclass(frozen=True)
class EmulatedView:
    original: np.ndarray     # HxWx3 uint8, the view's original training image
    gt_edit: np.ndarray      # HxWx3 uint8, the ground-truth edited view
    mask: np.ndarray         # HxW bool, True where the edit changes the colour


def _image_key(image: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(image).tobytes() + str(image.shape).encode()).hexdigest()


def _gaussian_blur(image: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 1e-3:
        return image
    import cv2

    return cv2.GaussianBlur(image, (0, 0), sigmaX=float(sigma), borderType=cv2.BORDER_REFLECT)


def _smooth_field(rng: np.random.Generator, cells: int, shape: tuple[int, int], channels: int = 1) -> np.ndarray:
    """A random low-frequency field N(0, ~1) of shape (H, W, channels), bicubically upsampled."""
    import cv2

    grid = rng.normal(size=(max(cells, 1), max(cells, 1), channels)).astype(np.float32)
    field = cv2.resize(grid, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    return field.reshape(shape[0], shape[1], channels)


class InstructPix2PixEmulator:
    """SIMULATOR of InstructPix2Pix for scenes with ground-truth edits; see the module docstring."""

    is_simulator = True

    def __init__(self, views: Sequence[EmulatedView], instruction: str, edit_id: str,
                 config: EmulatorConfig = EmulatorConfig()):
        self.instruction = instruction
        self.edit_id = edit_id
        self.config = config
        self._views: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        for view in views:
            if view.original.shape != view.gt_edit.shape or view.mask.shape != view.original.shape[:2]:
                raise EditorError(f"emulator: ground-truth edit {view.gt_edit.shape} / mask {view.mask.shape} "
                                  f"do not match the original image {view.original.shape}.")
            mask = _gaussian_blur(view.mask.astype(np.float32), config.mask_feather)[..., None]
            self._views[_image_key(view.original)] = (to_float_image(view.original),
                                                     to_float_image(view.gt_edit), mask)
        self.last_details: dict = {}

    @classmethod
    def from_scene_folder(cls, folder: Path, edit_id: str, instruction: str, names: Sequence[str],
                          originals: Sequence[np.ndarray], config: EmulatorConfig = EmulatorConfig()
                          ) -> InstructPix2PixEmulator:
        """Load the ground truth of edit `edit_id` for the views `names` from a folder carrying scene.toml
        and gt/edits/ (a procedural scene or a preprocessed dataset of one)."""
        from dualnerf.scenes.spec import load_gt_edit, load_scene_spec

        folder = Path(folder)
        spec = load_scene_spec(folder)
        edit = spec.edit(edit_id)
        if instruction != edit.instruction:
            raise EditorError(
                f"the synthetic editor (InstructPix2Pix emulator) can only emulate edit '{edit_id}' of scene "
                f"'{spec.name}', whose instruction is '{edit.instruction}', but the instruction is "
                f"'{instruction}'. Use that instruction, or editor 'ip2p' for free-form instructions.")
        views = []
        for name, original in zip(names, originals):
            loaded = load_gt_edit(folder, edit_id, name)
            if loaded is None:
                raise EditorError(f"{folder}/gt/edits/{edit_id}/images/{name} is missing: the InstructPix2Pix "
                                  f"emulator needs the ground-truth edited view of every training image, which "
                                  f"only procedural scenes have: for photographs use editor 'ip2p' "
                                  f"(docs/tutorial.md); a procedural scene regenerated with `dualnerf scene` has it.")
            gt, mask = loaded
            if gt.shape != original.shape:
                import cv2

                size = (original.shape[1], original.shape[0])
                gt = cv2.resize(gt, size, interpolation=cv2.INTER_AREA)
                mask = cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
            views.append(EmulatedView(original=np.asarray(original), gt_edit=gt, mask=mask))
        return cls(views, instruction, edit_id, config)

    @property
    def identity(self) -> dict:
        return {"kind": "synthetic", "name": "InstructPix2PixEmulator", "is_simulator": True,
                "version": EMULATOR_VERSION, "edit_id": self.edit_id, "config": asdict(self.config)}

    def edit(self, render: np.ndarray, original: np.ndarray, instruction: str, seed: int, step: int
             ) -> np.ndarray:
        if instruction != self.instruction:
            raise EditorError(f"the InstructPix2Pix emulator was built for '{self.instruction}', "
                              f"got instruction '{instruction}'.")
        key = _image_key(np.asarray(original))
        if key not in self._views:
            raise EditorError("the InstructPix2Pix emulator has no ground truth for this original image "
                              "(it only knows the training views it was built with).")
        orig, gt, mask = self._views[key]
        render_f = to_float_image(render, "render")
        if render_f.shape != orig.shape:
            raise EditorError(f"render shape {render_f.shape} differs from the original {orig.shape}.")
        cfg = self.config
        rng = np.random.default_rng([int(seed), int(step)])
        shape = orig.shape[:2]
        # Draw everything unconditionally so each knob only changes its own effect.
        noise_level = float(rng.uniform(*cfg.noise_range))
        strength = max(0.0, 1.0 + cfg.strength_jitter * float(rng.normal()))
        tint = cfg.tint_jitter * rng.normal(size=3).astype(np.float32)
        spatial = 1.0 + cfg.spatial_jitter * _smooth_field(rng, cfg.spatial_cells, shape)
        gain = 1.0 + cfg.background_drift * rng.normal(size=3).astype(np.float32)
        offset = cfg.background_drift * rng.normal(size=3).astype(np.float32)
        blur_sigma = float(rng.uniform(0.0, cfg.background_blur))
        failed = bool(rng.random() < cfg.failure_rate)
        failure_kind = "wrong_colour" if rng.random() < 0.5 else "garbage"
        wrong_colour = rng.uniform(0.0, 1.0, size=3).astype(np.float32)
        blobs = np.clip(0.5 + 0.35 * _smooth_field(rng, 4, shape, 3), 0.0, 1.0)

        # The image IP2P would produce from a clean input: original + the jittered ground-truth change.
        target = orig + (strength * spatial) * (gt - orig) + mask * tint
        if failed and failure_kind == "wrong_colour":
            target = mask * (0.3 * orig + 0.7 * wrong_colour) + (1.0 - mask) * target
        # Render dependence: at noise level s the render survives with weight 1 - s**render_dependence.
        render_weight = 1.0 - noise_level ** cfg.render_dependence
        out = render_weight * render_f + (1.0 - render_weight) * target
        if failed and failure_kind == "garbage":
            out = 0.3 * out + 0.7 * blobs
        # Background drift and blur (outside the edit mask only).
        background = _gaussian_blur(out, blur_sigma) * gain + offset
        out = mask * out + (1.0 - mask) * background
        self.last_details = {
            "editor": "InstructPix2PixEmulator (simulator)", "noise_level": noise_level,
            "render_weight": render_weight, "strength": strength, "tint": tint.tolist(),
            "background_gain": gain.tolist(), "background_offset": offset.tolist(), "blur_sigma": blur_sigma,
            "failed": failed, "failure_kind": failure_kind if failed else None,
        }
        return to_uint8_image(out)
