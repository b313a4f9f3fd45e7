"""`StartGate`: a source node's first output held back until the nodes that consume it are up.

A node that starts a stream (a camera, a bag player) names the nodes it waits for; each of them
reports its first NodeStatus on `/status` once its subscriptions are made, so a replayed video or
bag reaches them whole from its first frame. Only statuses published after the gate was made
count: `/status` is latched, and a forwarder that outlives a launch still holds the statuses of
the previous launch's nodes of the same names. After the timeout the gate opens anyway, warned."""
from __future__ import annotations

import time

from msgs import NodeStatus
from nodes.node import Node


class StartGate:
    """Open once every node of ``names`` has reported on `/status` since the gate was made (a node
    up before then is counted at its next periodic status), or ``timeout_s`` after creation.

    Create it in the node's setup (it subscribes to `/status` there when ``names`` is not empty)."""

    def __init__(self, node: Node, names: list[str], timeout_s: float) -> None:
        self.node = node
        self.awaited = set(names)
        self.timeout_s = timeout_s
        self.open_by = time.monotonic() + timeout_s
        self.made_ns = time.time_ns()
        if self.awaited:
            node.subscribe("/status", NodeStatus, self._on_status, depth=None)

    def _on_status(self, msg: NodeStatus) -> None:
        if msg.pub_ns >= self.made_ns:
            self.awaited.discard(msg.node)

    def waiting(self) -> bool:
        """Whether the first output is still held back (warns in the node's status once the timeout
        has passed with nodes missing)."""
        if not self.awaited:
            return False
        if time.monotonic() < self.open_by:
            return True
        self.node.warn(f"started without a status from {sorted(self.awaited)} after {self.timeout_s} s")
        self.awaited = set()
        return False
