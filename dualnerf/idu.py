"""The editing loop: Iterative Dataset Update (IDU, Instruct-NeRF2NeRF) with DualNeRF's three additions,
each a toggle for the ablation:

  dual_field (DF, Sec. 4.1)   on: f_S frozen, f_D trainable, fused with blend weights w_t = w_max tanh(lambda t)
                                  (eq. 6); off: the single-field baseline (a trainable copy of f_S).
  annealing (SA, Sec. 4.2)    at every dataset update draw gamma ~ U[0,1] and accept with p = exp((gamma-1)/T_t)
                                  (eqs. 7-8); accepted: render the view from the retreated model.
  consistency (CCI, Sec. 4.3) per-view S(I'|I,y) (eq. 9), cached until the view is updated again; the RGB loss
                                  of rays from view i is weighted by S_i / mean(S) (eq. 10). Off: uniform.

Loop (IN2N defaults): every `edit_rate` iterations (starting at iteration 0) update `edit_count` training
views, visited in a fixed cyclic order of the training split: render the view from the current (or
retreated) model, give the editor that render, the view's ORIGINAL image and the instruction, and replace
the view's training image with the result (quantised to 8 bits, as it is stored). Originals are kept.

Design decisions (documented here because the paper leaves them open):
  - Retreat with DF off: the single field f is pulled back toward f_S by the same feature fusion,
    h = (1 - gamma) h_S + gamma h_f (eqs. 4-5 with f in the dynamic role and w = 1), so SA keeps its meaning
    ("gamma = 0 is the original scene, gamma = 1 the latest model") for the baseline too.
  - CCI of views not edited yet: they train on their original image I, so S = S(I | I, y) =
    cos01(E_I(I), E_T(y)) (eq. 9 with I' = I); see dualnerf.consistency.
  - f_D's learning rate is the baseline's (the paper: "other hyperparameters follow the settings in
    [IN2N]"), so f_S's anchor works as the paper has it: fused features move ~w times slower than f_D's own.
    `dual_lr_scale` (off by default; a variant, not the paper's method) trains f_D at lr / w_max_color
    instead, which undoes that slowness, since Adam's step does not depend on the gradient's scale.
  - The consistency score S is computed and logged at every update whenever an encoder is given, also with
    CCI off, so the ablation can measure what CCI would have done; only `consistency` decides the weights.
  - Loss: RGB (eq. 3, CCI-weighted by eq. 10) plus, with lpips_weight > 0, lpips_weight x LPIPS on
    rendered 32x32 patches (the paper's "RGB loss and LPIPS loss", Instruct-NeRF2NeRF's patches; see
    dualnerf.training). Off by default here; the edit stage turns it on.

All randomness: the trainer's torch.Generator (rays, jitter, occupancy), a numpy Generator for SA draws,
and per-call editor seeds derived from (seed, iteration, slot); all three are saved in the checkpoint
state, so a resumed run continues exactly.
"""
from __future__ import annotations

import copy
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from dualnerf.annealing import AnnealingConfig, annealing_temperature, draw_retreat
from dualnerf.cameras import Cameras
from dualnerf.consistency import ConsistencyCache, consistency_score, consistency_weights
from dualnerf.dual_field import BlendSchedule, DualField, make_edit_model
from dualnerf.rendering import render_view
from dualnerf.training import RayTrainer, TrainConfig

STATE_FORMAT_VERSION = 1
_STATIC_PREFIX = "static_field."       # a DualField's f_S entries in its state dict


class IDUConfigError(ValueError):
    """An editing-loop configuration that cannot run; the message names the parameter."""

    user_error = True


