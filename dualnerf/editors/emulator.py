"""An InstructPix2Pix EMULATOR (a simulator, not a diffusion model) for procedural scenes.

It knows each training view's ground-truth edited image and edit mask (from the scene's `gt/edits/`) and
reproduces failure modes of IP2P, each with a knob and an off switch, each drawn per call from a generator
seeded by (seed, step). Next to each, the paper's claim it stands for (DualNeRF, Secs. 1 and 4):

  - noise level: a timestep fraction s ~ U[noise_range] as in Instruct-NeRF2NeRF. The output keeps the
    input render with weight 1 - s**render_dependence: at low noise the render's partial edit and its
    artefacts survive. Alone this is a contraction toward one fixed point (the ground-truth edit): it slows
    IDU down but has no local optimum to be trapped in.
  - mode lock-in (`lock_in`; off: the ground truth is the only mode). Claim: "partially edited renderings
    mislead IP2P to produce edits with similar appearances ... IDU tends to preserve sub-optimal edits
    due to the mutual reinforcement between IP2P edits and model training" (Sec. 1), which SA's retreated
    renders are to escape (Sec. 4.2). An instruction has the ground-truth appearance and alternative modes
    (another blue for "turn the tent blue", grey snow for "make it snow"; `EditDef.modes`, rendered by the
    scene's own ray caster, so each mode is as 3D-consistent as the ground truth). Each call draws ONE mode
    k with probability
        p_k = keep(s) q_k(render) + (1 - keep(s)) prior_k
    - q: the modes the render already shows, a soft assignment by squared distance inside the edit region:
      q = softmax_k(-R_k / T), R_k = D_k(render) / D_k(original), with D_k the mean squared difference to
      mode k in the region, so R_k is the share of the way to mode k still to go (1 for the unedited
      render, 0 at the mode) and the temperature T = `mode_temperature` is unit-free. The unedited
      render carries no evidence for either reading (q uniform); a render half-way to a mode is
      assigned to it.
    - keep(s) = n SNR(s) / (1 + n SNR(s)): how much of the render's region colour survives noise level s
      in Stable Diffusion's scaled-linear schedule (SNR = alphabar / (1 - alphabar)), for a region whose
      mean colour averages n = `mode_memory` independent latents. IP2P keeps what the input shows at low
      noise and chooses freely near s = 1.
    - prior: the instruction's reading with no input evidence: `mode_prior` for the ground truth, the rest
      shared by the alternatives. The ground truth is IP2P's favourite reading, not its only one.
    The drawn mode replaces the ground truth in the target below. So a field that drifts toward a wrong or
    mixed mode is told to stay there, and different views can be told different modes (3D inconsistency).
    Nothing here knows which method is running: a retreated (SA) render is just a render.
  - inconsistency across views: per-call edit strength (multiplicative jitter), an RGB tint of the
    edited region, and a low-frequency random field modulating the strength spatially.
  - zero-mean background drift and blur: a per-call colour gain/offset and a Gaussian blur outside the
    edit region. Claim: "IP2P edits with distorted backgrounds ... jittering the original texture and
    resulting in blurred backgrounds" (Sec. 1). Zero-mean: a field averaging many calls cancels most of it.
  - a systematic background colour cast (`background_cast`; 0: off): outside the edit region every call
    multiplies the colour by 1 + background_cast * v * CAST_RGB (a warm cast), with v in [0, 1] a fixed
    property of the view (0.5 + 0.5 x the camera's forward x component when cameras are given, else 0.5).
    Not zero-mean, and smooth in the viewing direction: a field can learn it as view-dependent colour.
    Claim: f_S's features are "anchors" that keep the training "not drifting far away from the initial
    state, mitigating the impact of color jitters in unedited areas" (Sec. 4.1).
  - outright failures with probability `failure_rate`: the edit region painted a wrong colour, or a
    garbage image (the render washed over by random colour blobs). Claim: CCI filters out "low-quality
    results which extremely deviate from the original image" (Sec. 1, 4.3). `last_details["failed"]`
    records each call's failure, so CCI's precision and recall can be measured.

The edited target is the original plus the (jittered) change to the drawn mode, so a render that already
carries the edit moves toward it and a render carrying garbage keeps part of it. Random draws are made in
a fixed order whatever the knobs, new knobs' draws after the old ones: with lock_in off and
background_cast 0 the outputs equal those of emulator version 1 bit for bit.
"""
from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from dualnerf.editors.base import EditorError, to_float_image, to_uint8_image

