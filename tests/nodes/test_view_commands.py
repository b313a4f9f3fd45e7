"""`fv view`: a bag to a video or a still, each frame with the markers of its own capture
stamp, a span of the bag, missing topics as labelled panels, and one-line errors."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from fv_algos.visualize import LOST
from nodes.cli import main
from tests.nodes.test_bag import write_bag
from tests.nodes.test_viewer import FRAME_NS, T0_NS, synthetic

N_FRAMES = 12
LAG_NS = 50_000_000  # markers, field and slip are logged 50 ms after their frame: after the next frame


def _record(folder: Path, topics: tuple[str, ...] = ("/camera/image", "/markers", "/field", "/slip")) -> Path:
    """A bag of N_FRAMES synthetic frames; in the markers of frame k, marker k is lost."""
    messages = []
    for k in range(N_FRAMES):
        for topic, msg in synthetic(k, k / N_FRAMES):
            if topic not in topics:
                continue
            if topic == "/markers":
                msg.valid[k] = False
            lag = 0 if topic == "/camera/image" else LAG_NS
            messages.append((topic, False, msg, T0_NS + k * FRAME_NS + lag))
    messages.sort(key=lambda m: m[3])
    write_bag(folder, messages)
    return folder


def _lost_near(picture: np.ndarray, x: int, y: int, r: int = 7) -> bool:
    patch = picture[y - r:y + r, x - r:x + r].astype(int)
    return bool(np.all(np.abs(patch - np.array(LOST)) < 50, axis=2).any())


def test_video_has_every_frame_and_a_still_matches_its_size(tmp_path: Path) -> None:
    bag = _record(tmp_path / "run")
    video = tmp_path / "out" / "run.mp4"
    assert main(["view", "--bag", str(bag), "--out", str(video)]) == 0
    cap = cv2.VideoCapture(str(video))
    frames = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    fps = cap.get(cv2.CAP_PROP_FPS)
    cap.release()
    assert frames == N_FRAMES and fps == pytest.approx(1e9 / FRAME_NS, rel=0.1)
    assert size[0] % 2 == 0 and size[1] % 2 == 0 and size[0] > 800 and size[1] > 500
    still = tmp_path / "still.png"
    assert main(["view", "--bag", str(bag), "--out", str(still), "--at", "0.2"]) == 0
    picture = cv2.imread(str(still))
    assert (picture.shape[1], picture.shape[0]) == size


def test_each_frame_gets_the_markers_of_its_own_stamp(tmp_path: Path) -> None:
    bag = _record(tmp_path / "run")
    still = tmp_path / "still.png"
    assert main(["view", "--bag", str(bag), "--out", str(still), "--at", str(6 * FRAME_NS / 1e9)]) == 0
    picture = cv2.imread(str(still))
    zoom, title_px = 360 / 120, 24  # 120 px tall frames drawn 360 px tall under a title bar

    def marker_xy(index: int, k: int) -> tuple[int, int]:
        return round((10 + 20 * index + 0.5 * k) * zoom), round(10 * zoom) + title_px

    assert _lost_near(picture, *marker_xy(6, 6))  # frame 6 with the markers of frame 6...
    assert not _lost_near(picture, *marker_xy(5, 5))  # ...not those of frame 5, logged after it


def test_start_and_duration_choose_the_span(tmp_path: Path) -> None:
    bag = _record(tmp_path / "run")
    video = tmp_path / "span.avi"
    assert main(["view", "--bag", str(bag), "--out", str(video), "--start", "0.1", "--duration", "0.1",
                 "--fps", "5"]) == 0
    cap = cv2.VideoCapture(str(video))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 3 and cap.get(cv2.CAP_PROP_FPS) == pytest.approx(5)
    cap.release()


def test_missing_topics_become_labelled_panels(tmp_path: Path) -> None:
    bag = _record(tmp_path / "run", ("/camera/image",))
    still = tmp_path / "still.jpg"
    assert main(["view", "--bag", str(bag), "--out", str(still)]) == 0
    assert cv2.imread(str(still)) is not None


@pytest.mark.parametrize("args, message", [
    (["--bag", "{tmp}/missing", "--out", "{tmp}/x.mp4"], "no such file"),
    (["--bag", "{slip_only}", "--out", "{tmp}/x.mp4"], "has no /camera/image topic"),
    (["--bag", "{bag}", "--out", "{tmp}/x.gif"], "use .mp4 or .avi"),
    (["--bag", "{bag}", "--out", "{tmp}/x.png", "--at", "99"], "99 s is outside the bag"),
    (["--bag", "{bag}", "--out", "{tmp}/x.png", "--start", "1"], "a still takes --at"),
    (["--bag", "{bag}", "--out", "{tmp}/x.png", "--fps", "10"], "a still takes --at"),  # it was ignored
    (["--bag", "{bag}", "--out", "{tmp}/x.mp4", "--at", "1"], "a video takes --start"),
    (["--bag", "{bag}", "--out", "{tmp}/x.mp4", "--start", "30"], "outside the bag"),
])
def test_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture, args: list[str], message: str) -> None:
    bag = _record(tmp_path / "run")
    slip_only = _record(tmp_path / "slip_only", ("/slip",))
    args = [a.format(tmp=tmp_path, bag=bag, slip_only=slip_only) for a in args]
    assert main(["view", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("fv view: error:") and message in err and "\n" not in err, err


def test_a_bag_of_other_image_topics_names_the_option_that_draws_one(tmp_path: Path, capsys) -> None:
    """A pair's bag (/left/camera/image ...) was told to record /camera/image, which it holds under another name."""
    messages = [("/left" + topic, False, msg, T0_NS + k * FRAME_NS) for k in range(N_FRAMES)
                for topic, msg in synthetic(k, k / N_FRAMES)]
    write_bag(tmp_path / "pair", sorted(messages, key=lambda m: m[3]))
    assert main(["view", "--bag", str(tmp_path / "pair"), "--out", str(tmp_path / "x.png")]) == 2
    assert "draw one of its images with --image-topic /left/camera/image" in capsys.readouterr().err
