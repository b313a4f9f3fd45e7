"""Read and change a running node's params over the bus (`fv param`, `nodes.client.set_param`).

Every node named N (the name `fv node list` shows: `left_slip_detector` for a slip detector a launch puts in
the namespace `left`; clients also take its ROS-style path, `/left/slip_detector`) reads `ParamSet`
requests on `/N/param/set` and publishes its params, latched, on `/N/param/state` (`ParamState`): at start, and
after each request with the request's id and the answer. A request is checked as the params are at start
(`build_params`: known names, types, the params dataclass's own validation) and applied, all or none, between
two callbacks, only when every param it names is one the node declares live (`Node.LIVE_PARAMS`); any other is
refused, named, as one that needs a restart. A request that cannot be decoded is dropped and counted in the
node's `malformed`, as on any topic. The launcher's status name (`launch_<file stem>`) answers as a node
without params (`NoParamService`).
"""
from __future__ import annotations

import dataclasses
import time
import uuid
from typing import TYPE_CHECKING, Any

import numpy as np

from msgs.param import ParamSet, ParamState
from nodes.bus import PublisherSocket, TopicReader, check_timeout, node_name, validate_topic
from nodes.endpoints import BusAddress, bus_address
from nodes.params import ParamError, build_params

if TYPE_CHECKING:
    from nodes.node import Node

ANSWER_TIMEOUT_S = 3.0  # how long a client waits for a node's answer by default (s)
POLL_S = 0.01  # how often a client looks whether the node's request subscription has reached the bus (s)


PARAM_SUFFIXES = ("/param/set", "/param/state")  # of every node's request and state topics


def param_topics(node: str) -> tuple[str, str]:
    """(request topic, state topic) of the node `node`: its name ("left_slip_detector") or its ROS-style path
    ("/left/slip_detector", "left/slip_detector"; "/slip_detector" for one at the root: `nodes.bus.node_name`)."""
    base = "/" + node_name(node)
    try:
        return validate_topic(base + PARAM_SUFFIXES[0]), validate_topic(base + PARAM_SUFFIXES[1])
    except ValueError as exc:
        raise ValueError(f"node name {node!r} names no param topics: {exc}") from None


def is_param_topic(topic: str) -> bool:
    """Whether `topic` is a node's param request or state topic (`param_topics`)."""
    return topic.endswith(PARAM_SUFFIXES)


def current_params(params: Any) -> dict[str, Any]:
    """{name: value} of a params dataclass instance, as plain values."""
    return {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}


class ParamService:
    """The param endpoints of `node`: created by the node runtime for every node, before `setup()`. Like ROS's
    services they are left out of the node's NodeStatus endpoints (`fv topic list` lists the data topics);
    `set_topic` names the subscription to leave out. `sock`: the node's publisher socket."""

    def __init__(self, node: Node, sock: PublisherSocket) -> None:
        self._node = node
        self._sock = sock
        set_topic, self._state_topic = param_topics(node.name)
        self.set_topic = node.subscribe(set_topic, ParamSet, self.on_set, depth=None).topic  # as remaps have it
        self._publish("", accepted=True, error="")

    def checked(self, values: dict[str, Any]) -> Any:
        """The node's params with `values` ({name: value}) applied; ParamError naming the param that is
        unknown, of the wrong type, invalid or not live."""
        node = self._node
        where = f"node {node.name!r}"
        if not values:
            raise ParamError(f"{where}: no param given")
        current = current_params(node.params)
        fixed = sorted(name for name in values if name in current and name not in node.LIVE_PARAMS)
        if fixed:  # said before any check of the value: those of a model or a device load things
            live = ", ".join(sorted(node.LIVE_PARAMS)) or "none"
            raise ParamError(f"{where}: param {', '.join(map(repr, fixed))} takes effect only at start: restart the "
                             f"node to change it (set live: {live})", fixed[0])
        return build_params(node.Params, {**current, **values}, where=where)  # unknown names, types, validation

    def on_set(self, msg: ParamSet) -> None:
        """Apply a request from the next callback on, and answer it (refused: the params are unchanged)."""
        try:
            self._node.params = self.checked(msg.values)
        except ParamError as exc:
            self._node.log.warning("param request %s from %r refused: %s", msg.request_id, msg.node, exc)
            self._publish(msg.request_id, accepted=False, error=str(exc))
            return
        self._node.log.info("params set by %r: %s", msg.node, msg.values)
        self._publish(msg.request_id, accepted=True, error="")

    def _publish(self, request_id: str, accepted: bool, error: str) -> None:
        _publish_state(self._sock, self._state_topic, current_params(self._node.params), sorted(self._node.LIVE_PARAMS),
                       request_id, accepted, error)


class NoParamService:
    """The param endpoints of a process that publishes a NodeStatus as `name` but is no `Node` (the launcher's
    `launch_<file stem>`), so that `fv param` answers for every name `fv node list` shows: its latched
    `ParamState` lists no params, and `answer()` refuses each request, saying so. `sock`: its publisher socket
    (its latched state is re-sent by that socket's `update()`, as all its latched messages)."""

    def __init__(self, name: str, sock: PublisherSocket, address: BusAddress) -> None:
        self._name = name
        self._sock = sock
        set_topic, self._state_topic = param_topics(name)
        self._reader = TopicReader([set_topic], address)
        self._publish("", accepted=True, error="")

    def answer(self) -> None:
        """Refuse the requests received since the last call (never waits)."""
        while (item := self._reader.recv(0.0)) is not None:
            if isinstance(item.msg, ParamSet):
                self._publish(item.msg.request_id, accepted=False, error=f"node {self._name!r} has no params")

    def close(self) -> None:
        self._reader.close()

    def _publish(self, request_id: str, accepted: bool, error: str) -> None:
        _publish_state(self._sock, self._state_topic, {}, [], request_id, accepted, error)


