"""Writing rendered frames as an mp4 video that browsers play: H.264 (libx264), yuv420p, faststart.

PyAV (PyPI `av`) ships FFmpeg with libx264 inside its wheels, so no system codec is needed. Chromium,
Firefox and Safari decode H.264 High profile in yuv420p; the `moov` index goes before the media data
(faststart) so a page can start playing before the whole file arrived.

Same frames, same bytes (the pipeline compares results byte for byte): the RGB -> Y'CbCr 4:2:0 conversion
is done here in exact integer arithmetic (BT.601, limited range, tagged as such in the stream) instead of
by FFmpeg's swscale: with swscale converting, 20 writes of one 32x24 clip gave 2-3 different files in this
PyAV build. x264 then runs on one thread at a fixed CRF. Even so, x264 has twice given one different file
among 20 writes of the same clip on the CI host (22 bytes more media data; never here, in thousands of
writes, with every asm level, a dirtied heap and both cores loaded). So a clip counts as written only when
two encodes of it agree byte for byte: the first two, normally; a disagreement is logged and another
encode settles it (docs/metrics.md, on the report's videos).
"""
from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from fractions import Fraction
from pathlib import Path

import numpy as np

CODEC = "libx264"
PIXEL_FORMAT = "yuv420p"        # 4:2:0 chroma: the only H.264 layout every browser decodes
CRF = "18"                      # visually lossless for renders; the files stay small (flat colours)
SMPTE170M = 6                   # FFmpeg's AVColorSpace/Primaries/TRC code for BT.601 (525-line)
LIMITED_RANGE = 1               # AVCOL_RANGE_MPEG: Y in [16, 235], Cb/Cr in [16, 240]
MAX_ENCODES = 5                 # encodes of one clip before giving up on two that agree

log = logging.getLogger(__name__)


