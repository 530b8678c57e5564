"""One radiance field f (paper eq. 1, modified as in Sec. 4.1 to output hidden features).

API:
    FieldConfig(...)                      frozen dataclass; `to_dict()` / `FieldConfig.from_dict(d)`
    RadianceField(config, generator=None) nn.Module
        forward(x: (M,3) in [-1,1]^3, d: (M,3) unit, dir_features=None) -> (h_sigma: (M,), h_color: (M,3))
        direction_features(d) -> (M, direction_degree**2)   SH of d; pass as dir_features to skip recomputing
        features(x) -> (M, F)   encoded features (fused kernel or reference_features(x), see dualnerf.kernels)
        heads(features, sh) -> (h_sigma, h_color);  density_head(features) -> h_sigma   the MLPs alone
        background_hidden(d: (R,3) unit, dir_features=None) -> (R,3)   pre-sigmoid background colour (below)
        query(x, d, blend=None, retreat=1.0, dir_features=None)   same as forward; rejects a blend
        occupancy: OccupancyGrid                  empty-space skipping state, saved with the model
    decode_density(h_sigma) -> sigma >= 0        D_sigma: truncated exponential
    decode_color(h_color) -> rgb in (0,1)        D_c: sigmoid

Architecture (sized for a 2-core CPU): dense trilinear feature grids (16^3..128^3 by default), optional
xy/xz/yz feature planes (the fit stage uses 256^2..1024^2) and optional hashed finer levels -> density
MLP (1 hidden layer) giving h_sigma and geometry features -> colour MLP on those and the view
direction's SH features giving h_color. FieldConfig also carries the render settings saved with a model
(samples_per_ray, render_samples_per_ray, proposal_samples, proposal_uniform, occupancy_resolution; see
dualnerf.rendering).

Hidden features are *pre-activation* values: the paper's decoders D_sigma and D_c are plain activation
functions (Sec. 4.4), so fusing two fields (eqs. 4-5, `dualnerf.dual_field`) happens on these values.

Background: rays that leave the normalised cube [-1,1]^3 with transmittance left see a background
colour. `background="learned"` gives each field a view-dependent background (a linear map of the
direction's SH features, decoded with the same sigmoid and fused like h_color), which suits captured
scenes with sky or far walls; "white" / "black" use a constant.
"""
from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass

import torch
from torch import nn

from dualnerf import kernels
from dualnerf.encoding import DenseGridEncoding, HashGridEncoding, PlaneGridEncoding, spherical_harmonics
from dualnerf.occupancy import OccupancyGrid

BACKGROUNDS = ("learned", "white", "black")
# exp() beyond this would overflow float32 rendering maths; the backward uses the same clamp.
TRUNC_EXP_MAX = 15.0
# Rows per block in heads() / density_head() without autograd (see heads); tuned on 2 cores (renders).
INFERENCE_BLOCK = 16384


class FieldConfigError(ValueError):
    """A field configuration that cannot build a model; the message names the field and a fix."""


