"""The trainer's optimiser: Adam, with instant-NGP's rule for feature tables.

API:
    FieldAdam(model, lr, betas=(0.9, 0.99), eps=1e-15, table_gradients=None)   torch.optim.Optimizer over
        model's trainable parameters in two groups: feature tables (skip_zero=True) and the MLPs; tables in
        `table_gradients` (dualnerf.kernels.TableGradients) take their gradients from there
    adam_reference(param, grad, exp_avg, exp_avg_sq, beta1, beta2, step_size, bias_correction2_sqrt, eps,
                   skip_zero)   the update in plain torch, in place (the kernel's operations, in its order)
    feature_table_parameters(model) -> list[Parameter]   the dense grids', planes' and hash tables' values

Update (Kingma & Ba), per entry, with bias corrections bc1 = 1 - b1^t, bc2 = 1 - b2^t of the
optimiser step t:
    m = b1 m + (1 - b1) g;   v = b2 v + (1 - b2) g^2;   p = p - lr / bc1 * m / (sqrt(v) / sqrt(bc2) + eps)
Feature tables skip every entry whose gradient is exactly zero: its value and moments stay as they are
(instant-NGP, Mueller et al. 2022, Sec. 4: "we skip Adam steps for hash table entries whose gradient is
exactly 0"). A ray batch touches a small part of the 13M table entries, and the dense update of all of
them (read and write value, gradient and two moments every step) was a fifth of a training step on
2 cores (benchmarks.profile_edit). The MLP weights, which every sample touches, take the plain update.

The update runs in the fused C++ kernel (dualnerf.kernels) where it is built, else in adam_reference.
The kernel's operations are each correctly rounded (compiled without fused multiply-adds), so it gives
the same bits on every CPU and on its AVX-512 and portable paths (tests/test_optim.py checks it against
numpy float32); torch's element-wise sqrt in the reference may round an ulp differently, by CPU. With table_gradients, the
look-up kernels' backward collects the tables' gradients in persistent buffers with touched-chunk flags
and the update visits the touched chunks only (the same bits again: an untouched chunk has no non-zero
gradient to apply). The learning rate is set
per step by the trainer (param_groups[i]["lr"]), as with torch.optim.Adam.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from dualnerf import kernels
from dualnerf.encoding import DenseGridEncoding, HashGridEncoding, PlaneGridEncoding


def feature_table_parameters(model: nn.Module) -> list[nn.Parameter]:
    tables = (DenseGridEncoding, HashGridEncoding, PlaneGridEncoding)
    return [p for m in model.modules() if isinstance(m, tables) for p in m.parameters()]


def adam_reference(param, grad, exp_avg, exp_avg_sq, beta1: float, beta2: float, step_size: float,
                   bias_correction2_sqrt: float, eps: float, skip_zero: bool) -> None:
    """One Adam step in place, in the kernel's order of float32 operations (torch's sqrt may differ from
    the correctly rounded one by an ulp on some CPUs)."""
    m = beta1 * exp_avg + (1 - beta1) * grad
    v = beta2 * exp_avg_sq + (1 - beta2) * grad * grad
    p = param - step_size * (m / (torch.sqrt(v) / bias_correction2_sqrt + eps))
    if skip_zero:
        keep = grad == 0
        m = torch.where(keep, exp_avg, m)
        v = torch.where(keep, exp_avg_sq, v)
        p = torch.where(keep, param, p)
    exp_avg.copy_(m)
    exp_avg_sq.copy_(v)
    param.copy_(p)


class FieldAdam(torch.optim.Optimizer):
    def __init__(self, model: nn.Module, lr: float, betas: tuple[float, float] = (0.9, 0.99), eps: float = 1e-15,
                 table_gradients: kernels.TableGradients | None = None):
        trainable = [p for p in model.parameters() if p.requires_grad]
        table_ids = {id(p) for p in feature_table_parameters(model)}
        groups = [{"params": [p for p in trainable if id(p) in table_ids], "skip_zero": True},
                  {"params": [p for p in trainable if id(p) not in table_ids], "skip_zero": False}]
        super().__init__([g for g in groups if g["params"]], {"lr": lr, "betas": tuple(betas), "eps": eps})
        # Tables whose gradients the look-up kernels collect outside autograd (dualnerf.kernels.TableGradients).
        self.table_gradients = table_gradients

    def zero_grad(self, set_to_none: bool = True) -> None:
        super().zero_grad(set_to_none)
        if self.table_gradients is not None:
            self.table_gradients.clear()

    @torch.no_grad()
    def step(self, closure=None):
        if closure is not None:
            raise ValueError("FieldAdam.step takes no closure")
        module = kernels.grid_kernel()
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for param in group["params"]:
                collected = None if self.table_gradients is None else self.table_gradients.gradient(param)
                if param.grad is None and collected is None:
                    continue
                if param.grad is not None and collected is not None:
                    raise RuntimeError("FieldAdam: a feature table got a gradient through autograd although its "
                                       "gradients are collected in TableGradients; run its forward passes inside "
                                       "table_gradients.collect()")
                state = self.state[param]
                if not state:
                    state["step"] = 0
                    state["exp_avg"] = torch.zeros_like(param, memory_format=torch.preserve_format)
                    state["exp_avg_sq"] = torch.zeros_like(param, memory_format=torch.preserve_format)
                state["step"] += 1
                t = state["step"]
                args = (beta1, beta2, group["lr"] / (1 - beta1 ** t), math.sqrt(1 - beta2 ** t), group["eps"],
                        group["skip_zero"])
                if collected is not None:          # touched chunks only; they are zeroed for the next step
                    module.adam_step_touched(param, *collected, state["exp_avg"], state["exp_avg_sq"], *args[:-1])
                    continue
                grad = param.grad
                if grad.stride() != param.stride():
                    grad = torch.empty_like(param).copy_(grad)
                if module is not None and param.device.type == "cpu" and param.dtype == torch.float32:
                    module.adam_step(param, grad, state["exp_avg"], state["exp_avg_sq"], *args)
                else:
                    adam_reference(param, grad, state["exp_avg"], state["exp_avg_sq"], *args)