EMULATOR_VERSION = 2          # 2: mode lock-in and the systematic background cast
CAST_RGB = np.array([1.0, 0.3, -0.8], np.float32)     # direction of the systematic cast: warm (red up, blue down)

# Stable Diffusion's scaled-linear noise schedule (1000 steps, beta 0.00085 -> 0.012): alphabar per step.
_SD_ALPHABAR = np.cumprod(1.0 - np.linspace(0.00085 ** 0.5, 0.012 ** 0.5, 1000) ** 2)


def mode_keep(noise_level: float, memory: float) -> float:
    """The share of the render's region colour that survives noise level s (see the module docstring)."""
    alphabar = float(np.interp(min(max(noise_level, 0.0), 1.0) * 999.0, np.arange(1000), _SD_ALPHABAR))
    snr = memory * alphabar / (1.0 - alphabar)
    return snr / (1.0 + snr)


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
    lock_in: bool = True                # mode lock-in (module docstring); off: the ground truth is the only mode
    mode_temperature: float = 0.1       # T of the soft assignment q (unit-free, see the module docstring)
    mode_memory: float = 16.0           # n: latents averaged by the region colour that decides the mode
    mode_prior: float = 2.0 / 3.0       # the ground truth's probability when the input shows no mode
    background_cast: float = 0.05       # systematic view-dependent warm cast outside the edit (0: off)

    def __post_init__(self) -> None:
        lo, hi = self.noise_range
        if not 0.0 <= lo <= hi <= 1.0:
            raise EditorError(f"emulator noise_range must satisfy 0 <= low <= high <= 1, got {self.noise_range}.")
        if not 0.0 <= self.failure_rate <= 1.0:
            raise EditorError(f"emulator failure_rate must be in [0, 1], got {self.failure_rate}.")
        if not 0.0 <= self.mode_prior <= 1.0:
            raise EditorError(f"emulator mode_prior must be in [0, 1], got {self.mode_prior}.")
        if not self.mode_temperature > 0:
            raise EditorError(f"emulator mode_temperature must be > 0, got {self.mode_temperature}.")
        for name in ("render_dependence", "strength_jitter", "tint_jitter", "spatial_jitter",
                     "background_drift", "background_blur", "mask_feather", "mode_memory", "background_cast"):
            if getattr(self, name) < 0:
                raise EditorError(f"emulator {name} must be >= 0, got {getattr(self, name)}.")


@dataclass(frozen=True)
class EmulatedView:
    original: np.ndarray     # HxWx3 uint8, the view's original training image
    gt_edit: np.ndarray      # HxWx3 uint8, the ground-truth edited view
    mask: np.ndarray         # HxW bool, True where the edit changes the colour
    modes: tuple = ()        # alternative modes: ((HxWx3 uint8 image, HxW bool mask), ...) (lock-in only)
    cast_weight: float = 0.5  # v in [0, 1]: this view's share of the systematic background cast


def cast_weights(c2w: np.ndarray) -> np.ndarray:
    """v = 0.5 + 0.5 x the camera's forward x component (OpenCV c2w: forward is the third column)."""
    forward = np.asarray(c2w)[:, :3, 2]
    forward = forward / np.maximum(np.linalg.norm(forward, axis=1, keepdims=True), 1e-12)
    return 0.5 + 0.5 * forward[:, 0]


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


class _PreparedView:
    """A view's float images: the original, its modes' targets (ground truth first) with feathered masks,
    the edit region (union of the modes' masks) and what the soft assignment needs."""

    def __init__(self, original, targets, mask, cast_weight, modes):
        self.original, self.targets, self.mask, self.cast_weight = original, targets, mask, cast_weight
        self.modes = modes
        region = mask[..., 0]
        self._region = region / max(float(region.sum()), 1e-12)
        self._baseline = np.maximum([self._distance(original, t[0]) for t in targets], 1e-8)

    def _distance(self, a: np.ndarray, b: np.ndarray) -> float:
        """Mean squared difference in the edit region (per channel)."""
        return float(np.einsum("hw,hw->", self._region, ((a - b) ** 2).mean(axis=-1)))

    def assignment(self, render: np.ndarray, temperature: float) -> np.ndarray:
        """q: softmax over modes of -R_k / T, R_k = D_k(render) / D_k(original) (module docstring)."""
        remaining = np.array([self._distance(render, t[0]) for t in self.targets]) / self._baseline
        logits = -remaining / temperature
        logits -= logits.max()
        weights = np.exp(logits)
        return weights / weights.sum()


