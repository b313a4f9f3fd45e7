"""Parameter messages: a request to change a running node's params, and the node's latched answer.

A node named N reads `ParamSet` on `/N/param/set` and publishes `ParamState`, latched, on `/N/param/state`:
once at start (request_id "") and after every request, so the last one always holds its current params.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from msgs.message import Message


def _check_names(values: dict, what: str) -> None:
    """ValueError unless `values` is keyed by text (param names)."""
    for key in values:
        if not isinstance(key, str):
            raise ValueError(f"{what}: key {key!r:.40} is not a param name")


@dataclass(kw_only=True)
class ParamSet(Message):
    """Set params of a running node.

    request_id: chosen by the sender; the node's `ParamState` answering it carries it back.
    values: {param name: new value} (plain values: numbers, text, booleans, lists), applied all or none.
    """

    TYPE: ClassVar[str] = "ParamSet"
    VERSION: ClassVar[int] = 1

    request_id: str = ""
    values: dict = field(default_factory=dict)

    def validate(self) -> None:
        super().validate()
        _check_names(self.values, "values")


@dataclass(kw_only=True)
class ParamState(Message):
    """A node's current params and its answer to the last request.

    params: {name: value} of every param, as the node runs now.
    live: the names of the params it takes while it runs (the others need a restart).
    request_id: the `ParamSet` this answers ("" for the state published at start).
    accepted: whether that request was applied; error: why not ("" when accepted).
    """

    TYPE: ClassVar[str] = "ParamState"
    VERSION: ClassVar[int] = 1

    params: dict = field(default_factory=dict)
    live: list = field(default_factory=list)
    request_id: str = ""
    accepted: bool = True
    error: str = ""

    def validate(self) -> None:
        super().validate()
        _check_names(self.params, "params")
        if not all(isinstance(name, str) for name in self.live):
            raise ValueError(f"live: {self.live!r:.80} is not a list of param names")
