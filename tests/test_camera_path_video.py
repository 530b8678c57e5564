"""mp4 writing: a browser-playable file (H.264, yuv420p, faststart) that decodes back to the frames written
(count, size, approximate colours), byte-identical when written twice."""
from pathlib import Path

import numpy as np
import pytest

from dualnerf.video import VideoError, probe_video, rgb_to_yuv420p, write_mp4


def test_mp4_round_trip(tmp_path):
    import av

    colours = [(200, 30, 30), (30, 200, 30), (30, 30, 200), (120, 120, 120)]
    frames = [np.full((31, 45, 3), c, dtype=np.uint8) for c in colours]       # odd size on purpose
    path = write_mp4(frames, tmp_path / "path.mp4", fps=8)
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        assert float(stream.average_rate) == 8.0
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
    assert len(decoded) == len(frames)
    assert decoded[0].shape == (32, 46, 3)
    for frame, colour in zip(decoded, colours):
        # Lossy codec: the centre of a flat frame comes back within a few levels.
        np.testing.assert_allclose(frame[8:24, 8:36].reshape(-1, 3).mean(0), colour, atol=8)


def test_mp4_is_browser_playable_h264_and_repeatable(tmp_path):
    frames = [np.full((40, 64, 3), (10 * i, 80, 200 - 10 * i), dtype=np.uint8) for i in range(13)]
    first = write_mp4(frames, tmp_path / "a.mp4", fps=24)
    info = probe_video(first)
    # What Chromium and Firefox decode: H.264 in yuv420p; the index first so playback starts at once.
    assert info == {"codec": "h264", "pix_fmt": "yuv420p", "width": 64, "height": 40, "profile": "High",
                    "frames": 13, "faststart": True}
    second = write_mp4(frames, tmp_path / "b.mp4", fps=24)
    assert first.read_bytes() == second.read_bytes()


def test_mp4_rejects_bad_frames(tmp_path):
    with pytest.raises(VideoError, match="frame 1 is"):
        write_mp4([np.zeros((16, 16, 3), np.uint8), np.zeros((16, 18, 3), np.uint8)], tmp_path / "a.mp4")
    with pytest.raises(VideoError, match="uint8"):
        write_mp4([np.zeros((16, 16, 3), np.float32)], tmp_path / "b.mp4")
    with pytest.raises(VideoError, match="no frames"):
        write_mp4([], tmp_path / "c.mp4")
    # A failure part-way leaves no partial file behind.
    assert not (tmp_path / "a.mp4").exists() and not (tmp_path / "c.mp4").exists()


def test_a_pyav_without_libx264_is_a_clear_error(tmp_path, monkeypatch):
    import av

    def no_such_codec(name, mode="r"):
        raise av.codec.codec.UnknownCodecError(name)

    monkeypatch.setattr(av.codec, "Codec", no_such_codec)
    with pytest.raises(VideoError, match="no libx264 encoder"):
        write_mp4([np.zeros((16, 16, 3), np.uint8)], tmp_path / "a.mp4")
    assert not (tmp_path / "a.mp4").exists()


def test_rgb_to_yuv420p_matches_the_bt601_limited_range_formula():
    # ITU-R BT.601: Y' = 0.299 R + 0.587 G + 0.114 B; Y = 16 + 219 Y'/255, Cb = 128 + 224 (B - Y')/(1.772 * 255),
    # Cr = 128 + 224 (R - Y')/(1.402 * 255); 8-bit integer coefficients stay within one level of it.
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (8, 10, 3)).astype(np.uint8)
    planes = rgb_to_yuv420p(rgb).astype(float)
    assert planes.shape == (12, 10)
    x = rgb.astype(float)
    luma = 0.299 * x[..., 0] + 0.587 * x[..., 1] + 0.114 * x[..., 2]
    np.testing.assert_allclose(planes[:8], 16 + 219 * luma / 255, atol=1.0)
    mean = lambda c: (c[0::2, 0::2] + c[1::2, 0::2] + c[0::2, 1::2] + c[1::2, 1::2]) / 4
    cb = 128 + 224 * (mean(x[..., 2]) - mean(luma)) / (1.772 * 255)
    cr = 128 + 224 * (mean(x[..., 0]) - mean(luma)) / (1.402 * 255)
    np.testing.assert_allclose(planes[8:10].reshape(4, 5), cb, atol=1.0)
    np.testing.assert_allclose(planes[10:12].reshape(4, 5), cr, atol=1.0)
    white, black = (rgb_to_yuv420p(np.full((2, 2, 3), v, np.uint8)).ravel().tolist() for v in (255, 0))
    assert white == [235] * 4 + [128, 128] and black == [16] * 4 + [128, 128]


