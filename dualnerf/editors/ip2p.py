"""InstructPix2Pix (diffusers components) as Instruct-NeRF2NeRF uses it for dataset updates.

For each call: encode the render to latents, add noise at timestep T ~ U{lower * N, ..., upper * N}
(N = the scheduler's training timesteps, lower/upper = 0.02/0.98), then denoise with `steps` = 20 DDIM
steps spread over [0, T], using three-way classifier-free guidance (text scale 7.5, image scale 1.5)
conditioned on the latents of the ORIGINAL image, and decode. The weights are a diffusers-format folder
(unet/, vae/, text_encoder/, tokenizer/, scheduler/), e.g. the hub repo timbrooks/instruct-pix2pix.
"""
from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from dualnerf.editors.base import EditorError, to_float_image

IP2P_HUB_ID = "timbrooks/instruct-pix2pix"
SUBFOLDERS = ("unet", "vae", "text_encoder", "tokenizer", "scheduler")


@dataclass(frozen=True)
class InstructPix2PixConfig:
    guidance_scale: float = 7.5          # text guidance (IN2N default)
    image_guidance_scale: float = 1.5    # image guidance (IN2N default)
    steps: int = 20                      # DDIM steps over [0, T]
    lower_bound: float = 0.02            # noise level range as a fraction of the training timesteps
    upper_bound: float = 0.98
    device: str = "cpu"
    half_precision: bool = False         # float16 weights (CUDA only)

    def __post_init__(self) -> None:
        if not 0.0 <= self.lower_bound <= self.upper_bound <= 1.0:
            raise EditorError(f"ip2p lower_bound/upper_bound must satisfy 0 <= lower <= upper <= 1, got "
                              f"{self.lower_bound}/{self.upper_bound}.")
        if self.steps < 1:
            raise EditorError(f"ip2p steps must be >= 1, got {self.steps}.")


def guided_noise(noise_text, noise_image, noise_uncond, guidance_scale: float, image_guidance_scale: float):
    """InstructPix2Pix's three-way classifier-free guidance (Brooks et al., eq. 3)."""
    return (noise_uncond + guidance_scale * (noise_text - noise_image)
            + image_guidance_scale * (noise_image - noise_uncond))


