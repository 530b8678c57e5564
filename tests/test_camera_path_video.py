"""mp4 writing: a browser-playable file (H.264, yuv420p, faststart) that decodes back to the frames written
(count, size, approximate colours), byte-identical when written twice."""
import numpy as np
import pytest

from dualnerf.video import VideoError, probe_video, write_mp4


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
