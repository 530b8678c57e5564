"""The preprocess key covers every file preprocess reads: edits, links inside the source, no file sources."""
from __future__ import annotations

import os
import shutil

import cv2
import pytest

from tests.test_preprocess import _transforms_case


def _preprocess_key(tmp_path, source) -> str:
    from pipeline.dag import External, Step, compute_keys
    from pipeline.store import Store
    from stages import STAGES

    step = Step("preprocess", {"method": "nerfstudio"}, {"source": External(source)})
    return compute_keys([step], registry=STAGES, store=Store(tmp_path / "cache"))[step].key


def test_preprocess_key_follows_links_inside_the_source(tiny_scene, tmp_path):
    folder = _transforms_case(tiny_scene, tmp_path, lambda doc: None)
    (folder / "images").rename(folder / "set_a")
    shutil.copytree(folder / "set_a", folder / "set_b")
    image = cv2.imread(str(folder / "set_b" / "view_004.png"))
    cv2.imwrite(str(folder / "set_b" / "view_004.png"), 255 - image)
    os.symlink("set_a", folder / "images")
    key_a = _preprocess_key(tmp_path, folder)
    (folder / "images").unlink()
    os.symlink("set_b", folder / "images")
    key_b = _preprocess_key(tmp_path, folder)
    assert key_a != key_b, "pointing the images link at other images must change the preprocess key"
    os.symlink(".", folder / "set_a" / "loop")      # a cycle is walked once, not forever
    assert _preprocess_key(tmp_path, folder) == key_b


def test_preprocess_key_changes_when_an_image_is_edited(tiny_scene, tmp_path):
    folder = _transforms_case(tiny_scene, tmp_path, lambda doc: None)
    before = _preprocess_key(tmp_path, folder)
    path = folder / "images" / "view_007.png"
    image = cv2.imread(str(path))
    image[0, 0] = 255 - image[0, 0]
    cv2.imwrite(str(path), image)
    assert _preprocess_key(tmp_path, folder) != before


def test_preprocess_stage_refuses_a_file_source(tiny_scene, tmp_path):
    from stages.preprocess import PreprocessInputError, PreprocessParams, PreprocessStage
    from tests.test_preprocess import FakeContext

    folder = _transforms_case(tiny_scene, tmp_path, lambda doc: None)
    ctx = FakeContext(PreprocessParams(), {"source": folder / "transforms.json"}, tmp_path / "ctx")
    with pytest.raises(PreprocessInputError, match=r"must be a folder.*transforms\.json"):
        PreprocessStage().run(ctx)
