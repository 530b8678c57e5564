"""Simulated annealing (SA) of the dual-field blend weights at dataset-update steps (paper Sec. 4.2).

At every dataset update the editing loop draws a retreat factor gamma ~ U[0, 1]. With probability
p(gamma) = exp((gamma - 1) / T_t) (eq. 7) it renders the view from a *retreated* model, whose blend
weights are scaled by gamma (gamma = 1: the latest model, gamma = 0: the original scene f_S); otherwise
it renders from the latest model. The temperature decays logarithmically, T_t = T_0 / lg(10 + t)
(eq. 8), so early updates retreat often and late ones rarely.

All randomness comes from the numpy Generator the caller passes in (seeded and recorded by the stage).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class AnnealingConfig:
    initial_temperature: float = 1.0     # T_0 (paper: 1)

    def __post_init__(self) -> None:
        if not self.initial_temperature > 0:
            raise ValueError(f"annealing initial_temperature (T0) must be > 0, got {self.initial_temperature}; "
                             "the paper uses T0 = 1.")


def annealing_temperature(iteration: int, initial_temperature: float = 1.0) -> float:
    """T_t = T_0 / lg(10 + t) (eq. 8). At t = 0 this is exactly T_0."""
    if iteration < 0:
        raise ValueError(f"annealing iteration must be >= 0, got {iteration}")
    return initial_temperature / math.log10(10.0 + iteration)


def acceptance_probability(retreat_factor: float, temperature: float) -> float:
    """p(gamma) = exp((gamma - 1) / T_t) (eq. 7): 1 for gamma = 1, smallest for gamma = 0."""
    return math.exp((retreat_factor - 1.0) / temperature)


def expected_acceptance_rate(temperature: float) -> float:
    """E_gamma~U[0,1][p(gamma)] = int_0^1 exp((g - 1)/T) dg = T (1 - exp(-1/T)); used to check the sampler."""
    return temperature * (1.0 - math.exp(-1.0 / temperature))


@dataclass(frozen=True)
class AnnealingDraw:
    """One SA decision, logged per dataset update."""

    iteration: int
    temperature: float           # T_t
    retreat_factor: float        # gamma ~ U[0, 1]
    acceptance_probability: float
    accepted: bool               # True: render from the retreated model (blend weights * gamma)

    @property
    def blend_scale(self) -> float:
        """The factor applied to the blend weights for this update's render."""
        return self.retreat_factor if self.accepted else 1.0

    def to_json(self) -> dict:
        return asdict(self)


def draw_retreat(rng: np.random.Generator, iteration: int, config: AnnealingConfig = AnnealingConfig()
                 ) -> AnnealingDraw:
    """Draw gamma and the accept/reject decision with two uniforms from `rng` (always two, so the stream
    position does not depend on the outcome and a resumed run stays in step)."""
    temperature = annealing_temperature(iteration, config.initial_temperature)
    retreat_factor, u = (float(v) for v in rng.random(2))
    probability = acceptance_probability(retreat_factor, temperature)
    return AnnealingDraw(iteration=iteration, temperature=temperature, retreat_factor=retreat_factor,
                         acceptance_probability=probability, accepted=bool(u < probability))
