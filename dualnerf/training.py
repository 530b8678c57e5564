"""Ray-batch training of a radiance field (static fit, dual-field or single-field editing).

API:
    TrainConfig(rays_per_batch=1024, learning_rate=1e-2, ...)       frozen dataclass
    RayTrainer(model, images: (N,H,W,3) float tensor in [0,1], cameras: Cameras, config: TrainConfig,
               generator: torch.Generator (CPU), train_indices: sequence[int] | None = None)
        .images                       mutable: the editing loop may overwrite trainer.images[i] in place
        .step(step: int, blend=None, view_weights=None) -> dict(loss, mse, psnr, samples, occupancy, lpips)
        .state_dict() / .load_state_dict(state)   model + optimiser + occupancy grid + generator state
    rgb_loss(pred (R,3), target (R,3), ray_weights (R,) | None) -> scalar
    normalised_view_weights(scores (N,), train_indices) -> (N,)  S_i / mean(S over training views)

The learning rate is constant unless lr_decay_steps > 0 (exponential decay, a function of `step` only).
One `step` draws `rays_per_batch` random (training view, pixel) pairs from the seeded CPU generator,
renders them with jittered samples, and takes one Adam step (dualnerf.optim.FieldAdam: feature-table
entries without gradient are skipped) on the parameters that require gradients (so a DualField trains
only f_D). Every `occupancy_every` steps (after `occupancy_warmup`) it first
refreshes the occupancy grid of the model being trained (the fused one for a DualField with `blend`).
Everything random comes from `generator`, so equal seeds give equal runs, and a resumed trainer
(load_state_dict) continues exactly as an uninterrupted one. The images are not part of the state:
the editing loop checkpoints its updated dataset itself.

With lpips_weight > 0 (the paper's RGB + LPIPS loss), about `patch_share` of each batch is drawn as
patch_size x patch_size patches (dualnerf.patches) and the loss adds lpips_weight x the mean LPIPS
(dualnerf.lpips, backbone `lpips_net`) of rendered vs target patches, each weighted like its view's rays.
With lpips_weight = 0 a batch and its random draws are exactly those of the RGB-only trainer.
"""
from __future__ import annotations

import contextlib
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from dualnerf import kernels
from dualnerf.cameras import Cameras, pixel_rays
from dualnerf.fields import decode_density
from dualnerf.optim import FieldAdam, feature_table_parameters
from dualnerf.rendering import render_rays


@dataclass(frozen=True)
class TrainConfig:
    rays_per_batch: int = 1024
    learning_rate: float = 1e-2
    beta1: float = 0.9
    beta2: float = 0.99
    eps: float = 1e-15              # tiny eps: grid cells see rare, small gradients (as in hash-grid NeRFs)
    lr_decay_steps: int = 0         # > 0: learning rate decays exponentially to lr_final_ratio * lr by then
    lr_final_ratio: float = 1.0
    occupancy_every: int = 16
    occupancy_warmup: int = 16
    occupancy_decay: float = 0.7     # fast forgetting: the grid density also drives the proposal sampler
    occupancy_alpha: float = 0.01   # a cell is empty when one sample step there would be this transparent
    distortion_weight: float = 0.0  # > 0: adds this x the mip-NeRF 360 distortion loss (against floaters)
    lpips_weight: float = 0.0       # > 0: adds this x LPIPS on rendered square patches (Instruct-NeRF2NeRF)
    lpips_net: str = "alex"         # LPIPS backbone: "alex" or "vgg"
    patch_size: int = 32            # patch side in pixels (IN2N: 32)
    patch_share: float = 0.5        # share of each batch's rays drawn as patches (at least one patch)
    samples_per_ray: int = 0        # field evaluations per training ray; 0: the model's FieldConfig value


class TrainingInputError(ValueError):
    """Images/cameras/weights that do not fit together; the message says which and how."""


