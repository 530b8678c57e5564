"""Volume rendering (paper Sec. 3.1) with occupancy-grid empty-space skipping.

API:
    ray_cube_bounds(origins, dirs, near, far) -> (t_start (R,), t_end (R,))
    stratified_samples(t_start, t_end, num_samples, jitter=None) -> (t (R,S), delta (R,S))
    proposal_intervals(t_start, t_end, points_density, num_samples, num_proposal, uniform_share, jitter=None)
        -> (t (R,S) interval midpoints, delta (R,S) interval lengths)
    composite(sigma (R,S), delta (R,S)) -> weights (R,S)        w_i = T_i (1 - exp(-delta_i sigma_i))
    ray_samples(grid, config, origins, dirs, t_start, t_end, num_samples, jitter=None)
        -> (t (R,S), delta (R,S), mask (R,S) bool)   proposal intervals + occupancy (fused kernel or torch)
    render_rays(model, origins, dirs, near, far, *, blend=None, retreat=1.0, generator=None,
                with_distortion=False, samples_per_ray=None, termination_eps=0.0)
        -> dict(color (R,3), opacity (R,), evaluated: int[, distortion (R,)])
    distortion(weights (R,S), t (R,S), delta (R,S), length (R,)) -> (R,)   mip-NeRF 360 distortion loss
    render_view(model, c2w, intrinsics, width, height, near, far, *, blend=None, retreat=1.0,
                chunk=8192, termination_eps=0.0, mlp_precision="fp32", samples_per_ray=None)
        -> (H,W,3) float tensor in [0,1] (CPU)

`model` is a RadianceField (static or single-field baseline) or a DualField; blend=None renders the
static/single field, blend=(w_density, w_color) the fused dual field (see dualnerf.dual_field).

Sampling: the field lives in the normalised cube [-1,1]^3, so each ray is clipped to the overlap of
[near, far] with the cube. That segment is cut into `samples_per_ray` intervals (render_view:
`render_samples_per_ray`) by `proposal_intervals`: fine where the occupancy grid's density estimate
(scaled by FieldConfig.proposal_density_scale) says the visible surface is, coarse elsewhere (jittered
in training, deterministic when rendering). The field is evaluated at interval midpoints; midpoints in
empty occupancy cells are not evaluated and get sigma = 0.

Colour: C = sum_i w_i c_i + (1 - sum_i w_i) * background, where background is the model's decoded
background colour for the ray direction (learned, white or black; see dualnerf.fields).

Without autograd (renders) on the CPU kernels, the occupied samples are packed and composited per ray
in C++ (kernels.occupied_samples / composite_rays) instead of the torch code, which stays the path for
training and the reference; the two agree to float32 rounding (tests/test_render_kernels.py).
"""
from __future__ import annotations

import math

import torch

from dualnerf import kernels
from dualnerf.fields import TRUNC_EXP_MAX, decode_color, decode_density


def ray_cube_bounds(origins, dirs, near, far):
    """Overlap of [near, far] with the ray's segment inside [-1,1]^3 (slab test); empty when t_end <= t_start."""
    safe = torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
    t1 = (-1.0 - origins) / safe
    t2 = (1.0 - origins) / safe
    t_enter = torch.minimum(t1, t2).amax(dim=-1)
    t_exit = torch.maximum(t1, t2).amin(dim=-1)
    near = torch.as_tensor(near, dtype=origins.dtype, device=origins.device).expand(origins.shape[0])
    far = torch.as_tensor(far, dtype=origins.dtype, device=origins.device).expand(origins.shape[0])
    return torch.maximum(t_enter, near), torch.minimum(t_exit, far)


def stratified_samples(t_start, t_end, num_samples: int, jitter: torch.Tensor | None = None):
    """One sample per equal bin of [t_start, t_end]; at bin centres, or at `jitter` (R,S) in [0,1)."""
    length = (t_end - t_start).clamp(min=0.0)
    offset = torch.full((t_start.shape[0], num_samples), 0.5, device=t_start.device) if jitter is None else jitter
    bins = torch.arange(num_samples, device=t_start.device, dtype=t_start.dtype)
    step = length / num_samples
    t = t_start[:, None] + (bins[None, :] + offset) * step[:, None]
    return t, step[:, None].expand(-1, num_samples)


