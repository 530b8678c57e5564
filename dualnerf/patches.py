"""Square-patch ray batches and the LPIPS loss on rendered patches (Instruct-NeRF2NeRF trains with
L1 + LPIPS on 32x32 patches; DualNeRF Sec. 4.4 with "both the RGB loss and LPIPS loss").

API:
    patch_count(rays_per_batch, patch_size, patch_share) -> int     patches per batch (>= 1)
    sample_patches(n, patch_size, train_indices, width, height, generator) -> views, u, v
        n patches, each patch_size^2 rays in raster order (patch p's rays are p*size^2 .. (p+1)*size^2-1)
    patch_lpips_loss(lpips_model, pred (n*s*s,3), target (n*s*s,3), patch_size, patch_weights (n,) | None)
        -> scalar: mean over patches of w_p * LPIPS(rendered patch p, target patch p)

A batch with the LPIPS loss on holds `patch_count` patches (about `patch_share` of its rays, at least one
patch) followed by uniformly drawn rays for the rest; the RGB loss covers all of them. Patches are drawn
from the trainer's seeded generator, and only when the LPIPS loss is on, so runs without it draw exactly
the numbers they drew before.
"""
from __future__ import annotations

import torch


class PatchConfigError(ValueError):
    """Patch settings that cannot fill a batch or fit the images; the message names the parameter."""

    user_error = True


def patch_count(rays_per_batch: int, patch_size: int, patch_share: float) -> int:
    if patch_size < 1 or not 0.0 < patch_share <= 1.0:
        raise PatchConfigError(f"patch_size must be >= 1 and patch_share in (0, 1], got {patch_size} and "
                               f"{patch_share}.")
    per_patch = patch_size * patch_size
    if per_patch > rays_per_batch:
        raise PatchConfigError(f"one {patch_size}x{patch_size} patch is {per_patch} rays, more than "
                               f"rays_per_batch = {rays_per_batch}; raise rays_per_batch or lower patch_size.")
    return max(1, round(patch_share * rays_per_batch / per_patch))


def check_patch_size(patch_size: int, net: str) -> None:
    from dualnerf.lpips import MIN_SIZE

    smallest = MIN_SIZE.get(net, 1)
    if patch_size < smallest:
        raise PatchConfigError(f"patch_size {patch_size} is too small for the LPIPS backbone '{net}' (it needs "
                               f">= {smallest} pixels); raise patch_size or use lpips_net 'vgg' (>= 16).")


def sample_patches(n: int, patch_size: int, train_indices: torch.Tensor, width: int, height: int,
                   generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    if patch_size > width or patch_size > height:
        raise PatchConfigError(f"patch_size {patch_size} does not fit in {width}x{height} images; lower "
                               f"patch_size or set lpips_weight = 0.")
    pick = torch.randint(len(train_indices), (n,), generator=generator)
    left = torch.randint(width - patch_size + 1, (n,), generator=generator)
    top = torch.randint(height - patch_size + 1, (n,), generator=generator)
    offsets = torch.arange(patch_size)
    rows = (top[:, None] + offsets[None, :])[:, :, None].expand(n, patch_size, patch_size)
    cols = (left[:, None] + offsets[None, :])[:, None, :].expand(n, patch_size, patch_size)
    views = train_indices[pick][:, None, None].expand(n, patch_size, patch_size)
    return views.reshape(-1), cols.reshape(-1), rows.reshape(-1)


def _as_patch_images(colors: torch.Tensor, n: int, patch_size: int) -> torch.Tensor:
    """(n*s*s, 3) colours in [0, 1] -> (n, 3, s, s) in [-1, 1], LPIPS's input range."""
    return colors.reshape(n, patch_size, patch_size, 3).permute(0, 3, 1, 2) * 2.0 - 1.0


def patch_lpips_loss(lpips_model, pred: torch.Tensor, target: torch.Tensor, patch_size: int,
                     patch_weights: torch.Tensor | None = None) -> torch.Tensor:
    n = pred.shape[0] // (patch_size * patch_size)
    distances = lpips_model(_as_patch_images(pred, n, patch_size), _as_patch_images(target, n, patch_size))
    if patch_weights is not None:
        distances = distances * patch_weights
    return distances.mean()