def rgb_loss(pred: torch.Tensor, target: torch.Tensor, ray_weights: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 3 (eq. 9 with per-ray weights), averaged instead of summed: mean_r w_r * mean_c (C^ - C)^2."""
    per_ray = ((pred - target) ** 2).mean(dim=-1)
    if ray_weights is not None:
        per_ray = per_ray * ray_weights
    return per_ray.mean()


def normalised_view_weights(scores: torch.Tensor, train_indices: Sequence[int]) -> torch.Tensor:
    """Eq. 9's S_i / mean(S): consistency scores normalised by their mean over the training views."""
    scores = torch.as_tensor(scores, dtype=torch.float32)
    mean = scores[torch.as_tensor(list(train_indices))].mean()
    if not torch.isfinite(scores).all() or float(mean) <= 0:
        raise TrainingInputError(f"view_weights must be finite with a positive mean over the training views, "
                                 f"got mean {float(mean)}; check the consistency scores passed to RayTrainer.step")
    return scores / mean


class RayTrainer:
    def __init__(self, model, images: torch.Tensor, cameras: Cameras, config: TrainConfig,
                 generator: torch.Generator, train_indices: Sequence[int] | None = None):
        if images.ndim != 4 or images.shape[-1] != 3 or not images.is_floating_point():
            raise TrainingInputError(f"RayTrainer: images must be an (N,H,W,3) float tensor in [0,1], "
                                     f"got {tuple(images.shape)} {images.dtype}")
        if images.shape[0] != len(cameras) or images.shape[1:3] != (cameras.height, cameras.width):
            raise TrainingInputError(f"RayTrainer: {images.shape[0]} images of {tuple(images.shape[1:3])} do not "
                                     f"match {len(cameras)} cameras of {(cameras.height, cameras.width)}")
        self.model = model
        self.device = next(model.parameters()).device
        self.images = images
        self.cameras = cameras.to(self.device)
        self.config = config
        self.generator = generator
        indices = range(len(cameras)) if train_indices is None else train_indices
        self.train_indices = torch.as_tensor(list(indices), dtype=torch.long)
        if len(self.train_indices) == 0:
            raise TrainingInputError("RayTrainer: no training views (every frame is held out)")
        if not any(p.requires_grad for p in model.parameters()):
            raise TrainingInputError("RayTrainer: the model has no trainable parameters")
        # The feature tables' gradients go to persistent buffers that the optimiser consumes chunk by chunk
        # (dualnerf.kernels.TableGradients), where the fused look-up kernel runs.
        tables = [p for p in feature_table_parameters(model) if p.requires_grad]
        self.table_gradients = None
        if kernels.grid_kernel() is not None and tables and all(
                p.device.type == "cpu" and p.dtype == torch.float32 for p in tables):
            self.table_gradients = kernels.TableGradients(tables)
        self.optimizer = FieldAdam(model, config.learning_rate, (config.beta1, config.beta2), config.eps,
                                   table_gradients=self.table_gradients)
        # Proposal bin spacing: the cube diagonal split into proposal_samples bins.
        spacing = 2.0 * math.sqrt(3.0) / model.config.proposal_samples
        self.sigma_threshold = -math.log(1.0 - config.occupancy_alpha) / spacing
        self.lpips = None
        if config.lpips_weight > 0:
            from dualnerf.lpips import load_lpips
            from dualnerf.patches import check_patch_size, patch_count

            check_patch_size(config.patch_size, config.lpips_net)
            self.patches = patch_count(config.rays_per_batch, config.patch_size, config.patch_share)
            self.lpips = load_lpips(config.lpips_net, self.device)

    def update_occupancy(self, blend=None) -> None:
        # The grid takes density values, never gradients: without a graph, 262k points per refresh are
        # not saved for a backward pass that never comes.
        @torch.no_grad()
        def density(x):
            return decode_density(self.model.query_density(x, blend=blend))
        self.model.occupancy_for(blend).update(density, self.generator, self.sigma_threshold,
                                               decay=self.config.occupancy_decay)

    def sample_batch(self):
        n = self.config.rays_per_batch
        g = self.generator
        if self.lpips is not None:
            return self._sample_patch_batch(n, g)
        pick = torch.randint(len(self.train_indices), (n,), generator=g)
        views = self.train_indices[pick]
        u = torch.randint(self.cameras.width, (n,), generator=g)
        v = torch.randint(self.cameras.height, (n,), generator=g)
        return views, u, v

    def _sample_patch_batch(self, n: int, g: torch.Generator):
        """`self.patches` square patches first (raster order each), then uniform rays for the rest."""
        from dualnerf.patches import sample_patches

        size = self.config.patch_size
        views, u, v = sample_patches(self.patches, size, self.train_indices, self.cameras.width,
                                     self.cameras.height, g)
        rest = n - len(views)
        pick = torch.randint(len(self.train_indices), (rest,), generator=g)
        u_rest = torch.randint(self.cameras.width, (rest,), generator=g)
        v_rest = torch.randint(self.cameras.height, (rest,), generator=g)
        return (torch.cat([views, self.train_indices[pick]]), torch.cat([u, u_rest]), torch.cat([v, v_rest]))

    def learning_rate(self, step: int) -> float:
        """Exponential decay; a function of the step only, so a resumed run follows the same schedule."""
        cfg = self.config
        if cfg.lr_decay_steps <= 0:
            return cfg.learning_rate
        return cfg.learning_rate * cfg.lr_final_ratio ** (min(step, cfg.lr_decay_steps) / cfg.lr_decay_steps)

    def step(self, step: int, blend=None, view_weights=None) -> dict:
        cfg = self.config
        for group in self.optimizer.param_groups:
            group["lr"] = self.learning_rate(step)
        if step >= cfg.occupancy_warmup and step % cfg.occupancy_every == 0:
            self.update_occupancy(blend)
        views, u, v = self.sample_batch()
        target = self.images[views, v, u].to(self.device, torch.float32)
        views_d, u_d, v_d = views.to(self.device), u.to(self.device), v.to(self.device)
        cams = self.cameras
        origins, dirs = pixel_rays(cams.c2w[views_d], cams.intrinsics[views_d], u_d, v_d)
        with self.table_gradients.collect() if self.table_gradients is not None else contextlib.nullcontext():
            result = render_rays(self.model, origins, dirs, cams.near[views_d], cams.far[views_d],
                                 blend=blend, generator=self.generator, with_distortion=cfg.distortion_weight > 0,
                                 samples_per_ray=cfg.samples_per_ray or None)
        ray_weights = None
        if view_weights is not None:
            ray_weights = normalised_view_weights(view_weights, self.train_indices.tolist()).to(self.device)[views_d]
        loss = rgb_loss(result["color"], target, ray_weights)
        if cfg.distortion_weight > 0:
            loss = loss + cfg.distortion_weight * result["distortion"].mean()
        lpips_value = None
        if self.lpips is not None:
            from dualnerf.patches import patch_lpips_loss

            patch_rays = self.patches * cfg.patch_size ** 2
            patch_weights = None if ray_weights is None else ray_weights[:patch_rays:cfg.patch_size ** 2]
            lpips_term = patch_lpips_loss(self.lpips, result["color"][:patch_rays], target[:patch_rays],
                                          cfg.patch_size, patch_weights)
            loss = loss + cfg.lpips_weight * lpips_term
            lpips_value = float(lpips_term.detach())
        self.optimizer.zero_grad(set_to_none=True)
        if loss.requires_grad:
            loss.backward()
            self.optimizer.step()
        mse = float(((result["color"].detach() - target) ** 2).mean())
        return {"loss": float(loss.detach()), "mse": mse, "psnr": -10.0 * math.log10(max(mse, 1e-12)),
                "samples": result["evaluated"],
                "occupancy": self.model.occupancy_for(blend).fraction(), "lpips": lpips_value}

    def state_dict(self) -> dict:
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
