"""Procedural test scenes with 3D-consistent ground-truth edits (synthetic renders, not photographs)."""
from dualnerf.scenes.generate import SceneConfigError, generate_scene, scene_cameras, scene_config
from dualnerf.scenes.library import SCENES, SceneConfig
from dualnerf.scenes.spec import (
           EditSpec,
           SceneSpec,
           SceneSpecError,
           load_gt_edit,
           load_scene_spec,
           mode_edit_id,
)

__all__ = [
           "SCENES",
           "EditSpec",
           "SceneConfig",
           "SceneConfigError",
           "SceneSpec",
           "SceneSpecError",
           "generate_scene",
           "load_gt_edit",
           "load_scene_spec",
           "mode_edit_id",
           "scene_cameras",
           "scene_config",
]
