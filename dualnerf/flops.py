"""Arithmetic cost of one radiance-field evaluation, counted from its FieldConfig (dualnerf.fields).

API:
    field_flops_per_sample(config: FieldConfig) -> float     FLOPs of RadianceField.forward per point

Counted: each Linear layer 2 x n_in x n_out (multiply-add) + n_out (bias), ReLU n_out; each trilinear
look-up (dense and hashed levels) 8 corners x features x 2 plus ~30 for the weights; each bilinear plane
look-up 4 x features x 2 plus ~15; the direction's SH features ~2 per component. Memory traffic is not
counted: the look-ups are bound by it, so a FLOP-based limit is optimistic for them.
"""
from __future__ import annotations


def _linear(n_in: int, n_out: int, relu: bool) -> float:
    return 2.0 * n_in * n_out + n_out + (n_out if relu else 0)


def field_flops_per_sample(config) -> float:
    f = config.grid_features
    levels_3d = len(config.grid_resolutions) + len(config.hash_resolutions)
    planes = 3 * len(config.plane_resolutions)
    encoding = levels_3d * (8 * f * 2 + 30) + planes * (4 * f * 2 + 15)
    n_features = (levels_3d + planes) * f
    width, geo, n_dir = config.hidden_width, config.geo_features, config.direction_degree ** 2
    mlp = (_linear(n_features, width, True) + _linear(width, 1 + geo, False)
           + _linear(geo + n_dir, width, True) + _linear(width, 3, False))
    return float(encoding + mlp + 2 * n_dir)
