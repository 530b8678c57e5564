"""Rays from dataset cameras (OpenCV c2w convention of `dualnerf.dataset`).

API:
    Cameras(c2w (N,4,4), intrinsics (N,4) fx fy cx cy, near (N,), far (N,), width, height)   float32 tensors
        Cameras.from_dataset(dataset, device="cpu");  .to(device)
    pixel_rays(c2w (R,4,4), intrinsics (R,4), u (R,), v (R,)) -> (origins (R,3), directions (R,3) unit)
    view_rays(c2w (4,4), intrinsics (4,), width, height) -> (origins (H*W,3), directions (H*W,3)), row-major

Camera axes are OpenCV: x right, y down, z forward; the pixel (u, v) (column, row) has its centre at
(u + 0.5, v + 0.5). Directions are unit length, so a ray parameter t is a Euclidean distance from the
camera centre and a frame's near/far are distances along the ray (not z-depths).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class Cameras:
    c2w: torch.Tensor
    intrinsics: torch.Tensor
    near: torch.Tensor
    far: torch.Tensor
    width: int
    height: int

    @classmethod
    def from_dataset(cls, dataset, device: str | torch.device = "cpu") -> Cameras:
        def t(a):
            return torch.as_tensor(np.asarray(a), dtype=torch.float32, device=device)
        return cls(t(dataset.c2w), t(dataset.intrinsics), t(dataset.near), t(dataset.far),
                   int(dataset.width), int(dataset.height))

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    def to(self, device) -> Cameras:
        return Cameras(self.c2w.to(device), self.intrinsics.to(device), self.near.to(device),
                       self.far.to(device), self.width, self.height)


def pixel_rays(c2w: torch.Tensor, intrinsics: torch.Tensor, u: torch.Tensor, v: torch.Tensor):
    """World-space rays through pixel centres; one camera per ray (gather cameras first)."""
    fx, fy, cx, cy = intrinsics.unbind(-1)
    x = (u.to(c2w.dtype) + 0.5 - cx) / fx
    y = (v.to(c2w.dtype) + 0.5 - cy) / fy
    d_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)
    d_world = torch.einsum("rij,rj->ri", c2w[:, :3, :3], d_cam)
    d_world = d_world / d_world.norm(dim=-1, keepdim=True)
    return c2w[:, :3, 3].expand_as(d_world).contiguous(), d_world


def view_rays(c2w, intrinsics, width: int, height: int):
    """All rays of one view, row-major (index = v * width + u)."""
    c2w = torch.as_tensor(np.asarray(c2w) if not torch.is_tensor(c2w) else c2w, dtype=torch.float32)
    intrinsics = torch.as_tensor(np.asarray(intrinsics) if not torch.is_tensor(intrinsics) else intrinsics,
                                 dtype=torch.float32, device=c2w.device)
    v, u = torch.meshgrid(torch.arange(height, device=c2w.device), torch.arange(width, device=c2w.device),
                          indexing="ij")
    n = height * width
    return pixel_rays(c2w.reshape(1, 4, 4).expand(n, 4, 4), intrinsics.reshape(1, 4).expand(n, 4),
                      u.reshape(-1), v.reshape(-1))
