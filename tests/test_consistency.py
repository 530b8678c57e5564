import numpy as np
import pytest

from dualnerf.consistency import ConsistencyCache, consistency_score, consistency_weights, cos01


def test_cos01_closed_form():
    assert cos01(np.array([1.0, 0.0]), np.array([1.0, 0.0])) == pytest.approx(1.0)
    assert cos01(np.array([1.0, 0.0]), np.array([-2.0, 0.0])) == pytest.approx(0.0)
    assert cos01(np.array([1.0, 0.0]), np.array([0.0, 3.0])) == pytest.approx(0.5)
    assert cos01(np.array([1.0, 1.0]), np.array([1.0, 0.0])) == pytest.approx((1 + 2 ** -0.5) / 2)


def test_score_is_product_of_both_consistencies():
    original = np.array([1.0, 0.0, 0.0])
    text = np.array([0.0, 1.0, 0.0])
    good_edit = np.array([1.0, 1.0, 0.0])           # halfway between: both consistencies high
    copy = original.copy()                           # ignores the prompt
    garbage = np.array([-1.0, -1.0, 0.0])            # neither
    s = consistency_score(np.stack([good_edit, copy, garbage]), original[None], text[None])
    c = (1 + 2 ** -0.5) / 2
    np.testing.assert_allclose(s, [c * c, 1.0 * 0.5, (1 - 2 ** -0.5) / 2 * (1 - 2 ** -0.5) / 2])
    assert s[0] > s[1] > s[2]


def test_weights_normalise_to_mean_one():
    w = consistency_weights(np.array([0.2, 0.4, 0.6]))
    np.testing.assert_allclose(w, [0.5, 1.0, 1.5])
    assert w.mean() == pytest.approx(1.0)
    np.testing.assert_allclose(consistency_weights(np.zeros(3)), 1.0)
    with pytest.raises(ValueError):
        consistency_weights(np.array([]))


def test_cache_initial_scores_and_updates_round_trip():
    rng = np.random.default_rng(0)
    originals = rng.normal(size=(4, 8))
    text = rng.normal(size=8)
    cache = ConsistencyCache.for_originals(originals, text)
    np.testing.assert_allclose(cache.scores, cos01(originals, text[None]))   # S(I|I,y) = cos01(I, y)
    cache.update(2, 0.9)
    restored = ConsistencyCache.from_state_dict(cache.state_dict())
    np.testing.assert_array_equal(restored.scores, cache.scores)
    assert restored.weights()[2] == pytest.approx(0.9 / cache.scores.mean())