def rgb_to_yuv420p(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB with even H, W -> the (3H/2, W) uint8 planes Y, Cb, Cr of yuv420p: BT.601
    limited range with 8-bit integer coefficients; chroma from the mean of each 2x2 block."""
    x = rgb.astype(np.int32)
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    y = ((66 * r + 129 * g + 25 * b + 128) >> 8) + 16
    quad = [c[0::2, 0::2] + c[1::2, 0::2] + c[0::2, 1::2] + c[1::2, 1::2] for c in (r, g, b)]   # 4x sums
    cb = ((-38 * quad[0] - 74 * quad[1] + 112 * quad[2] + 512) >> 10) + 128
    cr = ((112 * quad[0] - 94 * quad[1] - 18 * quad[2] + 512) >> 10) + 128
    height, width = rgb.shape[:2]
    planes = np.concatenate([y.ravel(), cb.ravel(), cr.ravel()])
    return planes.astype(np.uint8).reshape(height * 3 // 2, width)


class VideoError(ValueError):
    """Frames that cannot be written as a video; the message names the frame and what to do."""

    user_error = True        # the CLI prints the message and exits 2 (pipeline.errors)


def write_mp4(frames: Iterable[np.ndarray], path: Path, fps: float = 24.0) -> Path:
    """Write RGB uint8 frames (all (H, W, 3), same size) to `path` as H.264 mp4; returns the path.
    Odd sizes are padded by one black row/column because 4:2:0 chroma needs even dimensions. The file
    appears only once two encodes agree byte for byte (module doc); a failure leaves no file behind."""
    path = Path(path)
    frames = _checked_frames(frames, path)
    variants: list[bytes] = []
    for attempt in range(MAX_ENCODES):
        trial = path.with_name(f".{path.name}.encode{attempt}.part")
        try:
            _encode(frames, trial, fps)
            data = trial.read_bytes()
            if data in variants:
                if len(variants) > 1:
                    log.warning("x264 gave %d different files for the %d frames of %s (sizes %s); kept the one "
                                "two encodes agree on (%d bytes).", len(variants), len(frames), path,
                                [len(v) for v in variants], len(data))
                os.replace(trial, path)
                return path
        finally:
            trial.unlink(missing_ok=True)
        variants.append(data)
    raise VideoError(f"x264 gave {MAX_ENCODES} different files for the same {len(frames)} frames of {path} "
                     f"(sizes {[len(v) for v in variants]}), so no reproducible video can be written; rerun "
                     f"the step, and report it with `python -c 'import av; print(av.__version__)'` if it "
                     f"happens again.")


def _checked_frames(frames: Iterable[np.ndarray], path: Path) -> list[np.ndarray]:
    """The frames as a list of (H, W, 3) uint8 arrays of one size, or a VideoError naming the bad one."""
    import av

    try:
        av.codec.Codec(CODEC, "w")
    except ValueError:           # av.codec.codec.UnknownCodecError is a ValueError
        raise VideoError(f"this PyAV build ({av.__version__}) has no {CODEC} encoder, so {path} cannot be "
                         f"written as browser-playable H.264; install PyAV's own wheel from PyPI "
                         f"(pip install --force-reinstall 'av>=14'), which bundles libx264.") from None
    checked = []
    for i, frame in enumerate(frames):
        frame = np.asarray(frame)
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[-1] != 3:
            raise VideoError(f"video frame {i} must be (H, W, 3) uint8 RGB, got {frame.shape} "
                             f"{frame.dtype}; convert renders with to_uint8 first.")
        if checked and frame.shape != checked[0].shape:
            raise VideoError(f"video frame {i} is {frame.shape[1]}x{frame.shape[0]} but frame 0 is "
                             f"{checked[0].shape[1]}x{checked[0].shape[0]}; render every frame at one size.")
        checked.append(frame)
    if not checked:
        raise VideoError(f"no frames to write to {path}; the camera path is empty.")
    return checked


def _encode(frames: list[np.ndarray], path: Path, fps: float) -> None:
    """One libx264 encode of checked frames into `path` (removed again if the encode fails)."""
    import av

    size = frames[0].shape[:2]
    height, width = size[0] + size[0] % 2, size[1] + size[1] % 2
    try:
        container = av.open(str(path), mode="w", format="mp4", options={"movflags": "+faststart"})
    except OSError as err:
        raise VideoError(f"could not open {path} for writing ({err}); check that the folder exists and is "
                         f"writable.") from None
    try:
        stream = container.add_stream(CODEC, rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height, stream.pix_fmt = width, height, PIXEL_FORMAT
        stream.options = {"crf": CRF, "preset": "medium", "threads": "1"}
        context = stream.codec_context
        context.color_range = LIMITED_RANGE
        context.colorspace = context.color_primaries = context.color_trc = SMPTE170M
        padded = np.zeros((height, width, 3), dtype=np.uint8)
        for frame in frames:
            padded[:size[0], :size[1]] = frame
            picture = av.VideoFrame.from_ndarray(rgb_to_yuv420p(padded), format=PIXEL_FORMAT)
            picture.color_range, picture.colorspace = LIMITED_RANGE, SMPTE170M
            container.mux(stream.encode(picture))
        container.mux(stream.encode(None))           # flush the encoder's delayed frames
    except BaseException:
        container.close()
        path.unlink(missing_ok=True)
        raise
    container.close()


def probe_video(path: Path) -> dict:
    """Codec, pixel format, size, frame count and whether the index precedes the media (faststart) of a
    video file, read with PyAV: what a browser needs to know before it plays the file."""
    import av

    path = Path(path)
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        info = {"codec": stream.codec_context.name, "pix_fmt": stream.codec_context.pix_fmt,
                "width": stream.codec_context.width, "height": stream.codec_context.height,
                "profile": stream.codec_context.profile,
                "frames": sum(1 for _ in container.decode(stream))}
    info["faststart"] = _moov_before_mdat(path)
    return info


def _moov_before_mdat(path: Path) -> bool | None:
    """Walk the top-level ISO-BMFF boxes; None when the file is not an mp4."""
    order = []
    with open(path, "rb") as handle:
        while True:
            header = handle.read(8)
            if len(header) < 8:
                break
            size, kind = int.from_bytes(header[:4], "big"), header[4:8]
            if size == 1:
                size = int.from_bytes(handle.read(8), "big") - 8
            order.append(kind)
            if size == 0:
                break
            handle.seek(size - 8, 1)
    if b"moov" not in order or b"mdat" not in order:
        return None
    return order.index(b"moov") < order.index(b"mdat")