@dataclass(frozen=True)
class IDUConfig:
    dual_field: bool = True
    annealing: bool = True
    consistency: bool = True
    iterations: int = 15000
    edit_rate: int = 10                 # iterations between dataset updates (IN2N)
    edit_count: int = 1                 # views updated per dataset update (IN2N)
    rays_per_batch: int = 4096
    learning_rate: float = 1e-2
    dual_lr_scale: bool = False         # True: f_D's lr = learning_rate / w_max_color (a variant; docstring)
    blend: BlendSchedule = field(default_factory=BlendSchedule)
    annealing_config: AnnealingConfig = field(default_factory=AnnealingConfig)
    seed: int = 0
    lpips_weight: float = 0.0           # > 0: + this x LPIPS on rendered patches (see dualnerf.training)
    lpips_net: str = "alex"
    patch_size: int = 32
    patch_share: float = 0.5
    # The view updates' renders: "fp32", or "bf16" MLPs in the fused kernel (dualnerf.kernels.mlp_precision:
    # ~1e-3 mean colour difference, below the 8-bit step the edited image is stored with; the editor
    # re-noises the render anyway). Training, probes and evaluation renders stay fp32.
    update_precision: str = "fp32"
    # Field evaluations per ray in training and in the view updates' renders; 0: the field's own
    # (FieldConfig.samples_per_ray and render_samples_per_ray). Convergence probes and the saved model's
    # renders (evaluation) keep the field's render_samples_per_ray.
    samples_per_ray: int = 0

    def __post_init__(self) -> None:
        for name in ("iterations", "edit_rate", "edit_count", "rays_per_batch"):
            if getattr(self, name) < 1:
                raise IDUConfigError(f"edit parameter '{name}' must be >= 1, got {getattr(self, name)}.")
        if not self.learning_rate > 0:
            raise IDUConfigError(f"edit parameter 'lr' must be > 0, got {self.learning_rate}.")
        if self.samples_per_ray != 0 and self.samples_per_ray < 2:
            raise IDUConfigError(f"edit parameter 'samples_per_ray' must be 0 (the fitted field's) or >= 2, got "
                                 f"{self.samples_per_ray}.")
        if self.update_precision not in ("fp32", "bf16"):
            raise IDUConfigError(f"edit parameter 'update_precision' must be 'fp32' or 'bf16', got "
                                 f"{self.update_precision!r}.")

    def to_json(self) -> dict:
        return asdict(self)


def editor_seed(seed: int, iteration: int, slot: int) -> int:
    """The per-call editor seed for update slot `slot` at `iteration` (stateless, so resume-safe)."""
    return int(np.random.SeedSequence([int(seed), int(iteration), int(slot)]).generate_state(1)[0])