def first_difference(a: bytes, b: bytes) -> str:
    """Where two mp4 files first differ: the byte offset, the top-level box there and both files' sizes
    (seen once on CI, never reproduced here: the message is what the next occurrence has to tell)."""
    at = next((i for i, (x, y) in enumerate(zip(a, b)) if x != y), min(len(a), len(b)))
    box, start = b"?", 0
    while start + 8 <= len(a):
        size, kind = int.from_bytes(a[start:start + 4], "big"), a[start + 4:start + 8]
        if size < 8 or start + size > at:
            box = kind
            break
        start += size
    return (f"{len(a)} vs {len(b)} bytes, first difference at byte {at} in box {box!r} (starts at {start}): "
            f"{a[at:at + 16].hex()} vs {b[at:at + 16].hex()}")


def test_small_clips_encode_to_identical_bytes_every_time(tmp_path):
    # Four 32x24 camera-path frames of the tiny scene (an evaluate result's frames/edited/, stacked): with
    # FFmpeg's own RGB -> YUV conversion, 20 writes of them gave 2-3 different files.
    import cv2

    strip = cv2.imread(str(Path(__file__).parent / "data" / "tiny_path_frames.png"))[..., ::-1]
    frames = [np.ascontiguousarray(f) for f in np.split(strip, 4, axis=0)]
    written = [write_mp4(frames, tmp_path / f"{i}.mp4").read_bytes() for i in range(20)]
    variants = sorted(set(written))
    assert len(variants) == 1, (f"writes per file {[variants.index(w) for w in written]}; "
                                + first_difference(*variants[:2]))
    assert probe_video(tmp_path / "0.mp4")["frames"] == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f"{i}.mp4" for i in range(20))


class FlakyEncoder:
    """Stands in for one libx264 encode: writes the next of the given contents, whatever the frames."""

    def __init__(self, contents: list[bytes]):
        self.contents, self.calls = list(contents), 0

    def __call__(self, frames, path, fps):
        path.write_bytes(self.contents[self.calls])
        self.calls += 1


def test_a_video_is_kept_only_when_two_encodes_agree(tmp_path, monkeypatch, caplog):
    from dualnerf import video

    frames = [np.zeros((16, 16, 3), np.uint8)] * 2
    agreeing = FlakyEncoder([b"A", b"A"])
    monkeypatch.setattr(video, "_encode", agreeing)
    assert write_mp4(frames, tmp_path / "a.mp4").read_bytes() == b"A" and agreeing.calls == 2
    # One odd encode among them (what CI saw once in 20 writes): the bytes two encodes agree on are kept,
    # whichever came first, and the disagreement is logged.
    for contents, expected in (([b"A", b"B", b"A"], b"A"), ([b"B", b"A", b"A"], b"A"), ([b"A", b"B", b"C", b"B"], b"B")):
        flaky = FlakyEncoder(contents)
        monkeypatch.setattr(video, "_encode", flaky)
        with caplog.at_level("WARNING", logger="dualnerf.video"):
            caplog.clear()
            assert write_mp4(frames, tmp_path / "b.mp4").read_bytes() == expected
        assert flaky.calls == len(contents)
        assert f"gave {len(contents) - 1} different files" in caplog.text
    # Never two alike: an error, and neither a video nor a trial file is left behind.
    monkeypatch.setattr(video, "_encode", FlakyEncoder([b"%d" % i for i in range(video.MAX_ENCODES)]))
    with pytest.raises(VideoError, match=f"{video.MAX_ENCODES} different files"):
        write_mp4(frames, tmp_path / "c.mp4")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mp4", "b.mp4"]
