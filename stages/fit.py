"""Stage "fit": field initialisation (paper Sec. 4.1), training the static field f_S on the dataset.

Input: upstream "dataset" (a preprocess result folder, `dualnerf.dataset`).
Outputs in ctx.out_dir:
    model/                 the static field (dualnerf.model.save_model)
    heldout/<name>.png     renders of the held-out views
    metrics.json           PSNR and SSIM (skimage) per held-out view and their means
    curve.json, curve.png  loss and held-out PSNR against the training step
The training time goes to the manifest (record: train_time_s, and per curve point): published files hold
no wall-clock times, so one key's result is the same bytes wherever it was computed.
Checkpoints (trainer state: model, optimiser, occupancy grid, generator; plus step, curve and elapsed
training time) are written every `checkpoint_every` iterations; a killed run resumes from the newest one
and ends with the same parameters as an uninterrupted run (on CPU; CUDA scatter-adds are not bitwise
deterministic). Training time excludes evaluation and checkpoint writing.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

from pipeline.stage import Resources, Stage, StageContext
from stages.numerics import TorchNumerics, use_step_threads


class FitInputError(ValueError):
    """A dataset or parameter combination the fit cannot use."""

    user_error = True


@dataclass(frozen=True)
class FitParams:
    iterations: int = 2000              # training steps
    rays_per_batch: int = 1024          # rays per training step
    learning_rate: float = 1e-2         # Adam's initial learning rate
    lr_final_ratio: float = 0.1         # exponential decay to learning_rate * lr_final_ratio at the last step
    seed: int = 0                       # initialisation and ray sampling
    device: str = "cpu"                 # "cpu" or "cuda"
    checkpoint_every: int = 250         # steps between in-stage checkpoints (where a killed run resumes)
    eval_every: int = 250               # held-out PSNR for the curve (on up to `curve_views` views)
    curve_views: int = 2                # held-out views rendered per curve point
    grid_levels: int = 4                # dense feature grids from 16^3, doubling up to grid_max_resolution
    grid_max_resolution: int = 128      # finest dense grid level (cells per side)
    grid_features: int = 2              # features per grid and plane entry
    plane_levels: int = 3               # xy/xz/yz feature planes, halving from plane_max_resolution (0: none)
    plane_max_resolution: int = 1024    # finest feature plane (texels per side)
    hidden_width: int = 64              # width of the field's MLPs
    samples_per_ray: int = 48           # field evaluations per training ray (placed by the occupancy-grid proposal)
    render_samples_per_ray: int = 96    # per ray in full-image renders of this model (see FieldConfig)
    proposal_samples: int = 256         # occupancy-grid look-ups per ray for the sample proposal
    background: str = "learned"         # learned | white | black
    lpips_weight: float = 0.0           # > 0: RGB + this x LPIPS on rendered patches (measured: see README)
    lpips_net: str = "alex"             # LPIPS backbone: "alex" or "vgg"
    patch_size: int = 32                # LPIPS patch side (pixels)
    patch_share: float = 0.5            # share of each batch drawn as patches when lpips_weight > 0
    num_threads: int = 0                # non-semantic; 0: the threads the engine grants


def grid_resolutions(levels: int, max_resolution: int) -> tuple[int, ...]:
    """Geometric resolutions from 16 (or max_resolution if smaller) up to max_resolution."""
    if levels < 1 or max_resolution < 2:
        raise FitInputError(f"fit: grid_levels must be >= 1 and grid_max_resolution >= 2, got {levels}, "
                            f"{max_resolution}")
    base = min(16, max_resolution)
    if levels == 1:
        return (max_resolution,)
    growth = (max_resolution / base) ** (1.0 / (levels - 1))
    return tuple(round(base * growth ** i) for i in range(levels))


def plane_resolutions(levels: int, max_resolution: int) -> tuple[int, ...]:
    """Plane resolutions halving down from max_resolution: (256, 512, 1024) for 3 levels and 1024."""
    if levels < 0 or (levels and max_resolution >> (levels - 1) < 2):
        raise FitInputError(f"fit: plane_levels must be >= 0 and plane_max_resolution / 2^(plane_levels - 1) "
                            f">= 2, got {levels}, {max_resolution}")
    return tuple(max_resolution >> i for i in reversed(range(levels)))


def field_config(p: FitParams):
    """The FieldConfig of the static field these fit parameters train."""
    from dualnerf.fields import FieldConfig

    return FieldConfig(grid_resolutions=grid_resolutions(p.grid_levels, p.grid_max_resolution),
                       plane_resolutions=plane_resolutions(p.plane_levels, p.plane_max_resolution),
                       grid_features=p.grid_features, hidden_width=p.hidden_width,
                       samples_per_ray=p.samples_per_ray, render_samples_per_ray=p.render_samples_per_ray,
                       proposal_samples=p.proposal_samples, background=p.background)


class FitStage(TorchNumerics, Stage):
    name = "fit"
    # 2: proposal density scale (a different sampler, so different fields); 3: feature planes and the
    # render sample count; 4: Adam skips feature-table entries without gradient (dualnerf.optim); 5: renders
    # composite in the packed kernel path (dualnerf.rendering._render_packed: float32 rounding differs);
    # 6: the MLPs train on the kernels (thread-count independent sums), renders' exp and sums as the
    # portable path's, torch on one thread; 7: the occupancy refresh's density MLP in the fused inference
    # kernel (kernels.field_inference, density_only) instead of torch's matmul: float32 rounding differs;
    # 8: the fused kernels flush subnormal floats to zero (dualnerf/kernels/kernels.h, "Denormals": a
    # training step's tiny gradients cost microcode assists), so values below 1.2e-38 become zeros
    version = "8"
    Params = FitParams
    upstream = ("dataset",)
    resources = Resources(cpus=2, gpus=0, memory_gb=3)
    nonsemantic_params = frozenset({"num_threads"})
    packages = ("torch",)

    def run(self, ctx: StageContext) -> None:
        import torch

        from dualnerf.dataset import load_dataset

        p = ctx.params
        if p.device not in ("cpu", "cuda"):
            raise FitInputError(f"fit: device must be 'cpu' or 'cuda', got {p.device!r}")
        if p.device == "cuda" and not torch.cuda.is_available():
            raise FitInputError("fit: device='cuda' but no CUDA device is available; set fit.device='cpu'")
        if p.iterations < 1 or p.checkpoint_every < 1 or p.eval_every < 1:
            raise FitInputError("fit: iterations, checkpoint_every and eval_every must be >= 1")
        use_step_threads(ctx, p.num_threads)
        dataset = load_dataset(Path(ctx.inputs["dataset"]))
        if len(dataset.indices("train")) == 0:
            raise FitInputError(f"fit: dataset {ctx.inputs['dataset']} has no training views (all held out); "
                                "rerun preprocess with a larger holdout_every")
        config = field_config(p)
        from dualnerf.kernels import kernel_name

        # Which look-up code ran: the fused kernel and the torch reference agree to float rounding only.
        ctx.record(seed=p.seed, field_config=config.to_dict(), lpips=lpips_setting(p),
                   field_kernel=kernel_name())
        ctx.log.info("loss: %s", lpips_setting(p))
        _FitRun(ctx, dataset, config).train_and_publish()


class _FitRun:
    """The training loop with checkpoint/resume, then evaluation and outputs."""

    def __init__(self, ctx, dataset, config):
        import torch

        from dualnerf.cameras import Cameras
        from dualnerf.fields import RadianceField
        from dualnerf.training import RayTrainer, TrainConfig

        p = ctx.params
        self.ctx, self.p, self.dataset = ctx, p, dataset
        self.device = torch.device(p.device)
        generator = torch.Generator().manual_seed(p.seed)
        self.model = RadianceField(config, generator).to(self.device)
        images = torch.from_numpy(dataset.images).to(self.device).float() / 255.0
        self.trainer = RayTrainer(self.model, images, Cameras.from_dataset(dataset), TrainConfig(
            rays_per_batch=p.rays_per_batch, learning_rate=p.learning_rate, lr_decay_steps=p.iterations,
            lr_final_ratio=p.lr_final_ratio, lpips_weight=p.lpips_weight, lpips_net=p.lpips_net,
            patch_size=p.patch_size, patch_share=p.patch_share), generator, dataset.indices("train"))
        heldout = dataset.indices("heldout")
        self.eval_split = "heldout" if len(heldout) else "train"
        self.eval_views = heldout if len(heldout) else dataset.indices("train")[:4]
        self.curve: list[dict] = []
        self.curve_times: list[float] = []         # training seconds at each curve point (manifest only)
        self.train_time = 0.0
        self.running_loss: float | None = None     # smoothed loss for the curve; checkpointed too
        self.start_step = 0

    # ---- checkpoints ---------------------------------------------------------------------------
    def save_checkpoint(self, step: int) -> None:
        import torch

        with self.ctx.checkpoint(step) as folder:
            torch.save(self.trainer.state_dict(), Path(folder) / "trainer.pt")
            (Path(folder) / "progress.json").write_text(json.dumps(
                {"step": step, "train_time_s": self.train_time, "running_loss": self.running_loss,
                 "curve": self.curve, "curve_times": self.curve_times}))

    def resume(self) -> None:
        import torch

        latest = self.ctx.latest_checkpoint()
        if latest is None:
            return
        step, folder = latest
        state = torch.load(Path(folder) / "trainer.pt", map_location=self.device, weights_only=True)
        self.trainer.load_state_dict(state)
        progress = json.loads((Path(folder) / "progress.json").read_text())
        self.start_step, self.train_time, self.curve = step, progress["train_time_s"], progress["curve"]
        self.running_loss = progress["running_loss"]
        self.curve_times = progress.get("curve_times", [])
        self.ctx.log.info("resumed from checkpoint at step %d", step)

    # ---- evaluation ----------------------------------------------------------------------------
    def render(self, index: int):
        from dualnerf.rendering import render_view

        ds = self.dataset
        return render_view(self.model, ds.c2w[index], ds.intrinsics[index], ds.width, ds.height,
                           float(ds.near[index]), float(ds.far[index])).numpy()

    def psnr(self, index: int) -> float:
        import numpy as np

        mse = float(np.mean((self.render(index) - self.dataset.images[index] / 255.0) ** 2))
        return -10.0 * math.log10(max(mse, 1e-12))

    def train_and_publish(self) -> None:
        p = self.p
        self.resume()
        with self.ctx.progress(p.iterations, "fit", initial=self.start_step) as bar:
            for step in range(self.start_step, p.iterations):
                started = time.perf_counter()
                stats = self.trainer.step(step)
                self.train_time += time.perf_counter() - started
                loss = stats["loss"]
                self.running_loss = loss if self.running_loss is None else 0.9 * self.running_loss + 0.1 * loss
                done = step + 1
                bar.update(1, loss=stats["loss"], train_psnr=stats["psnr"])
                if done % p.eval_every == 0 or done == p.iterations:
                    views = self.eval_views[: max(1, p.curve_views)]
                    psnr = sum(self.psnr(int(i)) for i in views) / len(views)
                    self.curve.append({"step": done, "loss": self.running_loss, "heldout_psnr": psnr,
                                       "occupancy": stats["occupancy"], "samples": stats["samples"]})
                    self.curve_times.append(round(self.train_time, 3))
                    self.ctx.log.info("step %d: held-out PSNR %.2f dB after %.1f s of training", done, psnr,
                                      self.train_time)
                if done % p.checkpoint_every == 0 and done < p.iterations:
                    self.save_checkpoint(done)
        self.publish()

    def publish(self) -> None:
        import numpy as np
        from skimage.metrics import structural_similarity

        from dualnerf.model import save_model
        from stages.images import write_png

        out = Path(self.ctx.out_dir)
        (out / "heldout").mkdir(parents=True, exist_ok=True)
        per_view = {}
        for index in self.eval_views:
            image = self.render(int(index))
            truth = self.dataset.images[index] / 255.0
            mse = float(np.mean((image - truth) ** 2))
            name = self.dataset.names[index]
            per_view[name] = {"psnr": -10.0 * math.log10(max(mse, 1e-12)),
                              "ssim": float(structural_similarity(truth, image, channel_axis=-1, data_range=1.0))}
            png = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
            write_png(out / "heldout" / f"{Path(name).stem}.png", png)
        metrics = {
            "split": self.eval_split,
            "psnr_mean": float(np.mean([v["psnr"] for v in per_view.values()])),
            "ssim_mean": float(np.mean([v["ssim"] for v in per_view.values()])),
            "views": per_view,
            "iterations": self.p.iterations,
            "occupancy_fraction": self.model.occupancy.fraction(),
            "lpips_loss": lpips_setting(self.p),
        }
        (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
        (out / "curve.json").write_text(json.dumps(self.curve, indent=1))
        plot_curve(self.curve, out / "curve.png")
        save_model(out / "model", self.model, extra={"stage": "fit", "psnr_mean": metrics["psnr_mean"]})
        self.ctx.record(train_time_s=round(self.train_time, 3), curve_train_time_s=self.curve_times)
        self.ctx.log.info("fit done: %s PSNR %.2f dB, SSIM %.3f, %.1f s training", self.eval_split,
                          metrics["psnr_mean"], metrics["ssim_mean"], self.train_time)


def lpips_setting(p) -> str:
    """The training loss as one line: RGB only, or RGB + LPIPS with its weight, backbone and patches."""
    if p.lpips_weight <= 0:
        return "off (RGB loss only)"
    return f"RGB + {p.lpips_weight:g} x LPIPS ({p.lpips_net}, v0.1) on {p.patch_size}x{p.patch_size} patches"


def plot_curve(curve: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    steps = [c["step"] for c in curve]
    ax.plot(steps, [c["heldout_psnr"] for c in curve], "o-", color="tab:blue")
    ax.set_xlabel("training step")
    ax.set_ylabel("held-out PSNR (dB)", color="tab:blue")
    twin = ax.twinx()
    twin.plot(steps, [c["loss"] for c in curve], "s--", color="tab:red")
    twin.set_ylabel("training loss", color="tab:red")
    twin.set_yscale("log")
    ax.set_title("static field fit")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