@dataclass(frozen=True)
class FieldConfig:
    grid_resolutions: tuple[int, ...] = (16, 32, 64, 128)
    grid_features: int = 2
    hash_resolutions: tuple[int, ...] = ()   # extra finer levels stored in spatial-hash tables
    hash_table_size_log2: int = 19
    plane_resolutions: tuple[int, ...] = ()  # extra xy/xz/yz feature planes (see dualnerf.encoding)
    hidden_width: int = 64
    geo_features: int = 15           # density-MLP outputs passed on to the colour MLP
    direction_degree: int = 4        # SH bands for the view direction (degree**2 features)
    density_bias: float = -4.0       # initial h_sigma offset: start almost transparent (sigma ~ 0.02) so
                                     # the occupancy grid can prune free space early
    background: str = "learned"
    samples_per_ray: int = 48        # field evaluations per training ray (intervals placed by the proposal)
    # Field evaluations per ray in full-image renders (render_view: held-out views, IDU view updates,
    # evaluation). More than in training: a training ray's jittered intervals find a thin surface on
    # average, a render's fixed intervals miss it for good. Measured on campsite (planes, 180 s fit):
    # held-out PSNR 27.0 dB at 48, 28.1 at 96, 28.4 at 128 samples; 1.8 / 3.3 / 4.5 s per 256x192 image.
    render_samples_per_ray: int = 96
    proposal_samples: int = 256      # occupancy-grid lookups per ray for the proposal (cheap)
    proposal_uniform: float = 0.15   # share of the intervals spread uniformly along the ray
    # The proposal renders the occupancy grid's density scaled by this. The grid keeps a decayed running
    # *max* of sampled densities (right for the skip mask, biased high for a proposal): unscaled, the
    # first cell holding a density spike takes all intervals and the true surface behind it gets only the
    # uniform share. Scaled down, the intervals spread over the first few occupied cells along the ray.
    # Measured on campsite (bench_fit, 60 s): held-out PSNR 21.4 dB at 1, 23.1 at 0.1, 24.4 at 0.02,
    # 25.3 at 0.005, 25.0 at 0.001.
    proposal_density_scale: float = 0.005
    occupancy_resolution: int = 64

    def __post_init__(self):
        if self.background not in BACKGROUNDS:
            raise FieldConfigError(f"FieldConfig.background must be one of {BACKGROUNDS}, got {self.background!r}")
        if not self.grid_resolutions or min(self.grid_resolutions) < 2:
            raise FieldConfigError(f"FieldConfig.grid_resolutions needs values >= 2, got {self.grid_resolutions}")
        if not self.proposal_density_scale > 0.0:
            raise FieldConfigError(f"FieldConfig.proposal_density_scale must be > 0, got {self.proposal_density_scale}")
        if not 0.0 < self.proposal_uniform <= 1.0:
            raise FieldConfigError(f"FieldConfig.proposal_uniform must be in (0, 1], got {self.proposal_uniform}")
        for name in ("grid_features", "hidden_width", "geo_features", "samples_per_ray", "render_samples_per_ray",
                     "proposal_samples", "occupancy_resolution"):
            if getattr(self, name) < 1:
                raise FieldConfigError(f"FieldConfig.{name} must be >= 1, got {getattr(self, name)}")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["grid_resolutions"] = list(self.grid_resolutions)
        d["hash_resolutions"] = list(self.hash_resolutions)
        d["plane_resolutions"] = list(self.plane_resolutions)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> FieldConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise FieldConfigError(f"field config has unknown keys {unknown}; the model was saved by a newer "
                                   "version of dualnerf, upgrade or refit")
        d = dict(d)
        for key in ("grid_resolutions", "hash_resolutions", "plane_resolutions"):
            if key in d:
                d[key] = tuple(int(r) for r in d[key])
        return cls(**d)


class _TruncExp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x):
        clamped = x.clamp(max=TRUNC_EXP_MAX)
        ctx.save_for_backward(clamped)
        return torch.exp(clamped)

    @staticmethod
    def backward(ctx, grad):
        # Gradient of exp at the clamped value keeps flowing for large inputs (no dead units).
        (clamped,) = ctx.saved_tensors
        return grad * torch.exp(clamped)


def decode_density(h_sigma: torch.Tensor) -> torch.Tensor:
    """D_sigma (Sec. 4.4): truncated exponential of the density feature."""
    return _TruncExp.apply(h_sigma)


def decode_color(h_color: torch.Tensor) -> torch.Tensor:
    """D_c (Sec. 4.4): sigmoid of the colour feature."""
    return torch.sigmoid(h_color)


def _linear(n_in: int, n_out: int, generator: torch.Generator | None) -> nn.Linear:
    layer = nn.Linear(n_in, n_out)
    bound = (6.0 / (n_in + n_out)) ** 0.5
    nn.init.uniform_(layer.weight, -bound, bound, generator=generator)
    nn.init.zeros_(layer.bias)
    return layer


