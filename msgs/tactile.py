"""Tactile messages: tracked markers, the dense displacement field, contact and slip."""
from __future__ import annotations

from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import ClassVar

import numpy as np

from msgs.message import ArraySpec, Message, require_image_size, require_same_length


@dataclass(kw_only=True)
class MarkerArray(Message):
    """Tracked markers of one frame, in image px.

    ref_px: (N, 2) float reference (undeformed) positions x, y.
    cur_px: (N, 2) float current positions x, y (last seen position when not valid).
    valid: (N,) bool, the marker was matched in this frame and passed the checks.
    frames_since_seen: (N,) int, 0 when seen in this frame.
    width, height: size in px of the image the markers were found in (both > 0).
    """

    TYPE: ClassVar[str] = "MarkerArray"
    VERSION: ClassVar[int] = 1
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "ref_px": ArraySpec("f", (2,)),
        "cur_px": ArraySpec("f", (2,)),
        "valid": ArraySpec("b", (1,)),
        "frames_since_seen": ArraySpec("iu", (1,)),
    }

    ref_px: np.ndarray = dc_field(default_factory=lambda: np.zeros((0, 2), np.float32))
    cur_px: np.ndarray = dc_field(default_factory=lambda: np.zeros((0, 2), np.float32))
    valid: np.ndarray = dc_field(default_factory=lambda: np.zeros(0, bool))
    frames_since_seen: np.ndarray = dc_field(default_factory=lambda: np.zeros(0, np.int32))
    width: int = 0
    height: int = 0

    def validate(self) -> None:
        super().validate()
        for name in ("ref_px", "cur_px"):
            if getattr(self, name).shape[1:] != (2,):
                raise ValueError(f"{name}: shape {getattr(self, name).shape} is not (N, 2)")
        require_same_length(self, ("ref_px", "cur_px", "valid", "frames_since_seen"))
        require_image_size(self.width, self.height)


@dataclass(kw_only=True)
class DisplacementField(Message):
    """Dense marker displacement field on a regular grid in reference image coordinates.

    field: (H, W, 3) float32, channels dx, dy, magnitude, in `units` (px).
    grid_x_px: (W,) float x coordinate of each column; grid_y_px: (H,) of each row.
    valid: False when too few markers were tracked to trust the field.
    n_markers_used / n_markers: markers that entered the interpolation / tracked in all.
    """

    TYPE: ClassVar[str] = "DisplacementField"
    VERSION: ClassVar[int] = 1
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {
        "field": ArraySpec("f", (3,)),
        "grid_x_px": ArraySpec("f", (1,)),
        "grid_y_px": ArraySpec("f", (1,)),
    }

    field: np.ndarray = dc_field(default_factory=lambda: np.zeros((0, 0, 3), np.float32))
    grid_x_px: np.ndarray = dc_field(default_factory=lambda: np.zeros(0, np.float32))
    grid_y_px: np.ndarray = dc_field(default_factory=lambda: np.zeros(0, np.float32))
    units: str = "px"
    valid: bool = True
    n_markers_used: int = 0
    n_markers: int = 0
    method: str = ""

    def validate(self) -> None:
        super().validate()
        h, w, c = self.field.shape
        if c != 3:
            raise ValueError(f"field: shape {self.field.shape} is not (H, W, 3)")
        if self.grid_x_px.shape != (w,):
            raise ValueError(f"grid_x_px: shape {self.grid_x_px.shape} does not match field width {w}")
        if self.grid_y_px.shape != (h,):
            raise ValueError(f"grid_y_px: shape {self.grid_y_px.shape} does not match field height {h}")


@dataclass(kw_only=True)
class ContactSummary(Message):
    """Contact descriptors computed from one displacement field (field units: px).

    area_px2: area of grid cells whose displacement exceeds the contact threshold.
    area_share: those cells as a share of the grid, in [0, 1].
    centre_x_px, centre_y_px: displacement-weighted centre of the contact.
    shear_x_px, shear_y_px: mean displacement over the contact (mean shear).
    rotation_rad: half the mean curl (torsion; > 0 clockwise on screen).
    divergence: mean divergence, dimensionless (normal-press index: > 0 when the skin
    spreads out under a press).
    """

    TYPE: ClassVar[str] = "ContactSummary"
    VERSION: ClassVar[int] = 1

    in_contact: bool = False
    area_px2: float = 0.0
    area_share: float = 0.0
    centre_x_px: float = 0.0
    centre_y_px: float = 0.0
    shear_x_px: float = 0.0
    shear_y_px: float = 0.0
    rotation_rad: float = 0.0
    divergence: float = 0.0


@dataclass(kw_only=True)
class SlipState(Message):
    """Slip decision for the window of fields ending at `stamp_ns`.

    probability: P(slip) in [0, 1]. slip: the decision after threshold (in [0, 1]) and hysteresis.
    window_stamps_ns: (T,) int64 capture stamps of the fields the model judged (a trial
    model judges a whole grasp: its first stamp and that of its last frame judged, the current one
    unless a camera faster than the model has this frame left out).
    valid: False when the window held invalid fields (then probability is 0 and slip
    keeps its last value).
    """

    TYPE: ClassVar[str] = "SlipState"
    VERSION: ClassVar[int] = 1
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {"window_stamps_ns": ArraySpec("iu", (1,))}

    probability: float = 0.0
    slip: bool = False
    threshold: float = 0.5
    window_stamps_ns: np.ndarray = dc_field(default_factory=lambda: np.zeros(0, np.int64))
    model: str = ""
    valid: bool = True

    def validate(self) -> None:
        super().validate()
        for name in ("probability", "threshold"):
            if not 0.0 <= getattr(self, name) <= 1.0:  # NaN too
                raise ValueError(f"{name}: {getattr(self, name)} is not in [0, 1]")


@dataclass(kw_only=True)
class GraspStart(Message):
    """A new grasp starts: a tracker's reference from before is no longer tracked against. A tracker says each
    grasp it starts (on `markers/grasp_start`), a video or folder camera each pass of its source (on
    `camera/pass_start`).

    cause: "reset" (a message on /tracker/reset, stamp_ns its stamp: the next frame is the new reference) or
    "source restart" (the camera's source started over, a looped video's next pass: frame `reference_frame` of
    the pass is the new reference; stamp_ns the stamp of the pass's first frame the tracker saw, of the
    pass's frame 0 from the camera).
    """

    TYPE: ClassVar[str] = "GraspStart"
    VERSION: ClassVar[int] = 1
    CAUSES: ClassVar[tuple[str, ...]] = ("reset", "source restart")

    cause: str = "reset"

    def validate(self) -> None:
        super().validate()
        if self.cause not in self.CAUSES:
            raise ValueError(f"cause: {self.cause!r} is not one of {self.CAUSES}")
