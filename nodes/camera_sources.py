"""Frame sources for the camera node: a video file, a folder of images, a V4L2 device,
and the simulated sensor. Each is a small class with `open()`, `read()` and `close()`;
`read()` returns the frame and its capture stamp, or None when no frame came, or raises
`SourceError` naming the source and why; either way the node reports the source lost and
reopens it with backoff. `SourceConfigError` is for what no reopening mends: the node stops.

"Unplugged" means the same for every source: a V4L2 device whose read fails (or times
out after `V4L2_READ_TIMEOUT_S`), a video file or an image that is removed (checked on
each read, so a deleted file that the open handle could still read counts as gone), a
folder that is removed or emptied. Plugged back, the next reopen succeeds.

At the camera node's start, a V4L2 camera that is not there yet (no device of its name, one that
cannot be opened: missing, busy or not yet given its permissions, or one that gives no first frame)
raises `SourceMissing`: the node exits TEMPFAIL and a launch starts it again until the camera is
plugged in. Any other `SourceError` there (a video OpenCV cannot decode, a name that matches two
cameras) is a configuration error: the node exits CONFIG (`nodes.exit_codes`)."""
from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from fv_algos.calibration import image_files
from nodes.exit_codes import NotReadyError

log = logging.getLogger("fv.camera")
V4L2_READ_TIMEOUT_S = 1  # a V4L2 read that waits longer fails (a stalled or unplugged camera); OpenCV's default: 10


class SourceError(RuntimeError):
    """A source that cannot be opened or read; the message names the source and why."""


class SourceMissing(SourceError, NotReadyError):
    """A device source that is not there yet (unplugged, busy) and may come without a change of params."""


class SourceConfigError(RuntimeError):
    """A source that can give no further frame as configured, however often it is reopened (a simulated
    scene whose next frame cannot be played): the camera node stops with this error (`Node.fail`). The
    message names the source and why."""


@dataclass
class Frame:
    """image: (H, W) or (H, W, 3) uint8 (BGR); stamp_ns: capture time (ns since epoch); index: the frame's
    number in its video file or image folder, from 0 at each pass (`Image.frame_index`; -1: a live source)."""

    image: np.ndarray
    stamp_ns: int
    index: int = -1


class FrameSource(Protocol):
    name: str

    def open(self) -> None: ...

    def read(self) -> Frame | None: ...

    def close(self) -> None: ...


class VideoFileSource:
    """Frames of a video file, optionally looping, numbered from 0 at each pass (`Frame.index`: a
    looped or reopened file starts over at frame 0). A file removed or replaced while open
    raises SourceError at the next read (one stat() per frame): the node reports it lost
    and reopens it when it is back, as with an unplugged camera. Once `finished` (not looping),
    `missing_frames` is how many of the frames its container lists were not decoded: 0 at a clean end,
    more for a file cut short or damaged."""

    def __init__(self, path: str, loop: bool = True) -> None:
        self.path = Path(path)
        self.loop = loop
        self.name = f"video {self.path}"
        self._cap: cv2.VideoCapture | None = None
        self._identity: tuple[int, int] | None = None  # (st_dev, st_ino) of the file opened
        self.file_fps = 0.0
        self.finished = False
        self.missing_frames = 0
        self._listed = 0  # frames the container lists (0 when it does not say)
        self._index = 0  # number of the next frame in the file

    def open(self) -> None:
        if not self.path.is_file():
            raise SourceError(f"{self.name}: no such file")
        identity = _identity(self.path)
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise SourceError(f"{self.name}: OpenCV cannot decode it")
        self._cap = cap
        self._identity = identity
        self._index = 0
        self.file_fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self._listed = max(int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0)

    def read(self) -> Frame | None:
        if self._cap is None:
            return None
        try:
            identity = _identity(self.path)
        except OSError:
            raise SourceError(f"{self.name}: file removed") from None
        if identity != self._identity:
            raise SourceError(f"{self.name}: file replaced")
        ok, image = self._cap.read()
        if not ok:
            if not self.loop:
                self.finished = True
                self.missing_frames = max(self._listed - self._index, 0)
                return None
            self.close()
            self.open()  # raises SourceError when the file has gone: the node reopens with backoff
            ok, image = self._cap.read()
            if not ok:
                return None
        index, self._index = self._index, self._index + 1
        return Frame(image, time.time_ns(), index)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def _identity(path: Path) -> tuple[int, int]:
    """(device, inode) of `path`: tells the file opened from one put in its place."""
    st = os.stat(path)
    return st.st_dev, st.st_ino


class FolderSource:
    """Images of a folder in name order, optionally looping, each numbered by its place in that order
    (`Frame.index`). An unreadable image is
    skipped (logged once); a removed one raises SourceError (the folder is reopened). Images
    come as uint8 mono or BGR (`as_uint8`), deeper ones at one gain: the white level of the deepest
    bit depth seen so far (`full_scale`), which a frame raises by whole bits only."""

    def __init__(self, path: str, loop: bool = True) -> None:
        self.path = Path(path)
        self.loop = loop
        self.name = f"folder {self.path}"
        self._files: list[Path] = []
        self._unreadable: set[Path] = set()
        self._index = 0
        self._full_scale: float | None = None  # of images deeper than 8 bits: the highest so far
        self.finished = False

    def open(self) -> None:
        try:
            self._files = image_files(self.path)
        except ValueError as exc:
            raise SourceError(f"{self.name}: {exc}") from None
        self._index = 0

    def read(self) -> Frame | None:
        for _ in range(len(self._files)):  # at most one pass over unreadable images
            if self._index >= len(self._files):
                if not self.loop:
                    self.finished = True
                    return None
                self._index = 0
            path = self._files[self._index]
            self._index += 1
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if image is not None:
                if image.dtype != np.uint8:  # the white level only rises (a dark first frame: 255, then 4095)
                    self._full_scale = max(self._full_scale or 0.0, full_scale(image))
                return Frame(as_uint8(image, self._full_scale), time.time_ns(), self._index - 1)
            if not path.is_file():
                raise SourceError(f"{self.name}: {path.name} removed")
            if path not in self._unreadable:
                self._unreadable.add(path)
                log.warning("%s: cannot read %s, skipped", self.name, path.name)
        return None

    def close(self) -> None:
        self._files = []


