"""The smoke check refuses report videos that browsers do not play (e.g. OpenCV mp4v) and accepts H.264."""
import numpy as np

from dualnerf.video import write_mp4
from experiments.check_smoke import _video_problems


def test_smoke_check_names_videos_browsers_cannot_play(tmp_path):
    import cv2

    videos = tmp_path / "videos"
    videos.mkdir()
    write_mp4([np.full((16, 16, 3), 100, np.uint8)] * 3, videos / "good.mp4", fps=4)
    writer = cv2.VideoWriter(str(videos / "old.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 4.0, (16, 16))
    for _ in range(3):
        writer.write(np.full((16, 16, 3), 100, np.uint8))
    writer.release()
    found = _video_problems(tmp_path)
    assert len(found) == 1 and "old.mp4 is mpeg4/yuv420p with 3 frames" in found[0]