def _to_uint8(image) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype == np.uint8:
        return image
    return (np.clip(image.astype(np.float32), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


class IterativeDatasetUpdate:
    """The editing loop's state and steps. Build, optionally `load_state`, then `run`."""

    def __init__(self, config: IDUConfig, static_field, dataset, editor, instruction: str, *,
                 encoder=None, cci_text: str | None = None, device: str = "cpu", probe=None):
        if config.consistency and encoder is None:
            raise IDUConfigError("consistency (CCI) is on but no image-text encoder was given; set encoder "
                                 "'proxy' or 'clip', or turn consistency off.")
        self.config = config
        self.dataset = dataset
        self.editor = editor
        self.instruction = instruction
        self.encoder = encoder
        self.cci_text = cci_text if cci_text is not None else instruction
        self.device = torch.device(device)
        self.train_views = [int(i) for i in dataset.indices("train")]
        if not self.train_views:
            raise IDUConfigError("the dataset has no training views (every frame is held out); rerun preprocess "
                                 "with holdout_every = 0 or a larger value.")
        self.originals = dataset.images                          # (N,H,W,3) uint8, never modified
        self.images = dataset.images.copy()                      # the updated dataset

        # The static field f_S stays frozen in every mode; it is the SA retreat target.
        self.static_field = copy.deepcopy(static_field).to(self.device).requires_grad_(False)
        self.model = make_edit_model(self.static_field, "dual" if config.dual_field else "single")
        self.model.to(self.device)
        lr = config.learning_rate
        if config.dual_field and config.dual_lr_scale and config.blend.w_max_color > 0:
            lr = lr / config.blend.w_max_color
        self.train_config = TrainConfig(rays_per_batch=config.rays_per_batch, learning_rate=lr,
                                        lpips_weight=config.lpips_weight, lpips_net=config.lpips_net,
                                        patch_size=config.patch_size, patch_share=config.patch_share,
                                        samples_per_ray=config.samples_per_ray)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.trainer = RayTrainer(self.model, torch.from_numpy(self.images).to(self.device).float() / 255.0,
                                  Cameras.from_dataset(dataset), self.train_config, self.generator,
                                  self.train_views)
        self.sa_rng = np.random.default_rng(np.random.SeedSequence([config.seed, 0x5A]))
        self.iteration = 0

        self.scores: ConsistencyCache | None = None
        if encoder is not None:
            train = np.array(self.train_views)
            feats = encoder.encode_images(self.originals[train])
            self._original_features = np.zeros((len(self.originals), feats.shape[1]), np.float32)
            self._original_features[train] = feats
            self._text_feature = encoder.encode_texts([self.cci_text])[0]
            initial = np.ones(len(self.originals))
            initial[train] = consistency_score(feats, feats, self._text_feature[None])
            self.scores = ConsistencyCache(scores=initial)
        self.updates: list[dict] = []
        self.curves: dict[str, list] = {"iteration": [], "loss": [], "psnr": [], "blend_density": [],
                                        "blend_color": [], "temperature": [], "cci_weight_min": [],
                                        "cci_weight_max": []}
        self.cci_history: list[dict] = []
        # Optional dualnerf.convergence.ConvergenceProbe: PSNR of a few training-view renders to the
        # ground-truth edit at regular iterations (deterministic renders: probing does not change the run).
        self.probe = probe
        self.convergence: list[dict] = []

    # ---- the loop ------------------------------------------------------------------------------
    def blend_at(self, iteration: int):
        return self.config.blend.weights(iteration) if self.config.dual_field else None

    def view_weights(self) -> np.ndarray | None:
        """Per-frame loss weights S_i / mean(S) over the training views (eq. 10); None = uniform."""
        if not self.config.consistency:
            return None
        weights = np.ones(len(self.originals))
        train = np.array(self.train_views)
        weights[train] = consistency_weights(self.scores.scores[train])
        return weights

    def render(self, view: int, iteration: int, retreat: float = 1.0) -> np.ndarray:
        """The view rendered from the model at `iteration`, retreated toward f_S by `retreat` = gamma."""
        ds = self.dataset
        model, blend = self.model, self.blend_at(iteration)
        if not self.config.dual_field and retreat < 1.0:
            # Single-field retreat: fuse f_S and the single field with w = 1 scaled by gamma (module docstring).
            model = DualField(self.static_field, self.model)     # its occupancy: the union of both fields'
            blend = (1.0, 1.0)
        image = render_view(model, ds.c2w[view], ds.intrinsics[view], ds.width, ds.height, float(ds.near[view]),
                            float(ds.far[view]), blend=blend, retreat=float(retreat) if blend is not None else 1.0,
                            mlp_precision=self.config.update_precision,
                            samples_per_ray=self.config.samples_per_ray or None)
        return image.numpy()

    def dataset_update(self, iteration: int) -> None:
        cfg = self.config
        for slot in range(cfg.edit_count):
            index = (iteration // cfg.edit_rate) * cfg.edit_count + slot
            view = self.train_views[index % len(self.train_views)]
            draw = draw_retreat(self.sa_rng, iteration, cfg.annealing_config) if cfg.annealing else None
            gamma = draw.blend_scale if draw is not None else 1.0
            rendered = self.render(view, iteration, gamma)
            seed = editor_seed(cfg.seed, iteration, slot)
            edited = _to_uint8(self.editor.edit(rendered, self.originals[view], self.instruction, seed, iteration))
            if edited.shape != self.originals[view].shape:
                raise IDUConfigError(f"the editor returned an image of shape {edited.shape} for view "
                                     f"{self.dataset.names[view]} of shape {self.originals[view].shape}.")
            self.images[view] = edited
            self.trainer.images[view] = torch.from_numpy(edited).to(self.device).float() / 255.0
            score = None
            if self.scores is not None:
                feature = self.encoder.encode_images(edited[None])[0]
                score = float(consistency_score(feature, self._original_features[view], self._text_feature))
                self.scores.update(view, score)
            weights = self.view_weights()
            # S relative to the mean over the training views: < 1 is a call CCI would down-weight (the
            # flag whose precision and recall at the editor's failed calls the report measures).
            ratio = None if score is None else float(consistency_weights(self.scores.scores[self.train_views])[
                self.train_views.index(view)])
            entry = {"iteration": iteration, "view": view, "name": self.dataset.names[view],
                     "temperature": annealing_temperature(iteration, cfg.annealing_config.initial_temperature),
                     "gamma": None if draw is None else draw.retreat_factor,
                     "acceptance_probability": None if draw is None else draw.acceptance_probability,
                     "accepted": None if draw is None else draw.accepted, "render_retreat": gamma,
                     "score": score, "score_ratio": ratio,
                     "weight": None if weights is None else float(weights[view]),
                     "editor_seed": seed, "editor": dict(getattr(self.editor, "last_details", {}) or {})}
            self.updates.append(entry)
        if self.scores is not None:
            train = np.array(self.train_views)
            self.cci_history.append({"iteration": iteration,
                                     "scores": [float(s) for s in self.scores.scores[train]],
                                     "weights": [float(w) for w in consistency_weights(self.scores.scores[train])]})

    def train_step(self, iteration: int) -> dict:
        weights = self.view_weights()
        blend = self.blend_at(iteration)
        metrics = self.trainer.step(iteration, blend=blend,
                                    view_weights=None if weights is None else torch.from_numpy(weights))
        c = self.curves
        c["iteration"].append(iteration)
        c["loss"].append(float(metrics["loss"]))
        c["psnr"].append(float(metrics["psnr"]))
        w = blend or (0.0, 0.0)
        c["blend_density"].append(float(w[0]))
        c["blend_color"].append(float(w[1]))
        c["temperature"].append(annealing_temperature(iteration, self.config.annealing_config.initial_temperature))
        c["cci_weight_min"].append(None if weights is None else float(weights[self.train_views].min()))
        c["cci_weight_max"].append(None if weights is None else float(weights[self.train_views].max()))
        return metrics

    def run(self, until: int | None = None, on_round_end=None, progress=None) -> None:
        """Iterate from the current iteration to `until` (default: config.iterations). `on_round_end(i)` is
        called after every editing round (edit_rate iterations) with the next iteration i; `progress(n, **m)`
        after every iteration."""
        cfg = self.config
        end = cfg.iterations if until is None else min(until, cfg.iterations)
        while self.iteration < end:
            t = self.iteration
            self._probe(t)
            if t % cfg.edit_rate == 0:
                self.dataset_update(t)
            metrics = self.train_step(t)
            self.iteration = t + 1
            if progress is not None:
                progress(1, loss=float(metrics["loss"]), psnr=float(metrics["psnr"]))
            if on_round_end is not None and self.iteration % cfg.edit_rate == 0 and self.iteration < cfg.iterations:
                on_round_end(self.iteration)
        if self.iteration == cfg.iterations:
            self._probe(self.iteration)

    def _probe(self, iteration: int) -> None:
        """Record the convergence probe's PSNRs of the model after `iteration` training iterations."""
        last = self.config.iterations
        if self.probe is None or not self.probe.due(iteration, last):
            return
        if self.convergence and self.convergence[-1]["iteration"] >= iteration:
            return
        model = self.model
        blend = self.blend_at(min(iteration, last - 1))
        self.convergence.append(self.probe.measure(model, blend, iteration))

    # ---- results -------------------------------------------------------------------------------
    def final_model(self):
        """The edited model; a DualField carries the blend weights of the last iteration for rendering."""
        if isinstance(self.model, DualField):
            self.model.render_blend = self.config.blend.weights(max(self.config.iterations - 1, 0))
        return self.model

    def curves_json(self) -> dict:
        acc = [u for u in self.updates if u["accepted"] is not None]
        return {**self.curves,
                "updates": {key: [u[key] for u in self.updates]
                            for key in ("iteration", "view", "gamma", "accepted", "acceptance_probability",
                                        "temperature", "render_retreat", "score", "weight")},
                "acceptance_rate": (sum(bool(u["accepted"]) for u in acc) / len(acc)) if acc else None,
                "cci": self.cci_history, "train_views": self.train_views,
                "convergence": self.convergence_json(),
                "toggles": {"dual_field": self.config.dual_field, "annealing": self.config.annealing,
                            "consistency": self.config.consistency}}

    def convergence_json(self) -> dict | None:
        """The probe's columns: iteration, psnr_in (to the ground-truth edit inside its mask), psnr_out (to the
        original outside it), and the probed views; None without a probe."""
        if self.probe is None:
            return None
        return {"iteration": [c["iteration"] for c in self.convergence],
                "psnr_in": [c["psnr_in"] for c in self.convergence],
                "psnr_out": [c["psnr_out"] for c in self.convergence],
                "views": self.probe.views, "scale": 1.0 / self.probe.factor}

    # ---- checkpoint state ----------------------------------------------------------------------
    def save_state(self, folder: Path) -> None:
        folder = Path(folder)
        trainer_state = self.trainer.state_dict()
        # f_S is frozen and rebuilt from the fit result on resume: leave its tensors (a quarter of a
        # dual-field state with Adam's moments) out of every checkpoint.
        trainer_state["model"] = {k: v for k, v in trainer_state["model"].items()
                                  if not k.startswith(_STATIC_PREFIX)}
        tensors = {"trainer": trainer_state, "images": torch.from_numpy(self.images.copy())}
        if self.scores is not None:
            tensors["scores"] = torch.from_numpy(self.scores.scores.copy())
        torch.save(tensors, folder / "state.pt")
        doc = {"version": STATE_FORMAT_VERSION, "iteration": self.iteration, "config": self.config.to_json(),
               "sa_rng": self.sa_rng.bit_generator.state, "updates": self.updates, "curves": self.curves,
               "cci": self.cci_history, "convergence": self.convergence}
        (folder / "state.json").write_text(json.dumps(doc))

    def load_state(self, folder: Path) -> None:
        folder = Path(folder)
        doc = json.loads((folder / "state.json").read_text())
        if doc.get("version") != STATE_FORMAT_VERSION or doc.get("config") != json.loads(
                json.dumps(self.config.to_json())):
            raise IDUConfigError(f"{folder} is a checkpoint of a different edit configuration or format; "
                                 f"delete it to start over.")
        tensors = torch.load(folder / "state.pt", map_location="cpu", weights_only=True)
        trainer_state = tensors["trainer"]
        trainer_state["model"] = {**{k: v for k, v in self.trainer.model.state_dict().items()
                                     if k.startswith(_STATIC_PREFIX)}, **trainer_state["model"]}
        self.trainer.load_state_dict(trainer_state)
        self.images = tensors["images"].numpy().copy()
        self.trainer.images = torch.from_numpy(self.images).to(self.device).float() / 255.0
        if self.scores is not None and "scores" in tensors:
            self.scores = ConsistencyCache(scores=tensors["scores"].numpy().astype(np.float64).copy())
        self.sa_rng.bit_generator.state = doc["sa_rng"]
        self.iteration = int(doc["iteration"])
        self.updates = doc["updates"]
        self.curves = doc["curves"]
        self.cci_history = doc["cci"]
        self.convergence = doc.get("convergence", [])