def _prepare(view: EmulatedView, config: EmulatorConfig) -> _PreparedView:
    feather = lambda m: _gaussian_blur(m.astype(np.float32), config.mask_feather)[..., None]
    modes = view.modes if config.lock_in else ()
    targets = [(to_float_image(view.gt_edit), feather(view.mask))]
    targets += [(to_float_image(image), feather(mask)) for image, mask in modes]
    union = view.mask.copy()
    for _, mask in modes:
        union |= mask
    # The edit region, outside which the background effects act: the ground truth's mask without lock-in
    # (as in emulator version 1), the union of every mode's with it.
    return _PreparedView(to_float_image(view.original), targets, feather(union), float(view.cast_weight), modes)


def _load_resized(load_gt_edit, folder: Path, folder_id: str, name: str, original: np.ndarray):
    loaded = load_gt_edit(folder, folder_id, name)
    if loaded is None:
        raise EditorError(f"{folder}/gt/edits/{folder_id}/images/{name} is missing: the InstructPix2Pix "
                          f"emulator needs this edited view of every training image, which only procedural "
                          f"scenes have: for photographs use editor 'ip2p' (docs/tutorial.md); a procedural "
                          f"scene regenerated with `dualnerf scene` has it.")
    image, mask = loaded
    if image.shape != original.shape:
        import cv2

        size = (original.shape[1], original.shape[0])
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        mask = cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    return image, mask