def ddim_timesteps(max_timestep: int, steps: int) -> list[tuple[int, int]]:
    """(t, t_prev) pairs, 'leading' spacing over [0, max_timestep] as IN2N obtains by setting the
    scheduler's training length to T; t_prev = -1 means the clean end (alpha = 1)."""
    ratio = max(max_timestep // steps, 1)
    ts = [i * ratio for i in range(steps)][::-1]
    ts = [t + 1 if t + 1 <= max_timestep else t for t in ts]    # steps_offset = 1 as in SD's scheduler
    return [(t, t - ratio if t - ratio >= 0 else -1) for t in ts]


def ddim_sample(latents, predict_noise: Callable, schedule: list[tuple[int, int]], alphas_cumprod):
    """Deterministic DDIM (eta = 0): x0 = (x_t - sqrt(1-a_t) eps) / sqrt(a_t);
    x_prev = sqrt(a_prev) x0 + sqrt(1 - a_prev) eps."""
    for t, t_prev in schedule:
        eps = predict_noise(latents, t)
        a_t = alphas_cumprod[t]
        a_prev = alphas_cumprod[t_prev] if t_prev >= 0 else alphas_cumprod.new_tensor(1.0)
        x0 = (latents - (1 - a_t).sqrt() * eps) / a_t.sqrt()
        latents = a_prev.sqrt() * x0 + (1 - a_prev).sqrt() * eps
    return latents


class InstructPix2PixEditor:
    """InstructPix2Pix through diffusers; not a simulator."""

    is_simulator = False

    def __init__(self, model: str | Path = IP2P_HUB_ID, config: InstructPix2PixConfig = InstructPix2PixConfig()):
        import torch

        self.config = config
        self.model = str(model)
        self.device = torch.device(config.device)
        self.dtype = torch.float16 if (config.half_precision and self.device.type == "cuda") else torch.float32
        self._load(self.model)
        self.last_details: dict = {}
        self._text_cache: dict[str, object] = {}

    def _load(self, model: str) -> None:
        import torch

        local = Path(model)
        looks_local = local.exists() or model.startswith((".", "/", "~")) or model.count("/") != 1
        if looks_local:
            missing = [s for s in SUBFOLDERS if not (local / s).is_dir()]
            if missing:
                raise EditorError(
                    f"InstructPix2Pix weights not found: {local} lacks {', '.join(s + '/' for s in missing)}. "
                    f"Place the diffusers-format InstructPix2Pix model there (e.g. a download of the hub repo "
                    f"{IP2P_HUB_ID} with subfolders {', '.join(SUBFOLDERS)}), or set editor_model to a hub id "
                    f"on a machine with internet access.")
        try:
            from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
            from transformers import AutoTokenizer, CLIPTextModel

            self.unet = UNet2DConditionModel.from_pretrained(model, subfolder="unet", torch_dtype=self.dtype)
            self.vae = AutoencoderKL.from_pretrained(model, subfolder="vae", torch_dtype=self.dtype)
            self.text_encoder = CLIPTextModel.from_pretrained(model, subfolder="text_encoder", torch_dtype=self.dtype)
            self.tokenizer = AutoTokenizer.from_pretrained(model, subfolder="tokenizer")
            scheduler = DDIMScheduler.from_pretrained(model, subfolder="scheduler")
        except (OSError, ValueError) as err:
            raise EditorError(
                f"could not load InstructPix2Pix from '{model}' ({str(err).splitlines()[0]}). Put the "
                f"diffusers-format weights of {IP2P_HUB_ID} in a local folder (subfolders "
                f"{', '.join(SUBFOLDERS)}) and set editor_model to it.") from None
        for module in (self.unet, self.vae, self.text_encoder):
            module.to(self.device).eval().requires_grad_(False)
        self.alphas_cumprod = scheduler.alphas_cumprod.to(self.device, torch.float32)
        self.num_train_timesteps = int(scheduler.config.num_train_timesteps)
        self.vae_scale = 2 ** (len(self.vae.config.block_out_channels) - 1)
        digest = hashlib.sha256()
        for name in ("unet", "vae", "text_encoder"):
            digest.update(repr(getattr(self, name).config).encode())
        self._config_sha256 = digest.hexdigest()

    @property
    def identity(self) -> dict:
        return {"kind": "ip2p", "name": "InstructPix2Pix (diffusers)", "is_simulator": False,
                "model": self.model, "config_sha256": self._config_sha256, "config": asdict(self.config)}

    def _text_embeddings(self, instruction: str):
        import torch

        if instruction not in self._text_cache:
            tokens = self.tokenizer([instruction, ""], padding="max_length", truncation=True,
                                    max_length=self.tokenizer.model_max_length, return_tensors="pt")
            with torch.no_grad():
                text, uncond = self.text_encoder(tokens.input_ids.to(self.device))[0]
            # order matches the guidance chunks: (text, image-only, unconditional)
            self._text_cache[instruction] = torch.stack([text, uncond, uncond])
        return self._text_cache[instruction]

    def _to_tensor(self, image: np.ndarray, size: tuple[int, int]):
        import torch

        x = torch.from_numpy(to_float_image(image)).permute(2, 0, 1)[None].to(self.device)
        x = torch.nn.functional.interpolate(x, size=size, mode="bilinear", align_corners=False)
        return (x * 2.0 - 1.0).to(self.dtype)

    def edit(self, render: np.ndarray, original: np.ndarray, instruction: str, seed: int, step: int
             ) -> np.ndarray:
        import torch

        cfg = self.config
        height, width = np.asarray(render).shape[:2]
        size = (max(self.vae_scale, height // self.vae_scale * self.vae_scale),
                max(self.vae_scale, width // self.vae_scale * self.vae_scale))
        generator = torch.Generator(device="cpu").manual_seed(int(seed) * 1_000_003 + int(step))
        low = int(self.num_train_timesteps * cfg.lower_bound)
        high = max(low, int(self.num_train_timesteps * cfg.upper_bound))
        timestep = int(torch.randint(low, high + 1, (1,), generator=generator))
        timestep = min(max(timestep, 1), self.num_train_timesteps - 1)
        schedule = ddim_timesteps(timestep, cfg.steps)
        embeddings = self._text_embeddings(instruction)
        scaling = float(self.vae.config.scaling_factor)
        with torch.no_grad():
            posterior = self.vae.encode(self._to_tensor(render, size)).latent_dist
            eps0 = torch.randn(posterior.mean.shape, generator=generator).to(self.device, self.dtype)
            latents = (posterior.mean + posterior.std * eps0) * scaling
            # the original image conditions the UNet through its (unscaled) posterior mode, as in IP2P
            cond = self.vae.encode(self._to_tensor(original, size)).latent_dist.mode()
            cond = torch.cat([cond, cond, torch.zeros_like(cond)])
            noise = torch.randn(latents.shape, generator=generator).to(self.device, self.dtype)
            a_t = self.alphas_cumprod[schedule[0][0]].to(self.dtype)
            latents = a_t.sqrt() * latents + (1 - a_t).sqrt() * noise

            def predict_noise(x, t):
                model_in = torch.cat([torch.cat([x] * 3), cond], dim=1)
                out = self.unet(model_in, t, encoder_hidden_states=embeddings).sample
                return guided_noise(*out.chunk(3), cfg.guidance_scale, cfg.image_guidance_scale)

            latents = ddim_sample(latents, predict_noise, schedule, self.alphas_cumprod.to(self.dtype))
            image = self.vae.decode(latents / scaling).sample
        image = torch.nn.functional.interpolate(image.float(), size=(height, width), mode="bilinear",
                                                align_corners=False)
        self.last_details = {"editor": "InstructPix2Pix", "timestep": timestep,
                             "noise_level": timestep / self.num_train_timesteps, "steps": len(schedule)}
        return (image[0].permute(1, 2, 0) / 2 + 0.5).clamp(0, 1).cpu().numpy()
