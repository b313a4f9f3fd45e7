"""Several inputs' items, each input in its own stamp order, handed on in one stamp order whatever order
they arrive in: what makes a vote over cameras (:mod:`fv_algos.camera_vote`) the same on every replay of
a recording. No torch, no bus: the slip fusion node imports it."""
from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Generic, TypeVar

T = TypeVar("T")


@dataclass(order=True)
class _Pending(Generic[T]):
    stamp_ns: int
    rank: int  # the input's place in `inputs`: equal stamps go in that order
    seq: int  # arrival order, for equal stamps of one input
    name: str = field(compare=False)
    arrived_s: float = field(compare=False)
    item: T = field(compare=False)


class StampOrder(Generic[T]):
    """Items of named inputs, handed on by stamp (ns), ties in the order of ``inputs``.

    An item is held until every other input has sent an item stamped at or after it (then nothing
    earlier can come from it: each input sends in its own stamp order), or until ``wait_s`` (s) has
    passed since it arrived; with more than two inputs an item also waits for the earlier-stamped ones
    held before it (at most ``stale_after_s`` + ``wait_s``). An input is not waited for once it has sent
    nothing for ``stale_after_s`` (a camera that stopped), nor, ``stale_after_s`` after the first item of
    any input, if it has never sent one (a camera that never started). Counters: ``waited``, items
    handed on after ``wait_s`` while an input was still awaited; ``late``, items stamped before one
    already handed on (they are handed on at once: what comes after a wait, or an input whose clock is
    behind); ``restarts``, times the order started afresh because an input's stamps went back (a
    recording played again, a source restarted: one or more per pass, as the inputs' last items of the
    pass before come): everything held is then handed on, so the items around a restart go in arrival
    order. Times are the caller's monotonic clock (s)."""

    def __init__(self, inputs: Sequence[str], wait_s: float, stale_after_s: float) -> None:
        if len(inputs) < 1 or len(set(inputs)) != len(inputs):
            raise ValueError(f"inputs {list(inputs)} must be one or more different names")
        if not 0 < wait_s < math.inf or not stale_after_s > 0:
            raise ValueError(f"wait_s {wait_s} must be > 0 and finite, stale_after_s {stale_after_s} > 0")
        self.inputs = tuple(inputs)
        self.rank = {name: k for k, name in enumerate(self.inputs)}
        self.wait_s, self.stale_after_s = wait_s, stale_after_s
        self.pending: list[_Pending[T]] = []
        self.last_ns: dict[str, int] = {}  # each input's latest stamp in this order (since the last restart)
        self.arrived_s: dict[str, float] = {}  # when each input's latest item arrived
        self.first_s: float | None = None  # arrival of the first item of any input
        self.handed_ns: int | None = None  # the latest stamp handed on (since the last restart)
        self.counters = {"waited": 0, "late": 0, "restarts": 0}
        self._seq = itertools.count()

    def push(self, name: str, stamp_ns: int, item: T, now_s: float) -> list[tuple[str, T]]:
        """Take ``item`` of input ``name`` stamped ``stamp_ns``, arrived at ``now_s``; the items now due,
        in order, as (input, item). KeyError for a name not among the inputs."""
        rank = self.rank[name]
        due: list[tuple[str, T]] = []
        if name in self.last_ns and stamp_ns < self.last_ns[name]:
            self.counters["restarts"] += 1
            due = self.flush()
        self.last_ns[name] = stamp_ns  # not below the input's last: that was a restart, and cleared it
        self.arrived_s[name] = now_s
        self.first_s = now_s if self.first_s is None else self.first_s
        heapq.heappush(self.pending, _Pending(stamp_ns, rank, next(self._seq), name, now_s, item))
        return due + self.due(now_s)

    def due(self, now_s: float) -> list[tuple[str, T]]:
        """The held items due at ``now_s`` (call it now and then: those held for ``wait_s`` go on), in order."""
        out = []
        while self.pending:
            head = self.pending[0]
            awaited = self._awaited(head, now_s)
            if awaited and now_s - head.arrived_s < self.wait_s:
                break
            self.counters["waited"] += bool(awaited)
            out.append(self._hand_on(heapq.heappop(self.pending)))
        return out

    def held(self) -> int:
        """How many items are held."""
        return len(self.pending)

    def _awaited(self, head: _Pending[T], now_s: float) -> bool:
        """Whether an input other than ``head``'s may still send an item stamped before it."""
        for name in self.inputs:
            if name == head.name:
                continue
            if name not in self.arrived_s:
                if self.first_s is None or now_s - self.first_s <= self.stale_after_s:
                    return True
            elif self.last_ns.get(name, -1) < head.stamp_ns and now_s - self.arrived_s[name] <= self.stale_after_s:
                return True
        return False

    def _hand_on(self, pending: _Pending[T]) -> tuple[str, T]:
        if self.handed_ns is not None and pending.stamp_ns < self.handed_ns:
            self.counters["late"] += 1
        else:
            self.handed_ns = pending.stamp_ns
        return pending.name, pending.item

    def flush(self) -> list[tuple[str, T]]:
        """Every held item, in order, and the order started afresh (after a restart, at the end)."""
        out = [self._hand_on(heapq.heappop(self.pending)) for _ in range(len(self.pending))]
        self.last_ns.clear()
        self.handed_ns = None
        return out
