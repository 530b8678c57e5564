"""The dual-field representation (paper Sec. 4.1): a frozen static field f_S and a trainable dynamic field
f_D fused in hidden-feature space.

API:
    BlendSchedule(w_max_density=0.1, w_max_color=0.1, rate=0.005)   frozen dataclass
        weights(step: int) -> (w_density, w_color)                    eq. 6: w = w_max * tanh(rate * t)
    DualField(static_field: RadianceField, dynamic_field: RadianceField) nn.Module
        query(x, d, blend=(w_density, w_color) | None, retreat=1.0) -> (h_sigma (M,), h_color (M,3))
        query_density(x, blend, retreat) -> h_sigma;  query_background(d, blend, retreat) -> (R,3)
        occupancy_for(blend) -> OccupancyGrid   (static field's grid when blend is None)
        render_blend: tuple | None              blend to render the saved edit with (set by the edit stage)
        render_session() -> context manager     a whole-image render: both fields' tables interleaved once
    make_edit_model(static_field, mode: "dual" | "single") -> DualField | RadianceField

Fusion (eqs. 4-5), separately for density and colour features:
    h = (1 - w) * h^(S) + w * h^(D),   w = gamma * w_schedule
`retreat` is the simulated-annealing scale gamma in [0, 1] (Sec. 4.2): gamma = 1 keeps the current edit,
gamma = 0 retreats to the original scene. blend=None renders f_S alone. With w = 0 the output equals f_S
bit for bit (1.0 * h_S + 0.0 * h_D is exact for finite h_D).

f_S is frozen: its parameters have requires_grad False, are never handed to an optimiser, and it runs
under torch.no_grad, so a fused step costs one forward of f_S on top of a single-field step.

Initialising f_D (design choice; the paper only says "same architecture"): f_D starts as an exact copy
of f_S. Then the fused field equals the original scene for every w (no jump as w grows from 0 by eq. 6),
f_D has to learn only the *change* an edit asks for, and a small w (0.1) can still express any edit that
f_D can represent, because h = h_S + w * (h_D - h_S) reaches h_S + delta once f_D moves by delta / w. A
randomly initialised f_D would instead inject w * (noise) into every feature and have to relearn the
scene's geometry. Since Adam moves parameters by ~lr per step regardless of gradient scale, the fused
features move ~w times slower than f_D's own: that is the anchor of Sec. 4.1 at the paper's (IN2N's)
learning rate. The edit stage's `dual_lr_scale` variant scales f_D's learning rate by 1 / w_max and so
removes it (off by default).

Single-field mode (Instruct-NeRF2NeRF baseline): `make_edit_model(f_S, "single")` returns a trainable
copy of f_S; it is trained and rendered by the same RayTrainer / render_view with blend=None.
"""
from __future__ import annotations

import contextlib
import copy
import math
from dataclasses import dataclass

import torch
from torch import nn

from dualnerf import kernels
from dualnerf.fields import RadianceField
from dualnerf.occupancy import OccupancyGrid

EDIT_MODES = ("dual", "single")


class BlendError(ValueError):
    """Blend weights or a retreat scale outside [0, 1]."""


