"""Input handling: robust image reading, nerfstudio / COLMAP import, SfM with pycolmap, normalisation."""
from dualnerf.io.errors import InputError
from dualnerf.io.preprocess import METHODS, PreprocessConfig, detect_method, preprocess

__all__ = ["METHODS", "InputError", "PreprocessConfig", "detect_method", "preprocess"]
