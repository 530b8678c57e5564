"""The one error type for unusable preprocess input; messages name the file and say what to do."""
from __future__ import annotations


class InputError(ValueError):
    """User input that preprocess cannot use (bad images, poses, intrinsics, failed SfM)."""

    user_error = True        # the CLI prints the message and exits 2 (see pipeline.errors)