def _publish_state(sock: PublisherSocket, topic: str, params: dict[str, Any], live: list[str], request_id: str,
                   accepted: bool, error: str) -> None:
    """Publish a node's `ParamState` (its `params` and `live` names, the answer to `request_id`), latched."""
    sock.publish(topic, ParamState(stamp_ns=time.time_ns(), params=params, live=live, request_id=request_id,
                                   accepted=accepted, error=error), latched=True)


# -- clients ---------------------------------------------------------------------------
def _silent(node: str, topic: str, timeout_s: float, address: BusAddress) -> TimeoutError:
    """The error of a node that did not answer on `topic` within `timeout_s`, saying whether the bus answers."""
    from nodes.topic_tools import require_forwarder

    try:
        require_forwarder(address=address)
    except RuntimeError as exc:
        return TimeoutError(str(exc))
    return TimeoutError(f"no node {node!r} answers on {topic} within {timeout_s:g} s: is it running? "
                        "(`fv node list` shows the running nodes' names)")


def read_params(node: str, timeout_s: float = ANSWER_TIMEOUT_S, address: BusAddress | None = None) -> ParamState:
    """The `ParamState` of the running node `node` (its name or path, `param_topics`); TimeoutError when it
    does not answer in `timeout_s` s."""
    state = read_all_params([node], timeout_s, address)[node]
    if state is None:
        raise _silent(node, param_topics(node)[1], timeout_s, address or bus_address())
    return state


def read_all_params(nodes: list[str], timeout_s: float = ANSWER_TIMEOUT_S,
                    address: BusAddress | None = None) -> dict[str, ParamState | None]:
    """{node: its ParamState, or None when it gave none within `timeout_s` s} of each node in `nodes` (names or
    paths, `param_topics`)."""
    check_timeout(timeout_s)
    topics = {param_topics(n)[1]: n for n in nodes}
    found: dict[str, ParamState | None] = dict.fromkeys(nodes)
    deadline = time.monotonic() + timeout_s
    with TopicReader(list(topics), address) as reader:
        while any(v is None for v in found.values()) and (remaining := deadline - time.monotonic()) > 0:
            item = reader.recv(remaining)
            if item is not None and isinstance(item.msg, ParamState):
                found[topics[item.topic]] = item.msg
    return found


def _sendable(value: Any, name: str) -> Any:
    """`value` of param `name` as a message carries it: numpy scalars and arrays (within lists, tuples and dicts
    too) as their Python values (a np.float32 threshold ended `set_param` in msgpack's TypeError); ParamError
    naming the param for an integer past 64 bits (msgpack's bare OverflowError)."""
    if isinstance(value, (np.generic, np.ndarray)):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        return [_sendable(item, name) for item in value]
    if isinstance(value, dict):
        return {key: _sendable(item, name) for key, item in value.items()}
    if isinstance(value, int) and not -2**63 <= value < 2**64:
        raise ParamError(f"param {name!r}: {value} does not fit the 64-bit integers a message carries", name)
    return value


def set_params(node: str, values: dict[str, Any], timeout_s: float = ANSWER_TIMEOUT_S,
               address: BusAddress | None = None) -> ParamState:
    """Ask the running node `node` (its name or path, `param_topics`) to set `values` ({name: value}) and wait
    for its answer: its new `ParamState` when accepted; ParamError with the node's reason when refused;
    TimeoutError when the node (or the bus) does not answer within `timeout_s` s."""
    address = address or bus_address()
    set_topic, state_topic = param_topics(node)
    check_timeout(timeout_s)  # 0, negative and NaN answered "did not answer within nan s" at once
    unnamed = [name for name in values if not isinstance(name, str)]
    if unnamed:  # the node dropped the request as malformed, and this waited its whole timeout
        raise ParamError(f"param name {unnamed[0]!r} is not text", None)
    values = {name: _sendable(value, name) for name, value in values.items()}
    request_id = uuid.uuid4().hex
    deadline = time.monotonic() + timeout_s
    with TopicReader([state_topic], address) as reader:
        sock = PublisherSocket(f"fv_param_{uuid.uuid4().hex[:8]}", address)
        try:
            if reader.recv(timeout_s) is None:  # its latched state: the node runs
                raise _silent(node, state_topic, timeout_s, address)
            while not sock.has_subscribers(set_topic):  # its subscription reached the forwarder
                if time.monotonic() > deadline:
                    raise _silent(node, set_topic, timeout_s, address)
                time.sleep(POLL_S)
            sock.publish(set_topic, ParamSet(stamp_ns=time.time_ns(), request_id=request_id, values=values))
            while (remaining := deadline - time.monotonic()) > 0:
                item = reader.recv(remaining)
                if item is not None and isinstance(item.msg, ParamState) and item.msg.request_id == request_id:
                    if not item.msg.accepted:
                        raise ParamError(item.msg.error)
                    return item.msg
            raise TimeoutError(f"node {node!r} did not answer the request within {timeout_s:g} s")
        finally:
            sock.close()
