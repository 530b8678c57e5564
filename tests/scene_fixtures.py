"""Shared pytest fixtures: procedural scenes and normalised datasets built from them (session-scoped).

    tiny_scene    Path to a generated `tiny` scene folder (images/, scene.toml, gt/ with edits)
    tiny_dataset  Path to a normalised dataset built from tiny_scene's ground-truth cameras
                  (the nerfstudio-import path, no SfM); it also carries scene.toml and gt/edits/.
Both are read-only for tests: copy before modifying.
"""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    from dualnerf.scenes import generate_scene

    return generate_scene("tiny", tmp_path_factory.mktemp("scenes") / "tiny", seed=0)


@pytest.fixture(scope="session")
def tiny_dataset(tiny_scene, tmp_path_factory):
    from dualnerf.io import PreprocessConfig, preprocess

    out = tmp_path_factory.mktemp("datasets") / "tiny"
    preprocess(tiny_scene, out, PreprocessConfig(method="nerfstudio"))
    return out
