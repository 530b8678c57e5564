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