def composite(sigma: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """Blending weights w_i = T_i (1 - exp(-delta_i sigma_i)), T_i = exp(-sum_{j<i} delta_j sigma_j)."""
    tau = sigma * delta
    alpha = 1.0 - torch.exp(-tau)
    # Exclusive cumulative sum: T_1 = 1.
    transmittance = torch.exp(-(torch.cumsum(tau, dim=-1) - tau))
    return transmittance * alpha


def proposal_intervals(t_start, t_end, points_density, num_samples: int, num_proposal: int,
                       uniform_share: float, jitter: torch.Tensor | None = None):
    """Split each ray's [t_start, t_end] into `num_samples` intervals, fine where the proposal puts weight.

    The proposal is a coarse render of a cheap density estimate (the occupancy grid's per-cell density,
    `points_density(points) -> sigma`, evaluated at `num_proposal` bin centres): its blending weights,
    mixed with a uniform share so that every part of the ray keeps some intervals (new geometry can still
    appear), form a piecewise-constant pdf. Interval edges are its quantiles at 0, (i + jitter_i) / S, 1
    (hierarchical sampling by inverse transform, as in NeRF's coarse-to-fine scheme), so the intervals
    tile the segment exactly. Returns the interval midpoints t (R,S) and lengths delta (R,S).
    """
    n_rays = t_start.shape[0]
    t_c, delta_c = stratified_samples(t_start, t_end, num_proposal)
    with torch.no_grad():
        weights = composite(points_density(t_c), delta_c)
        pdf = (1.0 - uniform_share) * weights / (weights.sum(-1, keepdim=True) + 1e-6) + uniform_share / num_proposal
        pdf = pdf / pdf.sum(-1, keepdim=True)
        cdf = torch.cat([torch.zeros(n_rays, 1, dtype=pdf.dtype, device=pdf.device), pdf.cumsum(-1)], dim=-1)
        cdf[:, -1] = 1.0
        offset = 0.5 if jitter is None else jitter
        inner = (torch.arange(1, num_samples, device=t_start.device, dtype=t_start.dtype) - 0.5 + offset) / num_samples
        u = torch.cat([torch.zeros(n_rays, 1, device=t_start.device), inner.expand(n_rays, -1) if jitter is None
                       else inner, torch.ones(n_rays, 1, device=t_start.device)], dim=-1)
        bin_index = (torch.searchsorted(cdf, u.contiguous(), right=True) - 1).clamp(0, num_proposal - 1)
        frac = ((u - cdf.gather(-1, bin_index)) / pdf.gather(-1, bin_index)).clamp(0.0, 1.0)
        edges = t_start[:, None] + (bin_index + frac) * delta_c[:, :1]
        edges[:, 0], edges[:, -1] = t_start, torch.maximum(t_end, t_start)
    return 0.5 * (edges[:, 1:] + edges[:, :-1]), edges[:, 1:] - edges[:, :-1]


def distortion(weights: torch.Tensor, t: torch.Tensor, delta: torch.Tensor, length: torch.Tensor) -> torch.Tensor:
    """Mip-NeRF 360's distortion loss per ray (R,), on ray distances normalised by the segment `length`:
    sum_ij w_i w_j |s_i - s_j| + 1/3 sum_i w_i^2 delta_i. Small when the weight is one compact peak,
    large for haze spread along the ray. The double sum is O(S) with cumulative sums:
    sum_ij w_i w_j |s_i - s_j| = 2 sum_i w_i (s_i W_<i - (w s)_<i)."""
    scale = 1.0 / length.clamp(min=1e-9)[:, None]
    s, ds = t * scale, delta * scale
    w_before = torch.cumsum(weights, dim=-1) - weights
    ws_before = torch.cumsum(weights * s, dim=-1) - weights * s
    return 2.0 * (weights * (s * w_before - ws_before)).sum(-1) + (weights ** 2 * ds).sum(-1) / 3.0


# Early ray termination (render_view(..., termination_eps=RENDER_TERMINATION_EPS)): a sample is skipped once
# the transmittance in front of its segment is below this, which changes a colour by at most this much
# (see _query_until_opaque): far below one 8-bit step (1/255 = 0.004). OFF by default: on campsite with a
# 600-iteration f_S it skipped only 6% of the samples and the segment-wise evaluation made a 256x192 render
# 1.5-1.7x slower on 2 CPU cores (A/B, loaded machine); it pays off only for fields that turn opaque early.
# Training renders never terminate early (gradients need every sample).
RENDER_TERMINATION_EPS = 1e-4
# Samples per ray evaluated together before the transmittance is checked again.
TERMINATION_SEGMENT = 8


def _query_until_opaque(model, points, ray_features, delta, mask, blend, retreat, eps: float):
    """Evaluate the field front to back in segments of TERMINATION_SEGMENT samples per ray, only on rays
    whose transmittance before the segment is still >= eps. A skipped sample gets sigma = 0, so its weight
    (at most the transmittance T < eps in front of it) goes to the background term instead: the colour
    changes by sum_skipped w_i (c_i - c_bg), i.e. by less than eps per channel. Rays that never fall below
    eps evaluate exactly the samples of the reference path.
    Returns (sigma (R,S) with 0 where not evaluated, flat sample index r * S + s of the evaluated samples,
    their h_color), the last two in segment order."""
    n_rays, n_samples = mask.shape
    sigma = torch.zeros(mask.shape, dtype=points.dtype, device=points.device)
    optical_depth = torch.zeros(n_rays, dtype=points.dtype, device=points.device)
    log_eps = -math.log(eps)
    flat, colors = [], []
    for start in range(0, n_samples, TERMINATION_SEGMENT):
        stop = min(start + TERMINATION_SEGMENT, n_samples)
        seg = mask[:, start:stop] & (optical_depth <= log_eps)[:, None]
        index = torch.nonzero(seg)
        if index.shape[0] == 0:
            break
        ray_id, column = index[:, 0], index[:, 1] + start
        h_sigma, h_color = model.query(points[ray_id, column], None, blend=blend, retreat=retreat,
                                       dir_features=ray_features, dir_index=ray_id)
        seg_sigma = torch.zeros(seg.shape, dtype=h_sigma.dtype, device=h_sigma.device)
        seg_sigma[index[:, 0], index[:, 1]] = decode_density(h_sigma)
        sigma[:, start:stop] = seg_sigma
        optical_depth = optical_depth + (seg_sigma * delta[:, start:stop]).sum(-1)
        flat.append(ray_id * n_samples + column)
        colors.append(h_color)
    if not flat:
        return sigma, torch.zeros(0, dtype=torch.long, device=points.device), points.new_zeros((0, 3))
    return sigma, torch.cat(flat), torch.cat(colors)


def ray_grid_density(grid, origins, dirs, t, scale: float) -> torch.Tensor:
    """scale x the occupancy grid's density at the points origins + t dirs (R,S): the proposal's density
    estimate (the torch reference of the fused sampler in ray_samples)."""
    cells = grid.cell_index(origins[:, None, :] + t[..., None] * dirs[:, None, :])
    return scale * grid.density.reshape(-1)[cells]


def ray_samples(grid, config, origins, dirs, t_start, t_end, n_samples: int, jitter=None):
    """The render sampler: (t (R,S) interval midpoints, delta (R,S) lengths, mask (R,S)) for rays clipped
    to [t_start, t_end], mask = the ray overlaps the cube and the sample's occupancy cell may hold
    density. proposal_intervals on the occupancy grid's scaled density, then OccupancyGrid.occupied (the
    torch reference); the fused kernel computes the same per ray in one pass (equal to float32 rounding)."""
    module = kernels.grid_kernel()
    tensors = (origins, dirs, t_start, t_end, grid.density)
    if module is not None and all(x.device.type == "cpu" and x.dtype == torch.float32 for x in tensors):
        no_jitter = torch.empty(0)
        return tuple(module.ray_samples(origins, dirs, t_start, t_end, grid.density, grid.mask,
                                        float(config.proposal_density_scale), int(config.proposal_samples),
                                        int(n_samples), float(config.proposal_uniform),
                                        no_jitter if jitter is None else jitter, kernels.vector_path()))

    def grid_density(t):
        return ray_grid_density(grid, origins, dirs, t, config.proposal_density_scale)

    t, delta = proposal_intervals(t_start, t_end, grid_density, n_samples, config.proposal_samples,
                                  config.proposal_uniform, jitter)
    points = origins[:, None, :] + t[..., None] * dirs[:, None, :]
    return t, delta, (t_end > t_start)[:, None] & grid.occupied(points)


def _direction_features(model, dirs):
    field = getattr(model, "static_field", model)       # a DualField's fields share one config
    return field.direction_features(dirs)


def render_rays(model, origins, dirs, near, far, *, blend=None, retreat: float = 1.0,
                generator: torch.Generator | None = None, with_distortion: bool = False,
                samples_per_ray: int | None = None, termination_eps: float = 0.0) -> dict:
    """Colours of rays (training: jittered, `generator`; else bin centres) with `samples_per_ray` field
    evaluations each (default FieldConfig.samples_per_ray). termination_eps > 0: early ray termination,
    samples behind a transmittance below it are not evaluated (see _query_until_opaque); 0: every
    occupied sample is (the reference path, used in training)."""
    config = model.config
    n_samples = config.samples_per_ray if samples_per_ray is None else int(samples_per_ray)
    n_rays = origins.shape[0]
    t_start, t_end = ray_cube_bounds(origins, dirs, near, far)
    grid = model.occupancy_for(blend)

    jitter = None
    if generator is not None:
        jitter = torch.rand((n_rays, n_samples - 1), generator=generator).to(origins.device)
    t, delta, mask = ray_samples(grid, config, origins, dirs, t_start, t_end, n_samples, jitter)
    # The view direction's SH features once per ray (not per sample), shared by the fields of a DualField.
    ray_features = _direction_features(model, dirs)
    if termination_eps == 0.0 and not with_distortion and not torch.is_grad_enabled() and kernels.runs_on(t):
        return _render_packed(model, origins, dirs, t, delta, mask, ray_features, blend, retreat)
    points = origins[:, None, :] + t[..., None] * dirs[:, None, :]
    if termination_eps > 0.0:
        sigma, flat, h_color = _query_until_opaque(model, points, ray_features, delta, mask, blend, retreat,
                                                   termination_eps)
        weights = composite(sigma, delta)
        ray_id = torch.div(flat, n_samples, rounding_mode="floor")
        sample_weights = weights.reshape(-1)[flat]
    else:
        # The occupied samples' flat index r * S + s, found once and reused for every gather and scatter
        # (each boolean-mask index would search the mask again).
        flat = torch.nonzero(mask.reshape(-1))[:, 0]
        ray_id = torch.div(flat, n_samples, rounding_mode="floor")
        h_sigma, h_color = model.query(points.reshape(-1, 3)[flat], None, blend=blend, retreat=retreat,
                                       dir_features=ray_features, dir_index=ray_id)
        sigma = torch.zeros(mask.numel(), dtype=h_sigma.dtype, device=h_sigma.device).index_put(
            (flat,), decode_density(h_sigma)).view(mask.shape)
        weights = composite(sigma, delta)
        sample_weights = weights.reshape(-1)[flat]
    # Packed colour accumulation: only evaluated samples carry weight.
    color = torch.zeros(n_rays, 3, dtype=weights.dtype, device=weights.device).index_add(
        0, ray_id, sample_weights[:, None] * decode_color(h_color))
    opacity = weights.sum(dim=-1)
    background = decode_color(model.query_background(dirs, blend=blend, retreat=retreat,
                                                     dir_features=ray_features))
    color = color + (1.0 - opacity)[:, None] * background
    out = {"color": color, "opacity": opacity, "evaluated": int(ray_id.shape[0])}
    if with_distortion:
        out["distortion"] = distortion(weights, t, delta, (t_end - t_start).clamp(min=0.0))
    return out


def _render_packed(model, origins, dirs, t, delta, mask, ray_features, blend, retreat) -> dict:
    """render_rays without autograd on the kernels: the occupied samples packed, the fields queried, the
    samples composited per ray in C++ (the torch glue of the path below was ~15% of a 256x192 render).
    Agrees with the torch path to float32 rounding (tests/test_render_kernels.py)."""
    module = kernels.grid_kernel()
    x, flat, ray_id, starts = module.occupied_samples(origins, dirs, t, mask)
    h_sigma, h_color = model.query(x, None, blend=blend, retreat=retreat, dir_features=ray_features,
                                   dir_index=ray_id)
    background = decode_color(model.query_background(dirs, blend=blend, retreat=retreat,
                                                     dir_features=ray_features))
    color, opacity = module.composite_rays(h_sigma.float(), h_color.float(), flat, starts, delta,
                                           background.float(), TRUNC_EXP_MAX, kernels.vector_path())
    return {"color": color, "opacity": opacity, "evaluated": int(x.shape[0])}


@torch.no_grad()
def render_view(model, c2w, intrinsics, width: int, height: int, near: float, far: float, *,
                blend=None, retreat: float = 1.0, chunk: int = 8192, termination_eps: float = 0.0,
                mlp_precision: str = "fp32", samples_per_ray: int | None = None) -> torch.Tensor:
    """Full image in chunks of `chunk` rays (bounded memory); deterministic (bin-centre samples), with
    FieldConfig.render_samples_per_ray field evaluations per ray; termination_eps > 0 stops rays whose
    transmittance fell below it (each colour within termination_eps of the default, exact render).
    mlp_precision "bf16": the fused inference kernel's MLPs in bfloat16 (dualnerf.kernels.mlp_precision;
    ~1e-3 mean colour difference on campsite, for the IDU's view updates only). samples_per_ray: field
    evaluations per ray instead of FieldConfig.render_samples_per_ray (the IDU's view updates use its
    training sample count)."""
    from dualnerf.cameras import view_rays

    device = next(model.parameters()).device
    c2w = torch.as_tensor(c2w, dtype=torch.float32).to(device)
    intrinsics = torch.as_tensor(intrinsics, dtype=torch.float32).to(device)
    origins, dirs = view_rays(c2w, intrinsics, int(width), int(height))
    out = torch.empty(origins.shape[0], 3)
    with model.render_session(), kernels.mlp_precision(mlp_precision):
        for s in range(0, origins.shape[0], chunk):
            result = render_rays(model, origins[s:s + chunk], dirs[s:s + chunk], float(near), float(far),
                                 blend=blend, retreat=retreat,
                                 samples_per_ray=samples_per_ray or model.config.render_samples_per_ray,
                                 termination_eps=termination_eps)
            out[s:s + chunk] = result["color"].float().cpu()
    return out.reshape(int(height), int(width), 3).clamp(0.0, 1.0)
