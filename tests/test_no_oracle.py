"""No oracle in the default: the proxy encoder's captions come from the edit's specification and the
training views, never from the ground-truth edit or the evaluated (held-out) views; CCI's flagging of the
editor's failed calls is measured from the update records."""
import numpy as np
import pytest

from dualnerf.consistency import cos01, flagging_quality


def _views(tiny_dataset):
    from dualnerf.dataset import load_dataset

    dataset = load_dataset(tiny_dataset)
    train = dataset.indices("train")
    return dataset, train, [dataset.names[i] for i in train], dataset.images[train]


@pytest.mark.parametrize("edit", ["snow", "blue_tent"])
def test_proxy_captions_come_from_the_specification_not_the_ground_truth(tiny_dataset, tmp_path, edit):
    import shutil

    from dualnerf.encoders import load_encoder
    from dualnerf.encoders.vocabulary import SPEC, proxy_vocabulary_with_source
    from dualnerf.scenes import load_gt_edit, load_scene_spec

    dataset, train, names, originals = _views(tiny_dataset)
    spec = load_scene_spec(tiny_dataset).edit(edit)
    vocabulary, source = proxy_vocabulary_with_source(tiny_dataset, edit, names, originals)
    assert source == SPEC
    # The same vocabulary without any ground truth on disk: nothing in it came from gt/edits/.
    bare = tmp_path / "bare"
    shutil.copytree(tiny_dataset, bare, ignore=shutil.ignore_patterns("gt"))
    again, _ = proxy_vocabulary_with_source(bare, edit, names, originals)
    for text in vocabulary:
        np.testing.assert_array_equal(vocabulary[text], again[text])
    # Only the views passed in define it (the stages pass the training views).
    assert len(vocabulary[spec.target_caption]) == len(train)
    # It still reads the instruction the right way: ground-truth edited views (never seen by it) are closer
    # to the target caption than to the source caption, and the originals the other way round.
    enc = load_encoder("proxy", vocabulary=vocabulary, vocabulary_source=source)
    target, source_text = enc.encode_texts([spec.target_caption, spec.source_caption])
    heldout = dataset.indices("heldout")
    gt = np.stack([load_gt_edit(tiny_dataset, edit, dataset.names[i])[0] for i in heldout])
    f_gt, f_orig = enc.encode_images(gt), enc.encode_images(dataset.images[heldout])
    assert np.all(cos01(f_gt, target) > cos01(f_gt, source_text))
    assert np.all(cos01(f_orig, source_text) > cos01(f_orig, target))
    assert enc.identity["vocabulary_source"] == SPEC


def test_geometry_edits_fall_back_to_ground_truth_training_views_and_say_so(tmp_path):
    from dualnerf.encoders.vocabulary import GROUND_TRUTH, proxy_vocabulary_with_source
    from dualnerf.scenes import generate_scene
    from stages.evaluate import sees_ground_truth

    folder = generate_scene("campsite", tmp_path / "c", n_views=3, width=48, height=36, supersample=1)
    names = sorted(p.name for p in (folder / "images").iterdir())
    import cv2

    originals = np.stack([cv2.imread(str(folder / "images" / n))[..., ::-1] for n in names])
    _, source = proxy_vocabulary_with_source(folder, "canoe", names, originals)
    assert source == GROUND_TRUTH
    values = {"gt_psnr_edit": 1.0, "clip_text_image_direction": 0.1, "ssim_edited_vs_original": 0.9}
    assert sees_ground_truth(values, {"vocabulary_source": GROUND_TRUTH}) == ["gt_psnr_edit",
                                                                               "clip_text_image_direction"]
    assert sees_ground_truth(values, {"vocabulary_source": "spec"}) == ["gt_psnr_edit"]


def _update(score, ratio, failed):
    return {"score": score, "score_ratio": ratio, "editor": {"failed": failed}}


