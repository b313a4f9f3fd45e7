"""Names of the runnable nodes and where their classes live (imported on demand, so a
tool that lists nodes does not import torch)."""
from __future__ import annotations

import importlib

from nodes.node import Node

NODES: dict[str, str] = {
    "talker": "nodes.demo:Talker",
    "listener": "nodes.demo:Listener",
    "camera": "nodes.camera:CameraNode",
    "slip_monitor": "nodes.slip_monitor:SlipMonitor",
    "tracker": "nodes.tracker:TrackerNode",
    "interpolator": "nodes.interpolator:InterpolatorNode",
    "slip_detector": "nodes.slip_detector:SlipDetectorNode",
    "slip_fusion": "nodes.slip_fusion:SlipFusion",
    "bag_record": "nodes.bag.recorder:BagRecord",
    "bag_play": "nodes.bag.player:BagPlay",
    "viewer": "nodes.viewer:ViewerNode",
}


def node_class(kind: str) -> type[Node]:
    """The Node subclass registered as `kind`; KeyError naming the known kinds."""
    if kind not in NODES:
        raise KeyError(f"unknown node {kind!r}; known: {sorted(NODES)}")
    module, _, attr = NODES[kind].partition(":")
    return getattr(importlib.import_module(module), attr)
