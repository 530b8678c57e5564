"""Input encodings for the radiance field: multi-resolution dense feature grids and direction SH.

API:
    DenseGridEncoding(resolutions: tuple[int, ...], features: int, generator: torch.Generator | None)
        forward(x: (M,3) in [-1,1]^3) -> (M, len(resolutions) * features)
    HashGridEncoding(resolutions: tuple[int, ...], features: int, table_size_log2: int, generator)
        forward(x: (M,3) in [-1,1]^3) -> (M, len(resolutions) * features)
    PlaneGridEncoding(resolutions: tuple[int, ...], features: int, generator)
        forward(x: (M,3) in [-1,1]^3) -> (M, 3 * len(resolutions) * features)
    spherical_harmonics(d: (M,3) unit, degree: int) -> (M, degree**2)

Why dense grids: on a 2-core CPU a few trilinearly interpolated dense grids (F.grid_sample) train an
order of magnitude faster than an 8x256 MLP, need no custom kernels, and at the scene scales used here
(normalised cube, <=128^3 cells) fit comfortably in memory. Finer levels (256^3 and up) would need
hundreds of MB and a dense Adam update per step, so they are hashed (instant-NGP's spatial hash: a
fixed-size table indexed by XOR of the corner coordinates times large primes; collisions are resolved by
the MLP and by the coarser levels).

Why planes as well: sharp renders need features about as fine as a pixel's footprint (on campsite a
Gaussian blur of 1 px already costs the image 30 dB, 1.5 px 27 dB), i.e. ~1000 cells across the
normalised cube. A 1024^3 grid is out of reach, but three axis-aligned 1024^2 feature planes (the
tri-plane / TensoRF idea: a point reads the planes at its xy, xz and yz projections) cost 6M values
per feature and one fast 2D interpolation each. The coarse 3D grids tell apart points that project to
the same plane texel; flat surfaces aligned with a plane (the ground) get full resolution.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

# Initial grid values are tiny so the MLP initially sees ~zero features (as in hash-grid NeRFs).
_GRID_INIT_SCALE = 1e-4


def _feature_values(*shape: int, generator: torch.Generator | None) -> nn.Parameter:
    values = torch.empty(*shape)
    nn.init.uniform_(values, -_GRID_INIT_SCALE, _GRID_INIT_SCALE, generator=generator)
    # Grids and planes are stored channels-last (same shape and values, a point's features adjacent in
    # memory): the layout the fused look-up kernel (dualnerf.kernels) reads without a copy per call.
    if len(shape) == 5:
        values = values.contiguous(memory_format=torch.channels_last_3d)
    elif len(shape) == 4:
        values = values.contiguous(memory_format=torch.channels_last)
    return nn.Parameter(values)


class DenseGridEncoding(nn.Module):
    """Concatenated trilinear features from dense grids at several resolutions over [-1,1]^3."""

    def __init__(self, resolutions: tuple[int, ...], features: int, generator: torch.Generator | None = None):
        super().__init__()
        self.resolutions = tuple(int(r) for r in resolutions)
        self.features = int(features)
        self.grids = nn.ParameterList()
        for res in self.resolutions:
            self.grids.append(_feature_values(1, self.features, res, res, res, generator=generator))

    @property
    def output_dim(self) -> int:
        return len(self.resolutions) * self.features

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        m = x.shape[0]
        # grid_sample wants (N, D_out, H_out, W_out, 3); coordinate order (x, y, z) indexes (W, H, D).
        coords = x.reshape(1, m, 1, 1, 3).to(self.grids[0].dtype)
        parts = []
        for grid in self.grids:
            sampled = F.grid_sample(grid, coords, mode="bilinear", padding_mode="border", align_corners=True)
            parts.append(sampled.reshape(self.features, m))
        return torch.cat(parts, dim=0).t()


# Spatial-hash primes from the instant-NGP paper (the first is 1 so neighbouring x stay coherent).
_HASH_PRIMES = (1, 2654435761, 805459861)
_CORNERS = torch.tensor([[dx, dy, dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)], dtype=torch.long)


class HashGridEncoding(nn.Module):
    """Trilinear features from hashed grids: level l has resolution resolutions[l] and a table of
    2**table_size_log2 feature vectors (or fewer, when the dense grid would be smaller: then no hashing)."""

    def __init__(self, resolutions: tuple[int, ...], features: int, table_size_log2: int,
                 generator: torch.Generator | None = None):
        super().__init__()
        self.resolutions = tuple(int(r) for r in resolutions)
        self.features = int(features)
        self.tables = nn.ParameterList()
        for res in self.resolutions:
            size = min(2 ** int(table_size_log2), res ** 3)
            self.tables.append(_feature_values(size, self.features, generator=generator))

    @property
    def output_dim(self) -> int:
        return len(self.resolutions) * self.features

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        corners = _CORNERS.to(x.device)
        parts = []
        for res, table in zip(self.resolutions, self.tables):
            pos = (x.clamp(-1.0, 1.0) + 1.0) * (0.5 * (res - 1))
            base = pos.floor().clamp(max=res - 2)
            frac = pos - base
            ijk = base.long()[:, None, :] + corners                       # (M, 8, 3)
            size = table.shape[0]
            if size == res ** 3:
                index = (ijk[..., 0] * res + ijk[..., 1]) * res + ijk[..., 2]
            else:
                index = (ijk[..., 0] * _HASH_PRIMES[0]) ^ (ijk[..., 1] * _HASH_PRIMES[1]) ^ (ijk[..., 2] * _HASH_PRIMES[2])
                index = index & (size - 1)
            # Trilinear weights: prod over axes of frac (corner bit 1) or 1 - frac (corner bit 0).
            weight = torch.where(corners.bool(), frac[:, None, :], 1.0 - frac[:, None, :]).prod(dim=-1)
            values = table[index.reshape(-1)].reshape(x.shape[0], 8, self.features)
            parts.append((values * weight[..., None]).sum(dim=1))
        return torch.cat(parts, dim=-1)


class PlaneGridEncoding(nn.Module):
    """Bilinear features from the xy, xz and yz planes at several resolutions over [-1,1]^2."""

    _AXES = ((0, 1), (0, 2), (1, 2))

    def __init__(self, resolutions: tuple[int, ...], features: int, generator: torch.Generator | None = None):
        super().__init__()
        self.resolutions = tuple(int(r) for r in resolutions)
        self.features = int(features)
        self.planes = nn.ParameterList()
        for res in self.resolutions:
            for _ in self._AXES:
                self.planes.append(_feature_values(1, self.features, res, res, generator=generator))

    @property
    def output_dim(self) -> int:
        return 3 * len(self.resolutions) * self.features

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        m = x.shape[0]
        x = x.to(self.planes[0].dtype)
        # grid_sample wants (N, H_out, W_out, 2); coordinate order (u, v) indexes (W, H).
        coords = [x[:, list(axes)].reshape(1, m, 1, 2) for axes in self._AXES]
        parts = []
        for level in range(len(self.resolutions)):
            for axis in range(3):
                plane = self.planes[3 * level + axis]
                sampled = F.grid_sample(plane, coords[axis], mode="bilinear", padding_mode="border",
                                        align_corners=True)
                parts.append(sampled.reshape(self.features, m))
        return torch.cat(parts, dim=0).t()


def spherical_harmonics(d: torch.Tensor, degree: int) -> torch.Tensor:
    """Real spherical harmonics of unit directions, bands 0..degree-1 (degree**2 components, degree<=4).

    Constants are the standard orthonormal real SH normalisation (integral of Y_i Y_j over the sphere = δ_ij).
    """
    if not 1 <= degree <= 4:
        raise ValueError(f"spherical_harmonics: degree must be in 1..4, got {degree}")
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree > 1:
        out += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
    if degree > 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            1.0925484305920792 * x * y,
            -1.0925484305920792 * y * z,
            0.94617469575755997 * zz - 0.31539156525251999,
            -1.0925484305920792 * x * z,
            0.54627421529603959 * (xx - yy),
        ]
    if degree > 3:
        out += [
            0.59004358992664352 * y * (-3.0 * xx + yy),
            2.8906114426405538 * x * y * z,
            0.45704579946446572 * y * (1.0 - 5.0 * zz),
            0.3731763325901154 * z * (5.0 * zz - 3.0),
            0.45704579946446572 * x * (1.0 - 5.0 * zz),
            1.4453057213202769 * z * (xx - yy),
            0.59004358992664352 * x * (-xx + 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)
