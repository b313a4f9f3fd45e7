"""Tracker and interpolator nodes on the simulated camera: markers, fields and contact
flow at camera rate, and a press shows up in the field where the truth says."""
from __future__ import annotations

import numpy as np

from nodes.bus import TopicReader
from tests.nodes.conftest import REPO


def test_sim_press_reaches_field_and_contact(bus, spawn) -> None:
    scene = REPO / "launch" / "scenes" / "press_shear_slide.yaml"
    for args in (("node", "tracker"), ("node", "interpolator"),
                 ("node", "camera", "-p", "fps=15", "-p", f"scene={scene}")):
        spawn(*args)
    markers, fields, contacts = [], [], []
    with TopicReader(["/markers", "/field", "/contact", "/markers/reference"]) as reader:
        reference = None
        while len(fields) < 45:
            item = reader.recv(20.0)
            assert item is not None, f"pipeline stalled after {len(fields)} fields"
            {"/markers": markers, "/field": fields, "/contact": contacts}.get(item.topic, []).append(item.msg)
            if item.topic == "/markers/reference":
                reference = item.msg
    assert reference is not None and len(reference.ref_px) >= 200  # 16x16 grid, border markers may drop
    m = markers[-1]
    assert m.ref_px.shape == m.cur_px.shape and m.valid.mean() > 0.9
    f = fields[-1]
    assert f.field.shape == (30, 30, 3) and f.valid and np.isfinite(f.field).all()
    assert f.grid_x_px[0] < f.grid_x_px[-1] and f.grid_y_px[0] < f.grid_y_px[-1]
    # 2 N on a 10 mm sphere, then shear: several px of displacement, positive x shear
    peak = max(float(x.field[..., 2].max()) for x in fields)
    assert peak > 2.0, peak
    assert any(c.in_contact for c in contacts)
    stamps = [x.stamp_ns for x in fields]
    assert stamps == sorted(stamps)
    # each field carries the capture stamp of the frame its markers came from
    assert {x.stamp_ns for x in fields[5:]} <= {x.stamp_ns for x in markers}