class InstructPix2PixEmulator:
    """SIMULATOR of InstructPix2Pix for scenes with ground-truth edits; see the module docstring."""

    is_simulator = True

    def __init__(self, views: Sequence[EmulatedView], instruction: str, edit_id: str,
                 config: EmulatorConfig = EmulatorConfig()):
        self.instruction = instruction
        self.edit_id = edit_id
        self.config = config
        self._views: dict[str, _PreparedView] = {}
        for view in views:
            if view.original.shape != view.gt_edit.shape or view.mask.shape != view.original.shape[:2]:
                raise EditorError(f"emulator: ground-truth edit {view.gt_edit.shape} / mask {view.mask.shape} "
                                  f"do not match the original image {view.original.shape}.")
            for image, mask in view.modes:
                if image.shape != view.original.shape or mask.shape != view.original.shape[:2]:
                    raise EditorError(f"emulator: an alternative mode {image.shape} / mask {mask.shape} does not "
                                      f"match the original image {view.original.shape}.")
            self._views[_image_key(view.original)] = _prepare(view, config)
        self.n_modes = 1 + max((len(v.modes) for v in views), default=0) if config.lock_in else 1
        self.last_details: dict = {}

    @classmethod
    def from_scene_folder(cls, folder: Path, edit_id: str, instruction: str, names: Sequence[str],
                          originals: Sequence[np.ndarray], config: EmulatorConfig = EmulatorConfig(),
                          c2w: np.ndarray | None = None) -> InstructPix2PixEmulator:
        """Load the ground truth of edit `edit_id` (and, with lock_in, its alternative modes) for the views
        `names` from a folder carrying scene.toml and gt/edits/ (a procedural scene or a preprocessed
        dataset of one). `c2w` (N,4,4), the views' cameras, make the background cast view-dependent."""
        from dualnerf.scenes.spec import load_gt_edit, load_scene_spec, mode_edit_id

        folder = Path(folder)
        spec = load_scene_spec(folder)
        edit = spec.edit(edit_id)
        if instruction != edit.instruction:
            raise EditorError(
                f"the synthetic editor (InstructPix2Pix emulator) can only emulate edit '{edit_id}' of scene "
                f"'{spec.name}', whose instruction is '{edit.instruction}', but the instruction is "
                f"'{instruction}'. Use that instruction, or editor 'ip2p' for free-form instructions.")
        modes = edit.modes if config.lock_in else ()
        if config.lock_in and not modes:
            raise EditorError(
                f"the InstructPix2Pix emulator's mode lock-in needs alternative modes of edit '{edit_id}' "
                f"(scene.toml 'modes', gt/edits/{edit_id}.<mode>/), and {folder / 'scene.toml'} lists none; "
                f"regenerate the scene (scene stage version 3 renders them), or set emulator_lock_in = false.")
        weights = cast_weights(c2w) if c2w is not None else np.full(len(names), 0.5)
        views = []
        for name, original, weight in zip(names, originals, weights):
            original = np.asarray(original)
            gt, mask = _load_resized(load_gt_edit, folder, edit_id, name, original)
            alternatives = tuple(_load_resized(load_gt_edit, folder, mode_edit_id(edit_id, m), name, original)
                                 for m in modes)
            views.append(EmulatedView(original=original, gt_edit=gt, mask=mask, modes=alternatives,
                                      cast_weight=float(weight)))
        emulator = cls(views, instruction, edit_id, config)
        emulator.mode_names = (edit_id,) + tuple(modes)
        return emulator

    @property
    def identity(self) -> dict:
        return {"kind": "synthetic", "name": "InstructPix2PixEmulator", "is_simulator": True,
                "version": EMULATOR_VERSION, "edit_id": self.edit_id, "config": asdict(self.config),
                "modes": list(getattr(self, "mode_names", (self.edit_id,)))[:self.n_modes]}

    def edit(self, render: np.ndarray, original: np.ndarray, instruction: str, seed: int, step: int
             ) -> np.ndarray:
        if instruction != self.instruction:
            raise EditorError(f"the InstructPix2Pix emulator was built for '{self.instruction}', "
                              f"got instruction '{instruction}'.")
        key = _image_key(np.asarray(original))
        if key not in self._views:
            raise EditorError("the InstructPix2Pix emulator has no ground truth for this original image "
                              "(it only knows the training views it was built with).")
        view = self._views[key]
        orig, mask = view.original, view.mask
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
        mode_draw = float(rng.random())          # emulator version 2: drawn after every version-1 draw

        # Render dependence: at noise level s the render survives with weight 1 - s**render_dependence.
        render_weight = 1.0 - noise_level ** cfg.render_dependence
        mode, probabilities, keep = 0, None, None
        if cfg.lock_in and view.modes:
            keep = mode_keep(noise_level, cfg.mode_memory)
            assignment = view.assignment(render_f, cfg.mode_temperature)
            prior = np.array([cfg.mode_prior] + [(1.0 - cfg.mode_prior) / len(view.modes)] * len(view.modes))
            probabilities = keep * assignment + (1.0 - keep) * prior
            mode = min(int(np.searchsorted(np.cumsum(probabilities), mode_draw * probabilities.sum(),
                                           side="right")), len(probabilities) - 1)
        edited, edit_mask = view.targets[mode]
        # The image IP2P would produce from a clean input: original + the jittered change to the drawn mode.
        target = orig + (strength * spatial) * (edited - orig) + edit_mask * tint
        if failed and failure_kind == "wrong_colour":
            target = edit_mask * (0.3 * orig + 0.7 * wrong_colour) + (1.0 - edit_mask) * target
        out = render_weight * render_f + (1.0 - render_weight) * target
        if failed and failure_kind == "garbage":
            out = 0.3 * out + 0.7 * blobs
        # Background drift, blur and the systematic cast (outside the edit region only).
        cast = 1.0 + cfg.background_cast * view.cast_weight * CAST_RGB
        background = (_gaussian_blur(out, blur_sigma) * gain + offset) * cast
        out = mask * out + (1.0 - mask) * background
        self.last_details = {
            "editor": "InstructPix2PixEmulator (simulator)", "noise_level": noise_level,
            "render_weight": render_weight, "strength": strength, "tint": tint.tolist(),
            "background_gain": gain.tolist(), "background_offset": offset.tolist(), "blur_sigma": blur_sigma,
            "background_cast": float(cfg.background_cast * view.cast_weight),
            "failed": failed, "failure_kind": failure_kind if failed else None,
            "mode": mode, "mode_keep": keep,
            "mode_probabilities": None if probabilities is None else [float(v) for v in probabilities],
        }
        return to_uint8_image(out)
