"""Crop and resize of camera frames: cut a fixed share off each border of every frame (a
sensor's housing, the dark corners of its lens) and scale the rest to a fixed size, as the
GelSight Mini's own software does (1/7 off each border, then 320x240) before the frames its
users record. The camera matrix follows the same cut and scale."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

MAX_SIZE_PX = 8192  # largest width or height frames are resized to: past 8K, a typo (one 100000x100000 frame: 30 GB)


@dataclass(frozen=True)
class FrameCrop:
    """borders: shares of the frame cut off (top, bottom, left, right), each in [0, 0.5),
    top + bottom and left + right < 1; size: (width, height) in px the rest is resized to,
    or None to keep it as cut."""

    borders: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        if len(self.borders) != 4:
            raise ValueError(f"crop {list(self.borders)} must hold 4 shares: top, bottom, left, right")
        if not all(0.0 <= b < 0.5 for b in self.borders):
            raise ValueError(f"crop {list(self.borders)}: every share must be in [0, 0.5)")
        if self.size is not None and (len(self.size) != 2 or min(self.size) < 1 or max(self.size) > MAX_SIZE_PX):
            raise ValueError(f"size {list(self.size)} must be [width, height] in px, both >= 1 and <= {MAX_SIZE_PX}")

    @classmethod
    def from_lists(cls, crop: list[float], size: list[int]) -> FrameCrop | None:
        """From plain lists (the camera node's params): `crop` [] (none), [share] (every border)
        or [top, bottom, left, right]; `size` [] (as cut) or [width, height]. None when both
        are empty: frames pass untouched. ValueError names a bad list, share or size."""
        if len(crop) not in (0, 1, 4):
            raise ValueError(f"crop {list(crop)} must be [], [share] or [top, bottom, left, right]")
        if not crop and not size:
            return None
        if len(crop) == 1:
            crop = list(crop) * 4
        borders = tuple(float(b) for b in crop) if crop else (0.0, 0.0, 0.0, 0.0)
        return cls(borders, tuple(int(v) for v in size) if size else None)  # type: ignore[arg-type]

    def window(self, width: int, height: int) -> tuple[int, int, int, int]:
        """The part kept of a (height, width) frame: (x0, y0, x1, y1) in px, x1 / y1
        exclusive; each border is its share of the frame, rounded to whole px."""
        top, bottom, left, right = self.borders
        x0, x1 = round(left * width), width - round(right * width)
        y0, y1 = round(top * height), height - round(bottom * height)
        if x1 <= x0 or y1 <= y0:
            raise ValueError(f"crop {list(self.borders)} leaves nothing of a {width}x{height} frame")
        return x0, y0, x1, y1

    def apply(self, image: np.ndarray) -> np.ndarray:
        """(H, W) or (H, W, 3) uint8 -> the kept part, resized to `size` (area averaging when
        it shrinks, bilinear when it grows)."""
        x0, y0, x1, y1 = self.window(image.shape[1], image.shape[0])
        kept = image[y0:y1, x0:x1]
        if self.size is None or self.size == (x1 - x0, y1 - y0):
            return np.ascontiguousarray(kept)
        shrink = self.size[0] < x1 - x0
        return cv2.resize(kept, self.size, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)

    def camera_matrix(self, K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, int, int]:
        """A (3, 3) camera matrix K (px) of (width, height) frames -> the same camera's matrix
        in the cropped, resized frames and their width and height. The distortion of a
        fisheye model acts on normalised coordinates, so it is unchanged."""
        x0, y0, x1, y1 = self.window(width, height)
        out_w, out_h = self.size or (x1 - x0, y1 - y0)
        sx, sy = out_w / (x1 - x0), out_h / (y1 - y0)
        K2 = np.array(K, np.float64, copy=True)
        K2[0, 2] = (K2[0, 2] - x0 + 0.5) * sx - 0.5  # pixel centres: px k spans [k - 0.5, k + 0.5]
        K2[1, 2] = (K2[1, 2] - y0 + 0.5) * sy - 0.5
        K2[0, :2] *= sx
        K2[1, :2] *= sy
        return K2, out_w, out_h
