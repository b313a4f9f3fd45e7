"""`Unanswered`: a pipeline node's word that a message it took ends with it, unanswered."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from msgs.message import Message


@dataclass(kw_only=True)
class Unanswered(Message):
    """A node handled the message stamped `stamp_ns` (frame_id: the message's) on `topic` and published
    no answer to it: a tracker's frame before its reference, a window model's field while its window
    fills, a callback that raised. Published on `unanswered` in the node's namespace
    (`nodes.node.Node.subscribe(..., answered_by=...)`), so that a batch replay (`bag_play` with
    `sync_topic`) sends the next frame at once instead of waiting `sync_timeout_s` for an answer that
    does not come.
    """

    TYPE: ClassVar[str] = "Unanswered"
    VERSION: ClassVar[int] = 1

    topic: str = ""
