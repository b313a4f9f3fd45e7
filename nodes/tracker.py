"""The `tracker` node: Image -> MarkerArray on `/markers` at camera rate.

The frame number `reference_frame` (frame 0 of a real camera is often stale) becomes the
reference: its markers are published latched on `/markers/reference`. Any message on
`/tracker/reset` makes the next frame the new reference."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fv_algos.perception import Perception, PerceptionParams
from msgs import Image, MarkerArray
from nodes.node import Node

PRESETS = ("paper", "default", "fastest")


@dataclass
class TrackerNodeParams:
    preset: str = "default"  # paper (SimpleBlobDetector + nearest neighbour) | default | fastest
    reference_frame: int = 1  # frames to skip before taking the reference (frame 0 may be stale)

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"preset {self.preset!r} is not one of {PRESETS}")
        if self.reference_frame < 0:
            raise ValueError(f"reference_frame {self.reference_frame} must be >= 0")


def marker_array(state, image: Image) -> MarkerArray:
    """MarkerArray message of a `fv_algos.tracking.TrackState` for the frame `image`."""
    return MarkerArray(stamp_ns=image.stamp_ns, frame_id=image.frame_id,
                       ref_px=state.reference_px.astype(np.float32), cur_px=state.current_px.astype(np.float32),
                       valid=state.valid.astype(bool), frames_since_seen=state.frames_since_seen.astype(np.int32),
                       width=image.width, height=image.height)


class TrackerNode(Node):
    """Detects and tracks the skin markers in each camera frame (latest frame only)."""

    Params = TrackerNodeParams

    def setup(self) -> None:
        self.perception = Perception(PerceptionParams.preset(self.params.preset))
        self.frames_seen = 0
        self.needs_reference = True
        self.markers_pub = self.publisher("/markers", MarkerArray)
        self.reference_pub = self.publisher("/markers/reference", MarkerArray, latched=True)
        self.subscribe("/camera/image", Image, self.on_image, depth=1)
        self.subscribe("/tracker/reset", None, self.on_reset, depth=1)
        self.counters.update(references=0)

    def on_reset(self, _msg) -> None:
        self.needs_reference = True
        self.frames_seen = self.params.reference_frame

    def on_image(self, msg: Image) -> None:
        self.frames_seen += 1
        if self.needs_reference:
            if self.frames_seen <= self.params.reference_frame:
                return
            state = self.perception.reset(msg.data)
            self.needs_reference = False
            self.counters["references"] += 1
            self.reference_pub.publish(marker_array(state, msg))
        tracker = self.perception.tracker
        state = tracker.step(self.perception.detect(msg.data))
        self.markers_pub.publish(marker_array(state, msg))
        self.counters["valid_markers"] = int(state.valid.sum())