class RadianceField(nn.Module):
    """Feature grids + tiny MLPs -> (h_sigma, h_color) hidden features (Sec. 4.1)."""

    def __init__(self, config: FieldConfig = FieldConfig(), generator: torch.Generator | None = None):
        super().__init__()
        self.config = config
        self.encoding = DenseGridEncoding(config.grid_resolutions, config.grid_features, generator)
        self.hash_encoding = None
        if config.hash_resolutions:
            self.hash_encoding = HashGridEncoding(config.hash_resolutions, config.grid_features,
                                                  config.hash_table_size_log2, generator)
        self.plane_encoding = None
        if config.plane_resolutions:
            self.plane_encoding = PlaneGridEncoding(config.plane_resolutions, config.grid_features, generator)
        width = config.hidden_width
        n_features = sum(e.output_dim for e in self._encodings())
        self.density_mlp = nn.Sequential(
            _linear(n_features, width, generator), nn.ReLU(inplace=True),
            _linear(width, 1 + config.geo_features, generator))
        with torch.no_grad():
            self.density_mlp[-1].bias[0] = config.density_bias
        n_dir = config.direction_degree ** 2
        self.color_mlp = nn.Sequential(
            _linear(config.geo_features + n_dir, width, generator), nn.ReLU(inplace=True),
            _linear(width, 3, generator))
        self.background_head = _linear(n_dir, 3, generator) if config.background == "learned" else None
        self.occupancy = OccupancyGrid(config.occupancy_resolution)

    def _encodings(self) -> list[nn.Module]:
        return [e for e in (self.encoding, self.hash_encoding, self.plane_encoding) if e is not None]

    def render_session(self):
        """A whole-image render (see DualField.render_session): nothing to prepare for one field."""
        return contextlib.nullcontext()

    def grid_tables(self) -> tuple[list, list]:
        """(dense grids, planes): the tables the fused look-up kernel reads (dualnerf.kernels)."""
        planes = list(self.plane_encoding.planes) if self.plane_encoding is not None else []
        return list(self.encoding.grids), planes

    def can_fuse(self, x: torch.Tensor) -> bool:
        return self.hash_encoding is None and kernels.can_fuse(x, self.config.grid_features)

    def needs_autograd(self, *inputs: torch.Tensor) -> bool:
        """Whether a forward must record autograd: grad mode is on and an input or a parameter requires
        grad (a frozen f_S never does, so it takes the inference kernels in training steps too)."""
        return torch.is_grad_enabled() and (any(t.requires_grad for t in inputs)
                                            or any(p.requires_grad for p in self.parameters()))

    def can_infer(self, x: torch.Tensor) -> bool:
        """The fused inference kernel (look-ups and MLPs in one pass, no autograd) applies to x."""
        return (self.hash_encoding is None and kernels.can_infer(x, self.config.grid_features)
                and not self.needs_autograd(x))

    def mlp_layers(self) -> tuple[nn.Linear, nn.Linear, nn.Linear, nn.Linear]:
        """(density hidden, density out, colour hidden, colour out): the layers heads() runs, in order."""
        return self.density_mlp[0], self.density_mlp[2], self.color_mlp[0], self.color_mlp[2]

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """Concatenated encodings of x: the fused CPU kernel (dualnerf.kernels) when it applies, else the
        encodings' plain torch code (the reference; they agree to float32 rounding)."""
        if self.can_fuse(x):
            return kernels.fused_grid_features(x, *self.grid_tables())
        return self.reference_features(x)

    def reference_features(self, x: torch.Tensor) -> torch.Tensor:
        encodings = self._encodings()
        if len(encodings) == 1:
            return self.encoding(x)
        return torch.cat([e(x) for e in encodings], dim=-1)

    def direction_features(self, d: torch.Tensor) -> torch.Tensor:
        """The view direction's SH features (M, degree**2) that forward / background_hidden consume."""
        return spherical_harmonics(d, self.config.direction_degree)

    def forward(self, x: torch.Tensor, d: torch.Tensor | None, dir_features: torch.Tensor | None = None,
                dir_index: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """`dir_features` (M, degree**2): direction_features(d) computed by the caller (a renderer computes
        them once per ray, not per sample, and shares them between the fields of a DualField); then d is
        not used. The result is the same either way (element-wise maths). With `dir_index` (M,), sample i's
        are dir_features[dir_index[i]] (one row per ray). Without autograd the fused inference kernel runs
        where it applies (dualnerf.kernels.field_inference; equal to float32 rounding)."""
        sh = self.direction_features(d) if dir_features is None else dir_features
        if self.can_infer(x):           # renders: look-ups and MLPs in one cache-resident pass
            return kernels.field_inference(x, sh, self.grid_tables(), self.mlp_layers(), sh_index=dir_index)
        features = self.features(x)
        if self.needs_autograd(features) and kernels.can_train(features, sh):    # training: no (M, S) copy
            return kernels.train_heads(features, sh, self.mlp_layers(), sh_index=dir_index)
        return self.heads(features, sh if dir_index is None else sh[dir_index])

    def heads(self, features: torch.Tensor, sh: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The MLPs: (h_sigma, h_color) from encoded features (M, F) and direction SH features (M, degree**2).

        Where the kernel is built: without autograd (renders, the frozen f_S) its inference MLPs
        (dualnerf.kernels.mlp_inference), with autograd (training) its training MLPs
        (kernels.train_heads); both equal torch's layers to float32 rounding, on any thread count. In
        the torch reference the rows run in blocks of INFERENCE_BLOCK without autograd, so the MLPs'
        (block, hidden_width) activations stay in cache instead of streaming through memory three times
        per layer (bias copy, matmul, ReLU)."""
        if kernels.can_train(features, sh):
            if not self.needs_autograd(features, sh):
                return kernels.mlp_inference(features, sh, self.mlp_layers())
            return kernels.train_heads(features, sh, self.mlp_layers())
        if torch.is_grad_enabled() or features.shape[0] <= INFERENCE_BLOCK:
            return self._heads_block(features, sh)
        h_sigma = features.new_empty(features.shape[0])
        h_color = features.new_empty(features.shape[0], 3)
        for start in range(0, features.shape[0], INFERENCE_BLOCK):
            block = slice(start, start + INFERENCE_BLOCK)
            h_sigma[block], h_color[block] = self._heads_block(features[block], sh[block])
        return h_sigma, h_color

    def _heads_block(self, features: torch.Tensor, sh: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.density_mlp(features)
        h_sigma, geo = out[:, 0], out[:, 1:]
        h_color = self.color_mlp(torch.cat([geo, sh], dim=-1))
        return h_sigma, h_color

    def density_hidden(self, x: torch.Tensor) -> torch.Tensor:
        """h_sigma only (no colour branch): used by the occupancy-grid update. Without autograd on the
        kernels, look-ups and density MLP in one fused pass (kernels.field_inference, density_only)."""
        if self.can_infer(x):
            return kernels.field_inference(x, self.empty_direction_features(x), self.grid_tables(),
                                           self.mlp_layers(), density_only=True)[0]
        return self.density_head(self.features(x))

    def empty_direction_features(self, x: torch.Tensor) -> torch.Tensor:
        """A (0, S) tensor: the SH width for density-only inference, which reads no direction."""
        return x.new_zeros((0, self.config.direction_degree ** 2))

    def density_head(self, features: torch.Tensor) -> torch.Tensor:
        """h_sigma from encoded features (blocked without autograd, as in heads)."""
        if torch.is_grad_enabled() or features.shape[0] <= INFERENCE_BLOCK:
            return self.density_mlp(features)[:, 0]
        return torch.cat([self.density_mlp(features[s:s + INFERENCE_BLOCK])[:, 0]
                          for s in range(0, features.shape[0], INFERENCE_BLOCK)])

    def background_hidden(self, d: torch.Tensor, dir_features: torch.Tensor | None = None) -> torch.Tensor:
        if self.background_head is not None:
            return self.background_head(self.direction_features(d) if dir_features is None else dir_features)
        # A large pre-sigmoid logit decodes to (almost exactly) 1 or 0 for the constant backgrounds.
        value = 30.0 if self.config.background == "white" else -30.0
        return torch.full((d.shape[0], 3), value, dtype=d.dtype, device=d.device)

    # The rendering interface shared with DualField (see dualnerf.rendering).
    def query(self, x, d, blend=None, retreat: float = 1.0, dir_features=None, dir_index=None):
        _reject_blend(blend)
        return self(x, d, dir_features, dir_index)

    def query_density(self, x, blend=None, retreat: float = 1.0):
        _reject_blend(blend)
        return self.density_hidden(x)

    def query_background(self, d, blend=None, retreat: float = 1.0, dir_features=None):
        _reject_blend(blend)
        return self.background_hidden(d, dir_features)

    def occupancy_for(self, blend=None) -> OccupancyGrid:
        _reject_blend(blend)
        return self.occupancy


def _reject_blend(blend) -> None:
    if blend is not None:
        raise ValueError("blend weights were given but the model is a single RadianceField (static field or "
                         "the Instruct-NeRF2NeRF single-field baseline); pass blend=None, or build a DualField "
                         "with dualnerf.dual_field.make_edit_model(static_field, 'dual')")
