"""mp4 writing: the file decodes back to the frames written (count, size, approximate colours)."""
import numpy as np
import pytest

from dualnerf.video import VideoError, write_mp4


def test_mp4_round_trip(tmp_path):
    import cv2

    colours = [(200, 30, 30), (30, 200, 30), (30, 30, 200), (120, 120, 120)]
    frames = [np.full((31, 45, 3), c, dtype=np.uint8) for c in colours]       # odd size on purpose
    path = write_mp4(frames, tmp_path / "path.mp4", fps=8)
    capture = cv2.VideoCapture(str(path))
    decoded = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        decoded.append(frame[..., ::-1])
    capture.release()
    assert len(decoded) == len(frames)
    assert decoded[0].shape == (32, 46, 3)
    for frame, colour in zip(decoded, colours):
        # Lossy codec: the centre of a flat frame comes back within a few levels.
        np.testing.assert_allclose(frame[8:24, 8:36].reshape(-1, 3).mean(0), colour, atol=8)


def test_mp4_rejects_bad_frames(tmp_path):
    with pytest.raises(VideoError, match="frame 1 is"):
        write_mp4([np.zeros((16, 16, 3), np.uint8), np.zeros((16, 18, 3), np.uint8)], tmp_path / "a.mp4")
    with pytest.raises(VideoError, match="uint8"):
        write_mp4([np.zeros((16, 16, 3), np.float32)], tmp_path / "b.mp4")
    with pytest.raises(VideoError, match="no frames"):
        write_mp4([], tmp_path / "c.mp4")
