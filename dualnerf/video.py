"""Writing rendered frames as an mp4 video (OpenCV VideoWriter, MPEG-4 Part 2 "mp4v": no extra codecs)."""
from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np


class VideoError(ValueError):
    """Frames that cannot be written as a video; the message names the frame and what to do."""

    user_error = True        # the CLI prints the message and exits 2 (pipeline.errors)


def write_mp4(frames: Iterable[np.ndarray], path: Path, fps: float = 24.0) -> Path:
    """Write RGB uint8 frames (all (H, W, 3), same size) to `path` as mp4; returns the path.
    Odd sizes are padded by one black row/column because the codec works on even dimensions."""
    import cv2

    path = Path(path)
    writer = None
    size = None
    count = 0
    try:
        for i, frame in enumerate(frames):
            frame = np.asarray(frame)
            if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[-1] != 3:
                raise VideoError(f"video frame {i} must be (H, W, 3) uint8 RGB, got {frame.shape} "
                                 f"{frame.dtype}; convert renders with to_uint8 first.")
            if size is None:
                size = frame.shape[:2]
                height, width = size[0] + size[0] % 2, size[1] + size[1] % 2
                writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps),
                                         (width, height))
                if not writer.isOpened():
                    raise VideoError(f"OpenCV could not open {path} for writing with the mp4v codec; "
                                     f"check that the folder exists and is writable.")
            elif frame.shape[:2] != size:
                raise VideoError(f"video frame {i} is {frame.shape[1]}x{frame.shape[0]} but frame 0 is "
                                 f"{size[1]}x{size[0]}; render every frame at one size.")
            padded = np.zeros((height, width, 3), dtype=np.uint8)
            padded[:size[0], :size[1]] = frame[..., ::-1]          # OpenCV wants BGR
            writer.write(padded)
            count += 1
    finally:
        if writer is not None:
            writer.release()
    if count == 0:
        raise VideoError(f"no frames to write to {path}; the camera path is empty.")
    return path
