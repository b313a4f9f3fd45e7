"""Shared pytest fixtures: paths to the recordings in ../shared/data (never copied here)."""
from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def real_data() -> Path:
    """Folder of real sensor recordings (`../shared/data/real`); skips when absent."""
    path = SHARED_DATA / "real"
    if not path.is_dir():
        pytest.skip(f"real recordings not found at {path} (../shared/data/real is absent)")
    return path


@pytest.fixture(scope="session")
def isd_data() -> Path:
    """Folder of the labelled incipient-slip dataset (`../shared/data/isd`); skips when absent."""
    path = SHARED_DATA / "isd"
    if not path.is_dir():
        pytest.skip(f"incipient-slip dataset not found at {path} (../shared/data/isd is absent)")
    return path


def dots_image(shift_px: float) -> "np.ndarray":
    """(240, 320) uint8: a 12x9 grid of dark dots (pitch 24 px) moved `shift_px` in x."""
    import cv2
    import numpy as np
    image = np.full((240, 320), 200, np.uint8)
    for y in range(24, 240 - 12, 24):
        for x in range(28, 320 - 20, 24):
            cv2.circle(image, (int(round(x + shift_px)), y), 5, 40, -1, cv2.LINE_AA)
    return image


def write_raw_mini(video: Path, out: Path) -> None:
    """A GelSight Mini's frames before its software cuts 1/7 off each border: every frame of the
    recorded ``video`` (320x240) inside a 448x336 frame with a dark housing and a bright rim, written
    lossless (FFV1) to ``out``, so that the inside is the recording's decoded pixels. A crop of
    0.142857 on every border keeps exactly the recording."""
    import cv2
    import numpy as np
    cap = cv2.VideoCapture(str(video))
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"FFV1"), 25.0, (448, 336))
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        big = np.full((336, 448, 3), 25, np.uint8)
        cv2.rectangle(big, (40, 30), (407, 305), (200, 210, 220), 12)  # the rim of the gel's frame
        big[48:288, 64:384] = frame
        writer.write(big)
    writer.release()
    cap.release()
