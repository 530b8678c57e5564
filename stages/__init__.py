"""DualNeRF pipeline stages. Each stage is looked up lazily by name so `dualnerf --help` stays instant."""

# name -> "module:Class"; the engine imports a stage only when it runs or keys it.
STAGES = {
    "scene": "stages.scene:SceneStage",
    "preprocess": "stages.preprocess:PreprocessStage",
    "fit": "stages.fit:FitStage",
    "edit": "stages.edit:EditStage",
    "evaluate": "stages.evaluate:EvaluateStage",
    "perframe": "stages.perframe:PerFrameStage",
    "gtviews": "stages.gtviews:GroundTruthViewsStage",
}