@dataclass(frozen=True)
class BlendSchedule:
    w_max_density: float = 0.1
    w_max_color: float = 0.1
    rate: float = 0.005

    def __post_init__(self):
        for name in ("w_max_density", "w_max_color"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise BlendError(f"BlendSchedule.{name} must be in [0, 1], got {getattr(self, name)}")
        if self.rate < 0:
            raise BlendError(f"BlendSchedule.rate must be >= 0, got {self.rate}")

    def weights(self, step: int) -> tuple[float, float]:
        """Blend weights at editing iteration `step` (eq. 6): w_* = w_*^max tanh(lambda t)."""
        growth = math.tanh(self.rate * step)
        return self.w_max_density * growth, self.w_max_color * growth


def _effective_blend(blend, retreat: float) -> tuple[float, float]:
    if not 0.0 <= retreat <= 1.0:
        raise BlendError(f"retreat scale gamma must be in [0, 1], got {retreat}")
    w_density, w_color = (float(w) for w in blend)
    if not (0.0 <= w_density <= 1.0 and 0.0 <= w_color <= 1.0):
        raise BlendError(f"blend weights must be in [0, 1], got {blend}")
    return retreat * w_density, retreat * w_color


def _fuse(h_static: torch.Tensor, h_dynamic: torch.Tensor, w: float) -> torch.Tensor:
    """Eqs. 4-5: h = (1 - w) h^(S) + w h^(D)."""
    return (1.0 - w) * h_static + w * h_dynamic


class DualField(nn.Module):
    def __init__(self, static_field: RadianceField, dynamic_field: RadianceField):
        super().__init__()
        if static_field.config != dynamic_field.config:
            raise ValueError("DualField: static and dynamic fields must share one FieldConfig (same architecture)")
        self.config = static_field.config
        self.static_field = static_field
        self.dynamic_field = dynamic_field
        self.static_field.requires_grad_(False)
        # The fused field can only hold density where either field does: start from the union of both
        # grids (equal to f_S's when f_D is its copy); the trainer then updates it during editing.
        self.occupancy = copy.deepcopy(static_field.occupancy)
        with torch.no_grad():
            self.occupancy.mask |= dynamic_field.occupancy.mask.to(self.occupancy.mask.device)
            self.occupancy.density.copy_(torch.maximum(self.occupancy.density,
                                                       dynamic_field.occupancy.density.to(self.occupancy.density.device)))
        self.render_blend: tuple[float, float] | None = None
        self._interleaved: list[torch.Tensor] | None = None
        self._kept_interleaved: list[torch.Tensor] | None = None      # see _interleave_tables
        self._kept_stamp: list | None = None

    @contextlib.contextmanager
    def render_session(self):
        """For a whole-image render, during which no parameter changes: f_S's and f_D's tables interleaved
        once (kernels.interleave_pair), so every chunk's look-ups read both fields' corner from one cache
        line. Renders give the same bits with and without it."""
        if self._interleaved is not None:           # nested: the outer session's tables are current
            yield
            return
        self._interleaved = self._interleave_tables()
        try:
            yield
        finally:
            self._interleaved = None

    def _interleave_tables(self) -> list[torch.Tensor] | None:
        """The interleaved tables for a render session. They are kept between sessions: f_D's half is
        rewritten each time, f_S's only when one of its tables was replaced or changed in place (torch
        counts in-place writes in a tensor's _version), so an IDU view update copies one field, not two,
        into memory that is already mapped (the fresh 104 MB copy was ~4% of a dual view update)."""
        static, dynamic = self.static_field.grid_tables(), self.dynamic_field.grid_tables()
        stamp = [(id(t), t._version) for t in (*static[0], *static[1])]
        if self._kept_interleaved is None:
            self._kept_interleaved = kernels.interleave_pair(static, dynamic)
        else:
            kernels.interleave_pair(static, dynamic, into=self._kept_interleaved,
                                    write_first=stamp != self._kept_stamp)
        self._kept_stamp = stamp
        return self._kept_interleaved

    def query(self, x, d, blend=None, retreat: float = 1.0, dir_features=None, dir_index=None):
        """dir_features / dir_index as in RadianceField.forward (per-ray SH features and each sample's ray)."""
        if dir_features is None:          # one SH evaluation for both fields (equal configs)
            dir_features = self.static_field.direction_features(d)
        if blend is None:
            with torch.no_grad():
                return self.static_field(x, d, dir_features, dir_index)
        w_density, w_color = _effective_blend(blend, retreat)
        if self.static_field.can_infer(x) and self.dynamic_field.can_infer(x):   # renders: both fields and
            # eqs. 4-5 in one kernel pass (a training step, where f_D needs autograd, takes the torch path)
            return kernels.field_inference(x, dir_features, self.static_field.grid_tables(),
                                           self.static_field.mlp_layers(),
                                           second=(self.dynamic_field.grid_tables(), self.dynamic_field.mlp_layers()),
                                           blend=(w_density, w_color), interleaved=self._interleaved,
                                           sh_index=dir_index)
        if dir_index is not None:
            dir_features = dir_features[dir_index]
        features_s, features_d = self._both_features(x)
        with torch.no_grad():
            h_sigma_s, h_color_s = self.static_field.heads(features_s, dir_features)
        h_sigma_d, h_color_d = self.dynamic_field.heads(features_d, dir_features)
        return _fuse(h_sigma_s, h_sigma_d, w_density), _fuse(h_color_s, h_color_d, w_color)

    def _both_features(self, x):
        """(f_S's encoded features of x without gradient, f_D's). Where the fused kernel applies, one pass
        computes both (the look-up maths shared, see dualnerf.kernels); each equals that field's own
        features(x) bit for bit."""
        if self.static_field.can_fuse(x) and kernels.can_fuse_pair(x, self.config.grid_features):
            return kernels.fused_pair_features(x, *self.static_field.grid_tables(),
                                               *self.dynamic_field.grid_tables())
        with torch.no_grad():
            features_s = self.static_field.features(x)
        return features_s, self.dynamic_field.features(x)

    def query_density(self, x, blend=None, retreat: float = 1.0):
        if blend is None:
            with torch.no_grad():
                return self.static_field.density_hidden(x)
        w_density, w_color = _effective_blend(blend, retreat)
        if self.static_field.can_infer(x) and self.dynamic_field.can_infer(x):    # the occupancy refresh
            return kernels.field_inference(x, self.static_field.empty_direction_features(x),
                                           self.static_field.grid_tables(), self.static_field.mlp_layers(),
                                           second=(self.dynamic_field.grid_tables(), self.dynamic_field.mlp_layers()),
                                           blend=(w_density, w_color), density_only=True)[0]
        features_s, features_d = self._both_features(x)
        with torch.no_grad():
            h_sigma_s = self.static_field.density_head(features_s)
        return _fuse(h_sigma_s, self.dynamic_field.density_head(features_d), w_density)

    def query_background(self, d, blend=None, retreat: float = 1.0, dir_features=None):
        if dir_features is None:
            dir_features = self.static_field.direction_features(d)
        with torch.no_grad():
            h_bg_s = self.static_field.background_hidden(d, dir_features)
        if blend is None:
            return h_bg_s
        _, w_color = _effective_blend(blend, retreat)
        return _fuse(h_bg_s, self.dynamic_field.background_hidden(d, dir_features), w_color)

    def occupancy_for(self, blend=None) -> OccupancyGrid:
        return self.static_field.occupancy if blend is None else self.occupancy


def make_edit_model(static_field: RadianceField, mode: str = "dual") -> DualField | RadianceField:
    """The model the editing stage trains, built from a fitted static field (which is not modified)."""
    if mode not in EDIT_MODES:
        raise ValueError(f"edit mode must be one of {EDIT_MODES}, got {mode!r}")
    if mode == "single":
        field = copy.deepcopy(static_field)
        field.requires_grad_(True)
        return field
    static = copy.deepcopy(static_field)
    dynamic = copy.deepcopy(static_field)
    dynamic.requires_grad_(True)
    return DualField(static, dynamic)