def test_flagging_quality_closed_forms():
    perfect = [_update(0.2, 0.5, True), _update(0.9, 1.2, False), _update(0.8, 1.1, False)]
    assert flagging_quality(perfect) == {"calls": 3, "failed": 1, "flagged": 1, "flagged_failed": 1,
                                         "precision": 1.0, "recall": 1.0,
                                         "auc": 1.0}
    inverted = [_update(0.9, 1.2, True), _update(0.2, 0.5, False)]
    q = flagging_quality(inverted)
    assert q["precision"] == 0.0 and q["recall"] == 0.0 and q["auc"] == 0.0
    ties = [_update(0.5, 1.0, True), _update(0.5, 1.0, False)]
    q = flagging_quality(ties)
    assert q["flagged"] == 0 and q["precision"] is None and q["auc"] == 0.5
    # Records without a score (no encoder) or without a failure flag (a real editor) are left out.
    assert flagging_quality([{"score": None, "score_ratio": None, "editor": {"failed": True}},
                             {"score": 0.5, "score_ratio": 0.9, "editor": {"kind": "ip2p"}}])["calls"] == 0


def _palette_pixels(materials, tags):
    """One uint8 pixel per palette colour of the materials `tags`, and those colours as floats."""
    colours = np.concatenate([materials[t][0] for t in tags])
    return np.round(colours * 255).astype(np.uint8)[None, None], colours


def test_caption_images_read_each_palette_colour_as_the_specification_says():
    """Closed forms: a pixel showing a recoloured material's palette colour becomes the new palette's
    colour; under "snow" a solid material's colour mixes half-way toward the snow colour (shading 1);
    and a pixel's caption depends only on its colour (a stack equals its views captioned one by one)."""
    from dualnerf.scenes.captions import SNOW_CAPTION_COVER, caption_images, scene_materials
    from dualnerf.scenes.library import BUILDERS
    from dualnerf.scenes.materials import SNOW

    materials = scene_materials("campsite")
    edits = {e.id: e for e in BUILDERS["campsite"][1]}
    new_tent = np.asarray(edits["blue_tent"].variant.recolour["tent"], np.float32)
    pixels, own = _palette_pixels(materials, ["tent"])
    shown = pixels[0, 0] / 255.0                      # the palette colour as an 8-bit pixel shows it
    blue = caption_images("campsite", "blue_tent", pixels)[0, 0] / 255.0
    np.testing.assert_allclose(blue, np.clip(shown * new_tent / own, 0, 1), atol=1 / 255)
    np.testing.assert_allclose(blue, np.clip(new_tent, 0, 1), atol=0.05)

    # Colours whose chromaticity another material's palette nearly shares are read as either: skip them.
    every = np.concatenate([palette for palette, _ in materials.values()])
    chroma = every / every.sum(axis=1, keepdims=True)
    apart = np.sort(np.linalg.norm(chroma[:, None] - chroma[None], axis=-1), axis=1)[:, 1] > 0.03
    solid = np.concatenate([np.full(3, not emissive) for _, emissive in materials.values()])
    own = every[apart & solid]
    assert len(own) >= 5
    pixels = np.round(own * 255).astype(np.uint8)[None, None]
    shown = pixels[0, 0] / 255.0
    luminance = np.array([0.299, 0.587, 0.114])
    shading = np.clip(shown @ luminance / (own @ luminance), 0.2, 1.5)[:, None]
    snowy = caption_images("campsite", "snow", pixels)[0, 0] / 255.0
    expected = (1 - SNOW_CAPTION_COVER) * shown + SNOW_CAPTION_COVER * np.asarray(SNOW[0]) * shading
    np.testing.assert_allclose(snowy, np.clip(expected, 0, 1), atol=1 / 255)

    rng = np.random.default_rng(0)
    views = rng.integers(0, 256, (3, 16, 24, 3), dtype=np.uint8)
    views[1, :4] = views[0, :4]                       # shared colours across views
    one_by_one = np.concatenate([caption_images("campsite", "snow", v[None]) for v in views])
    np.testing.assert_array_equal(caption_images("campsite", "snow", views), one_by_one)
