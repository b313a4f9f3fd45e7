"""The `interpolator` node: MarkerArray -> DisplacementField on `/field` (30x30 by
default: dx, dy, magnitude in px) and a ContactSummary on `/contact`."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fv_algos.contact_summary import ContactParams, summarise_contact
from fv_algos.field import MAX_MARKERS, FieldInterpolator, FieldParams
from msgs import ContactSummary, DisplacementField, MarkerArray
from nodes.node import Node


@dataclass
class InterpolatorParams:
    method: str = "rbf_operator"  # rbf_operator (precomputed) | rbf_refit (the paper) | griddata (cubic)
    kernel: str = "thin_plate_spline"  # thin_plate_spline | multiquadric | inverse_multiquadric | gaussian | linear | cubic
    grid: int = 30  # grid is grid x grid cells over the reference markers
    smoothing: float = 0.0
    width_px: float = 0.0  # kernel width for multiquadric / gaussian; 0 = marker spacing
    contact: bool = True  # also publish /contact
    contact_threshold_px: float = 1.0
    input_timeout_s: float = 2.0  # warn in NodeStatus after this long without markers (0 = never)
    max_markers: int = MAX_MARKERS  # a MarkerArray with more is refused: the RBF solve grows as N^3

    def __post_init__(self) -> None:
        self.field_params()  # ValueError names a bad method, kernel, grid, smoothing or width_px
        if self.input_timeout_s < 0:
            raise ValueError(f"input_timeout_s {self.input_timeout_s} must be > 0, or 0 for never")
        if self.max_markers < 3:
            raise ValueError(f"max_markers {self.max_markers} must be >= 3")

    def field_params(self) -> FieldParams:
        """The field interpolation these params describe."""
        return FieldParams(method=self.method, grid_shape=(self.grid, self.grid), kernel=self.kernel,
                           smoothing=self.smoothing, width_px=self.width_px or None)


class InterpolatorNode(Node):
    """Interpolates marker displacements onto the fixed grid (one operator per reference)."""

    Params = InterpolatorParams

    def setup(self) -> None:
        p = self.params
        self.field_params = p.field_params()
        self.contact_params = ContactParams(p.contact_threshold_px)
        self.interpolator = None
        self.reference_key: bytes | None = None  # ref_px of the reference `interpolator` was built for
        self.field_pub = self.publisher("field", DisplacementField)
        self.contact_pub = self.publisher("contact", ContactSummary) if p.contact else None
        self.subscribe("markers", MarkerArray, self.on_markers, depth=5,
                       stale_after_s=p.input_timeout_s or None, answered_by=self.field_pub)
        self.counters.update(invalid_fields=0, too_many_markers=0, bad_references=0)

    def on_markers(self, msg: MarkerArray) -> None:
        """Publish the field (and the contact summary) of `msg`'s markers, interpolated on the grid from its
        reference (the operator rebuilt when the reference changes). Refused with a warning: more than
        max_markers markers (too_many_markers), a reference the interpolator cannot be built from
        (bad_references; the last good one is kept)."""
        if len(msg.ref_px) > self.params.max_markers:
            self.counters["too_many_markers"] += 1
            self.warn(f"a MarkerArray of {len(msg.ref_px)} markers from {msg.node!r} refused: more than max_markers "
                      f"{self.params.max_markers} (too_many_markers)", kind="too many markers")
            return
        key = msg.ref_px.tobytes()
        if key != self.reference_key:
            try:
                self.interpolator = FieldInterpolator(msg.ref_px, self.field_params)
            except ValueError as exc:  # a NaN, no marker, one listed twice: from the bus, not from a tracker
                self.counters["bad_references"] += 1
                self.warn(f"a MarkerArray from {msg.node!r} refused: {exc} (bad_references)", kind="bad reference")
                return
            self.reference_key = key
        self.clear_warning()
        dense = self.interpolator.interpolate(msg.cur_px, msg.valid)
        if not dense.valid:
            self.counters["invalid_fields"] += 1
        self.field_pub.publish(DisplacementField(
            stamp_ns=msg.stamp_ns, frame_id=msg.frame_id, field=dense.field.astype(np.float32),
            grid_x_px=dense.x_px.astype(np.float32), grid_y_px=dense.y_px.astype(np.float32), valid=dense.valid,
            n_markers_used=dense.markers_used, n_markers=int(msg.valid.sum()), method=self.params.method))
        if self.contact_pub is not None:
            self.publish_contact(dense, msg)

    def publish_contact(self, dense, msg: MarkerArray) -> None:
        c = summarise_contact(dense, self.contact_params)
        self.contact_pub.publish(ContactSummary(
            stamp_ns=msg.stamp_ns, frame_id=msg.frame_id, in_contact=bool(c.in_contact), area_px2=float(c.area_px2),
            area_share=float(c.area_share), centre_x_px=float(c.centre_px[0]), centre_y_px=float(c.centre_px[1]),
            shear_x_px=float(c.shear_px[0]), shear_y_px=float(c.shear_px[1]), rotation_rad=float(c.rotation_rad),
            divergence=float(c.divergence)))
