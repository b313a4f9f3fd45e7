"""Camera messages: `Image` frames and the latched `CameraInfo` calibration."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from msgs.message import ArraySpec, Message, require_image_size

ENCODING_CHANNELS = {"mono8": 1, "bgr8": 3, "rgb8": 3}


def source_started_over(frame_index: int, previous_index: int) -> bool:
    """Whether a frame numbered `frame_index` (`Image.frame_index`), after one numbered `previous_index` (-1:
    none, or a live camera's), begins a new pass of its source: its number went back."""
    return 0 <= frame_index < previous_index


@dataclass(kw_only=True)
class Image(Message):
    """One camera frame.

    data: (H, W) uint8 for "mono8", (H, W, 3) uint8 for "bgr8" / "rgb8", H and W > 0.
    stamp_ns is the capture time of the frame.
    frame_index: the frame's number in the video file or image folder it was read from, from 0, and from 0
    again each time the source starts over (a looped video's next pass, a file reopened); -1 for frames
    of a live camera or the simulator, and in recordings made before the field existed.
    """

    TYPE: ClassVar[str] = "Image"
    VERSION: ClassVar[int] = 1
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"data": ArraySpec("u", (2, 3))}
    ADDED: ClassVar[frozenset[str]] = frozenset({"frame_index"})

    encoding: str = "mono8"
    data: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.uint8))
    frame_index: int = -1

    def validate(self) -> None:
        super().validate()
        if self.frame_index < -1:
            raise ValueError(f"frame_index: {self.frame_index} is not >= -1")
        if self.encoding not in ENCODING_CHANNELS:
            raise ValueError(f"encoding: {self.encoding!r} is not one of {sorted(ENCODING_CHANNELS)}")
        # mono8 (H, W), colour (H, W, 3): mono8 data of (H, W, 1) was taken, and the tracker refused every such frame
        if self.data.shape[2:] != (() if ENCODING_CHANNELS[self.encoding] == 1 else (3,)):  # (2 or 3 dims: ARRAYS)
            raise ValueError(f"data: shape {self.data.shape} does not match encoding {self.encoding!r} ((H, W) for "
                             "mono8, (H, W, 3) for bgr8 and rgb8)")
        if self.data.dtype != np.uint8:
            raise ValueError(f"data: dtype {self.data.dtype} is not uint8")
        if not self.data.size:
            raise ValueError(f"data: shape {self.data.shape} holds no pixels")

    @property
    def width(self) -> int:
        return int(self.data.shape[1])

    @property
    def height(self) -> int:
        return int(self.data.shape[0])


CAMERA_MODELS = ("fisheye", "pinhole")


@dataclass(kw_only=True)
class CameraInfo(Message):
    """The camera model of the published frames, latched.

    model: "fisheye" (OpenCV's fisheye model: D its coefficients k1..k4) or "pinhole" (frames the
    camera node undistorted: D zeros). K: (3, 3) float64 camera matrix in px. D: (4,) float64.
    width, height: image size in px the calibration applies to. rms_px: calibration
    reprojection error (0 when unknown, e.g. a simulated camera with exact intrinsics).
    """

    TYPE: ClassVar[str] = "CameraInfo"
    VERSION: ClassVar[int] = 1
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"K": ArraySpec("f", (2,)), "D": ArraySpec("f", (1,))}

    model: str = "fisheye"
    width: int = 0
    height: int = 0
    K: np.ndarray = field(default_factory=lambda: np.eye(3))
    D: np.ndarray = field(default_factory=lambda: np.zeros(4))
    rms_px: float = 0.0

    def validate(self) -> None:
        super().validate()
        if self.K.shape != (3, 3):
            raise ValueError(f"K: shape {self.K.shape} is not (3, 3)")
        if self.D.shape != (4,):
            raise ValueError(f"D: shape {self.D.shape} is not (4,)")
        if self.model not in CAMERA_MODELS:
            raise ValueError(f"model: {self.model!r} is not one of {CAMERA_MODELS}")
        require_image_size(self.width, self.height)