def full_scale(image: np.ndarray) -> float:
    """The white level of an image deeper than 8 bits: 1 for float images in [0, 1], else the
    largest 2**bits - 1 its maximum needs (4095 for 12-bit data stored in 16 bits), at least 255."""
    top = float(np.max(image))
    if image.dtype.kind == "f" and top <= 1.0:
        return 1.0
    return float(2 ** max(8, int(np.ceil(np.log2(max(top, 1.0) + 1.0)))) - 1)


def as_uint8(image: np.ndarray, white: float | None = None) -> np.ndarray:
    """`image` as uint8 mono (H, W) or BGR (H, W, 3): an alpha channel dropped (a BGRA image broke
    `encoding: bgr8`), deeper images scaled so that `white` is 255 (default: `full_scale` of this
    image; a folder passes the highest so far, so its frames share one gain: scaled by its own
    maximum, a frame with one hot pixel came out half as bright as the next)."""
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    elif image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.dtype != np.uint8:
        image = cv2.convertScaleAbs(image, alpha=255.0 / (white or full_scale(image)))
    return image


V4L2_SYSFS = Path("/sys/class/video4linux")  # one folder per device node, with its `name` and `index`


def find_v4l2_device(name: str, sysfs: Path = V4L2_SYSFS) -> str:
    """The /dev path of the one V4L2 capture node whose name holds `name` (case-insensitive;
    e.g. "GelSight Mini", or a serial number to pick one of two). A UVC camera has a
    metadata node of the same name beside its capture node: only index 0 counts. Raises
    SourceMissing when none matches (not plugged in yet), SourceError when several do, naming the
    devices seen."""
    seen, matches = [], []
    for node in sorted(sysfs.glob("video*"), key=lambda d: (len(d.name), d.name)):
        try:
            label = (node / "name").read_text().strip()
            index = (node / "index").read_text().strip() if (node / "index").exists() else "0"
        except OSError:
            continue
        seen.append(f"/dev/{node.name} ({label})")
        if name.lower() in label.lower() and index == "0":
            matches.append(f"/dev/{node.name}")
    if len(matches) == 1:
        return matches[0]
    listed = ", ".join(seen) or "none"
    if matches:
        raise SourceError(f"v4l2 {name!r}: {len(matches)} cameras match ({', '.join(matches)}); "
                          f"give more of the name (a serial number) or the /dev path. Devices: {listed}")
    raise SourceMissing(f"v4l2 {name!r}: no camera of that name (plugged in?). Devices: {listed}")


class V4L2Source:
    """A V4L2 webcam (index, /dev/videoN, or part of its name: see `find_v4l2_device`, looked
    up at every open, so a camera plugged back under another number is found) with size,
    rate, exposure and white balance locked by params (a size of 0 keeps the camera's own, a
    negative exposure / white balance the camera's auto mode)."""

    def __init__(self, device: str, width: int, height: int, fps: float, exposure: float,
                 white_balance: float) -> None:
        self.device = device
        self.name = f"v4l2 {device}"
        self.settings = (width, height, fps, exposure, white_balance)
        self._cap: cv2.VideoCapture | None = None

    def _target(self) -> int | str:
        """The device to open: an index, a /dev path, or the node found by name."""
        if self.device.isdigit():
            return int(self.device)
        if self.device.startswith("/"):
            return self.device
        return find_v4l2_device(self.device)

    def open(self) -> None:
        target = self._target()
        node = Path(f"/dev/video{target}" if isinstance(target, int) else target)  # OpenCV's node of an index
        if not node.exists():  # unplugged: said without OpenCV's warnings (each carries the time: no two alike)
            raise SourceMissing(f"{self.name}: no {node} (plugged in?)")
        # OpenCV's V4L2 backend ignores CAP_PROP_READ_TIMEOUT_MSEC; it reads this once, at the first capture
        os.environ.setdefault("OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT", str(V4L2_READ_TIMEOUT_S))
        cap = cv2.VideoCapture(target, cv2.CAP_V4L2)
        if not cap.isOpened():
            raise SourceMissing(f"{self.name}: cannot open {target} (missing, busy or no permission)")
        width, height, fps, exposure, white_balance = self.settings
        if width and height:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        cap.set(cv2.CAP_PROP_FPS, fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        if exposure >= 0:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2 "manual" mode
            cap.set(cv2.CAP_PROP_EXPOSURE, exposure)
        if white_balance >= 0:
            cap.set(cv2.CAP_PROP_AUTO_WB, 0)
            cap.set(cv2.CAP_PROP_WB_TEMPERATURE, white_balance)
        self._cap = cap

    def read(self) -> Frame | None:
        """The next frame; SourceMissing when the camera gives none (unplugged or stalled)."""
        if self._cap is None:
            return None
        ok = self._cap.grab()
        stamp = time.time_ns()
        if not ok:
            raise SourceMissing(f"{self.name}: no frame (unplugged or stalled?)")
        ok, image = self._cap.retrieve()
        return Frame(image, stamp) if ok else None

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None
