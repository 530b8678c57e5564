import itertools
import math

import numpy as np
import pytest

from dualnerf.annealing import (
    AnnealingConfig,
    acceptance_probability,
    annealing_temperature,
    draw_retreat,
    expected_acceptance_rate,
)


def test_temperature_matches_eq8():
    assert annealing_temperature(0, 1.0) == pytest.approx(1.0)          # lg(10) = 1
    assert annealing_temperature(90, 1.0) == pytest.approx(0.5)         # lg(100) = 2
    assert annealing_temperature(990, 2.0) == pytest.approx(2.0 / 3.0)  # lg(1000) = 3
    temps = [annealing_temperature(t) for t in range(0, 15000, 500)]
    assert all(a > b for a, b in itertools.pairwise(temps))


def test_acceptance_probability_matches_eq7():
    assert acceptance_probability(1.0, 0.3) == pytest.approx(1.0)
    assert acceptance_probability(0.0, 1.0) == pytest.approx(math.exp(-1.0))
    assert acceptance_probability(0.5, 0.25) == pytest.approx(math.exp(-2.0))


def test_expected_rate_closed_form_matches_quadrature():
    for temperature in (0.2, 0.5, 1.0, 3.0):
        gammas = np.linspace(0.0, 1.0, 200001)
        numeric = np.trapezoid(np.exp((gammas - 1.0) / temperature), gammas)
        assert expected_acceptance_rate(temperature) == pytest.approx(numeric, rel=1e-6)


@pytest.mark.parametrize("iteration", [0, 90, 14990])
def test_empirical_acceptance_rate_matches_closed_form(iteration):
    rng = np.random.default_rng(123)
    draws = [draw_retreat(rng, iteration) for _ in range(20000)]
    rate = np.mean([d.accepted for d in draws])
    expected = expected_acceptance_rate(annealing_temperature(iteration))
    # binomial standard error for 20000 draws is < 0.0036; 4 sigma
    assert abs(rate - expected) < 0.015
    gammas = np.array([d.retreat_factor for d in draws])
    assert gammas.min() >= 0.0 and gammas.max() < 1.0 and abs(gammas.mean() - 0.5) < 0.01
    # accepted draws are biased toward gamma near 1: E[gamma | accepted] > 1/2
    accepted_gammas = gammas[[d.accepted for d in draws]]
    assert accepted_gammas.mean() > 0.5


def test_blend_scale_and_determinism():
    a = [draw_retreat(np.random.default_rng(5), 10) for _ in range(3)]
    assert a[0] == a[1] == a[2]
    rng = np.random.default_rng(0)
    for _ in range(200):
        d = draw_retreat(rng, 3)
        assert d.blend_scale == (d.retreat_factor if d.accepted else 1.0)
        assert d.acceptance_probability == pytest.approx(acceptance_probability(d.retreat_factor, d.temperature))


def test_bad_temperature_is_a_clear_error():
    with pytest.raises(ValueError, match="T0"):
        AnnealingConfig(initial_temperature=0.0)
