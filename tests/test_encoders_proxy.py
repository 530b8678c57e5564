import numpy as np
import pytest

from dualnerf.consistency import cos01
from dualnerf.encoders import EncoderError, ImageTextEncoder, load_encoder


def _scene(rng, tint=(0.0, 0.0, 0.0), n=4, size=48):
    """Smooth random 'views': a gradient background with a coloured square at a per-view position."""
    images = []
    for i in range(n):
        yy, xx = np.mgrid[0:size, 0:size] / size
        base = np.stack([0.3 + 0.2 * xx, 0.5 + 0.1 * yy, 0.3 * np.ones_like(xx)], -1)
        x0 = 8 + 4 * i
        base[16:32, x0:x0 + 16] = [0.7, 0.2, 0.2]
        images.append(np.clip(base + np.array(tint) + rng.normal(0, 0.01, base.shape), 0, 1))
    return (np.stack(images) * 255).astype(np.uint8)


def test_features_normalised_and_input_types_agree():
    rng = np.random.default_rng(0)
    images = _scene(rng)
    enc = load_encoder("proxy", vocabulary={})
    assert isinstance(enc, ImageTextEncoder)
    f_uint8 = enc.encode_images(images)
    f_float = enc.encode_images(images.astype(np.float32) / 255)
    np.testing.assert_allclose(f_uint8, f_float, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(f_uint8, axis=1), 1.0, atol=1e-5)
    assert enc.identity["kind"] == "proxy" and "NOT CLIP" in enc.identity["model"]


def test_text_embeddings_come_from_defining_views_and_rank_edits():
    rng = np.random.default_rng(1)
    originals = _scene(rng)
    snowy = _scene(rng, tint=(0.35, 0.35, 0.45))       # the 'edited' look
    enc = load_encoder("proxy", vocabulary={"make it snowy": snowy, "a campsite": originals})
    text = enc.encode_texts(["make it snowy", "a campsite"])
    # held-out views of each look are closer to their own caption than to the other one
    new_orig, new_snow = _scene(rng, n=2), _scene(rng, tint=(0.35, 0.35, 0.45), n=2)
    s_orig = cos01(enc.encode_images(new_orig)[:, None], text[None])
    s_snow = cos01(enc.encode_images(new_snow)[:, None], text[None])
    assert np.all(s_orig[:, 1] > s_orig[:, 0]) and np.all(s_snow[:, 0] > s_snow[:, 1])
    # a wrong-colour edit is further from both the original and the snow text than a good edit
    wrong = _scene(rng, tint=(-0.3, 0.4, -0.3), n=1)
    good = _scene(rng, tint=(0.35, 0.35, 0.45), n=1)
    f_wrong, f_good = enc.encode_images(wrong)[0], enc.encode_images(good)[0]
    assert cos01(f_good, text[0]) > cos01(f_wrong, text[0])


def test_blur_and_noise_move_texture_features():
    rng = np.random.default_rng(2)
    image = _scene(rng, n=1)
    import cv2

    blurred = cv2.GaussianBlur(image[0], (0, 0), 3)[None]
    enc = load_encoder("proxy", vocabulary={})
    f, fb = enc.encode_images(image)[0], enc.encode_images(blurred)[0]
    assert 0.5 < cos01(f, fb) < 0.999


def test_unknown_text_and_bad_input_are_clear_errors():
    enc = load_encoder("proxy", vocabulary={"a campsite": np.zeros((1, 8, 8, 3), np.uint8)})
    with pytest.raises(EncoderError, match="proxy.*'make it pink'.*known: 'a campsite'"):
        enc.encode_texts(["make it pink"])
    with pytest.raises(EncoderError, match="non-empty"):
        load_encoder("proxy", vocabulary={"x": np.zeros((0, 8, 8, 3), np.uint8)})
    with pytest.raises(EncoderError, match="unknown encoder kind"):
        load_encoder("lpips")
    with pytest.raises(EncoderError, match="RGB"):
        enc.encode_images(np.zeros((2, 8, 8), np.uint8))
