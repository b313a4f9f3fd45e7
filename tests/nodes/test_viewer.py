"""The `viewer` node: state and pictures over HTTP from synthetic messages, encoding only
on demand, clients that vanish, a clear error for a taken port, its launch file, and the
page itself in headless Chromium (loads, shows a frame, the slip plot moves)."""
from __future__ import annotations

import json
import math
import re
import socket
import struct
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np
import pytest

from fv_algos.visualize import ARROW
from msgs import ContactSummary, DisplacementField, Image, MarkerArray, Message, SlipState
from nodes.bus import PublisherSocket
from nodes.launch_file import load_launch
from nodes.viewer import ViewerNode, ViewerParams
from tests.nodes.conftest import REPO, Bus, poll_until, wait_for
from tests.nodes.headless_browser import HeadlessChromium

T0_NS = 1_700_000_000_000_000_000
FRAME_NS = 33_000_000


def synthetic(k: int, probability: float) -> list[tuple[str, Message]]:
    """Frame k of a fake pipeline: a 120x160 grey image with 6x8 dark markers moving
    0.5 px right per frame (back to the start every 20 frames), its markers, a 30x30 field
    bump 0.1 px higher per frame, and a slip state."""
    stamp = T0_NS + k * FRAME_NS
    xs, ys = np.meshgrid(10 + 20 * np.arange(8), 10 + 20 * np.arange(6))
    ref = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float32)
    cur = ref + np.float32([0.5 * (k % 20), 0.0])
    image = np.full((120, 160), 170, np.uint8)
    for x, y in cur:
        cv2.circle(image, (int(x), int(y)), 3, 40, -1)
    yy, xx = np.mgrid[0:30, 0:30]
    mag = 0.1 * (k % 20) * np.exp(-((xx - 15) ** 2 + (yy - 15) ** 2) / 40.0)
    field = np.stack([mag, 0 * mag, mag], axis=-1).astype(np.float32)
    n = len(ref)
    return [
        ("/camera/image", Image(stamp_ns=stamp, data=image)),
        ("/markers", MarkerArray(stamp_ns=stamp, ref_px=ref, cur_px=cur, valid=np.ones(n, bool),
                                 frames_since_seen=np.zeros(n, np.int32), width=160, height=120)),
        ("/field", DisplacementField(stamp_ns=stamp, field=field, grid_x_px=np.linspace(10, 150, 30),
                                     grid_y_px=np.linspace(10, 110, 30), n_markers_used=n, n_markers=n,
                                     method="synthetic")),
        ("/contact", ContactSummary(stamp_ns=stamp, in_contact=k > 2, area_share=0.1, shear_x_px=0.05 * k)),
        ("/slip", SlipState(stamp_ns=stamp, probability=probability, slip=probability > 0.5)),
    ]


@pytest.fixture
def viewer(bus: Bus) -> Iterator[ViewerNode]:
    """A viewer node on the test bus, spinning in a thread, on a free port. Its plot spans 600 s: with the
    default 20 s, a Chromium slow to start (23 s to its first snapshot, once) saw the window full twice, the
    same number of points, and the page test failed though the plot had moved on."""
    node = ViewerNode("viewer", {"port": 0, "rate_hz": 20.0, "history_s": 600.0})
    thread = threading.Thread(target=node.spin, kwargs={"install_signals": False}, daemon=True)
    thread.start()
    wait_for(lambda: getattr(node, "port", 0) or not thread.is_alive(), 5.0, "the viewer's start", period_s=0.02)
    assert getattr(node, "port", 0), "viewer did not start"
    yield node
    node.stop()
    thread.join(5.0)
    assert not thread.is_alive()


@pytest.fixture
def pipeline(bus: Bus, viewer: ViewerNode) -> Iterator[PublisherSocket]:
    """A publisher standing in for the pipeline, connected once the viewer's
    subscriptions reached it (no message lost to the slow joiner)."""
    pub = PublisherSocket("fake_pipeline", bus.address)
    assert pub.wait_connected(2.0)
    wait_for(lambda: all(pub.has_subscribers(t) for t in ("/camera/image", "/markers", "/field", "/slip")), 5.0,
             "the viewer's subscriptions", period_s=0.02)
    yield pub
    pub.close()


def publish_frame(pub: PublisherSocket, k: int, probability: float) -> None:
    for topic, msg in synthetic(k, probability):
        pub.publish(topic, msg)
        time.sleep(0.002)  # let the viewer take each one (its queues keep the latest only)


def get(viewer: ViewerNode, path: str) -> tuple[int, str, bytes]:
    """(status, content type, body) of GET `path` on the viewer."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{viewer.port}{path}", timeout=5) as r:
            return r.status, r.headers["Content-Type"], r.read()
    except urllib.error.HTTPError as err:
        return err.code, err.headers["Content-Type"], err.read()


def wait_state(viewer: ViewerNode, predicate, timeout_s: float = 5.0) -> dict:
    last: dict[str, dict] = {}

    def matched() -> bool:
        last["state"] = json.loads(get(viewer, "/state.json")[2])
        return predicate(last["state"])

    assert poll_until(matched, timeout_s, period_s=0.05), f"state never matched: {last['state']}"
    return last["state"]


def test_viewer_serves_the_page_state_and_pictures(viewer: ViewerNode, pipeline: PublisherSocket) -> None:
    assert get(viewer, "/frame.jpg")[0] == 404 and get(viewer, "/field.jpg")[0] == 404
    status, kind, page = get(viewer, "/")
    assert status == 200 and kind.startswith("text/html") and b"FingerVision live view" in page
    assert get(viewer, "/nothing")[0] == 404
    for k in range(10):
        publish_frame(pipeline, k, k / 10)
    state = wait_state(viewer, lambda s: s["slip"] is not None and len(s["slip"]["t_s"]) == 10
                       and s["frame"] is not None and s["frame"]["markers"] is not None and s["field"] is not None
                       and "viewer" in [n["name"] for n in s["nodes"]])
    assert state["frame"]["width"] == 160 and state["frame"]["markers"] == {"tracked": 48, "total": 48}
    field = state["field"]
    assert (field["rows"], field["cols"], field["valid"], field["method"]) == (30, 30, True, "synthetic")
    assert field["max_px"] == pytest.approx(0.9, abs=1e-3)
    slip = state["slip"]
    assert slip["p"] == pytest.approx([k / 10 for k in range(10)])
    assert slip["t_s"] == pytest.approx([k * FRAME_NS / 1e9 for k in range(10)])
    assert slip["decision"] == [0] * 6 + [1] * 4 and slip["slip"] is True
    assert state["contact"]["in_contact"] is True
    assert state["config"]["rate_hz"] == 20.0
    own = next(n for n in state["nodes"] if n["name"] == "viewer")
    assert own["state"] == "ok" and own["rate_hz"] is not None

    status, kind, data = get(viewer, "/frame.jpg")
    frame = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert status == 200 and kind == "image/jpeg" and frame.shape == (480, 640, 3)  # 120x160 zoomed to 480 tall
    arrows = np.all(np.abs(frame.astype(int) - np.array(ARROW)) < 50, axis=2)
    assert arrows.sum() > 500  # 48 markers moved 4.5 px: 54 px arrows at scale 3, zoom 4
    field_jpg = cv2.imdecode(np.frombuffer(get(viewer, "/field.jpg")[2], np.uint8), cv2.IMREAD_COLOR)
    assert field_jpg.shape[0] == 480

    encoded = viewer.counters["frames_encoded"]
    get(viewer, "/frame.jpg")
    assert viewer.counters["frames_encoded"] == encoded  # nothing new: the same JPEG again
    publish_frame(pipeline, 10, 0.2)
    wait_state(viewer, lambda s: len(s["slip"]["t_s"]) == 11)
    get(viewer, "/frame.jpg")
    assert viewer.counters["frames_encoded"] == encoded + 1
    assert viewer.counters["port"] == viewer.port


def test_a_slip_decision_that_stops_coming_is_shown_stale(viewer: ViewerNode, pipeline: PublisherSocket) -> None:
    """After the pipeline stopped, the page's badge said "SLIP p=0.90" in red for good: the state gave
    the last decision with no age."""
    viewer.params.stale_s = 60.0  # fresh however slow the machine
    publish_frame(pipeline, 0, 0.9)
    state = wait_state(viewer, lambda s: s["slip"] is not None)
    assert state["slip"]["stale"] is False and state["slip"]["slip"] is True and state["slip"]["age_s"] < 60.0
    viewer.params.stale_s = 0.3
    state = wait_state(viewer, lambda s: s["slip"]["stale"])
    assert state["slip"]["age_s"] >= 0.3 and state["slip"]["probability"] == pytest.approx(0.9)  # (to 0.01 s)
    viewer.params.stale_s = 60.0
    sent_s = time.monotonic()
    publish_frame(pipeline, 1, 0.1)
    state = wait_state(viewer, lambda s: s["slip"]["probability"] == pytest.approx(0.1))
    assert state["slip"]["stale"] is False  # a new decision is fresh again: aged from its own arrival
    assert state["slip"]["age_s"] <= time.monotonic() - sent_s + 0.01


def _abort(sock: socket.socket) -> None:
    """Close with a TCP reset, as a crashed browser tab would."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()


def test_viewer_survives_clients_that_go_away(viewer: ViewerNode, pipeline: PublisherSocket) -> None:
    publish_frame(pipeline, 3, 0.5)
    wait_state(viewer, lambda s: s["frame"] is not None)
    for request in (b"GET /frame.jpg HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n", b"GET /sta", b"", b"NONSENSE\r\n\r\n"):
        sock = socket.create_connection(("127.0.0.1", viewer.port), timeout=2)
        sock.sendall(request)
        _abort(sock)
    with socket.create_connection(("127.0.0.1", viewer.port), timeout=2) as sock:
        sock.sendall(b"GET /frame.jpg HTTP/1.1\r\nHost: localhost\r\n\r\n")
        assert sock.recv(64).startswith(b"HTTP/1.1 200")
    status, _, body = get(viewer, "/state.json")
    assert status == 200 and json.loads(body)["frame"] is not None


def test_head_answers_as_get_without_a_body_and_writes_are_refused(viewer: ViewerNode) -> None:
    """HEAD and POST were answered 501 (HEAD is required of a server, a write to a read-only page is 405)."""
    import http.client
    conn = http.client.HTTPConnection("127.0.0.1", viewer.port, timeout=5)
    for method, status in (("HEAD", 200), ("POST", 405), ("GET", 200), ("DELETE", 405)):  # one kept-alive connection
        conn.request(method, "/state.json")
        response = conn.getresponse()
        body = response.read()
        assert response.status == status, method
        if method == "HEAD":
            assert body == b"" and int(response.headers["Content-Length"]) > 0
        if method == "GET":
            assert "frame" in json.loads(body)  # the body comes whole after a HEAD on the same connection
        if status == 405:
            assert response.headers["Allow"] == "GET, HEAD"
    conn.close()


def test_a_request_body_is_never_read_as_the_next_request(viewer: ViewerNode) -> None:
    """The viewer reads no body: a POST's, left on the kept-alive connection, was parsed as the next
    request, so a page of another site (403 for its own GETs) smuggled in a GET with a loopback Host and
    was answered 200. Now the connection closes after the answer to a request with a body."""
    inner = b"GET /state.json HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"
    for method in (b"POST", b"GET"):
        with socket.create_connection(("127.0.0.1", viewer.port), timeout=5) as sock:
            sock.sendall(method + b" / HTTP/1.1\r\nHost: evil.example\r\nContent-Length: %d\r\n\r\n" % len(inner)
                         + inner)
            data = b""
            while chunk := sock.recv(65536):  # the server closes the connection: recv returns b""
                data += chunk
        statuses = re.findall(rb"^HTTP/1.1 (\d+)", data, re.MULTILINE)
        assert statuses == [b"405" if method == b"POST" else b"403"], (method, statuses)


def test_a_page_of_another_site_cannot_read_the_local_viewer(viewer: ViewerNode) -> None:
    """DNS rebinding: a site whose name a browser resolves to 127.0.0.1 sends its own name as Host. The
    viewer, serving on loopback, answers only to loopback names (it answered any Host with 200)."""
    for host, status in ((b"evil.example", b"403"), (b"evil.example:%d", b"403"), (b"127.0.0.1:%d", b"200"),
                         (b"localhost:%d", b"200"), (b"[::1]:%d", b"200")):
        with socket.create_connection(("127.0.0.1", viewer.port), timeout=2) as sock:
            sock.sendall(b"GET /state.json HTTP/1.1\r\nHost: " + (host % viewer.port if b"%d" in host else host)
                         + b"\r\n\r\n")
            assert sock.recv(64).startswith(b"HTTP/1.1 " + status), host


def test_a_taken_port_is_a_clear_error(bus: Bus) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        node = ViewerNode("viewer", {"port": port})
        with pytest.raises(RuntimeError, match=f"cannot listen on 127.0.0.1:{port}.*port=0"):
            node.spin(install_signals=False)


@pytest.mark.parametrize("params", [{"port": 70000}, {"rate_hz": 0.0}, {"history_s": -1.0},
                                    {"rate_hz": 1e-9}, {"rate_hz": 1e3},  # 1e-9: the page's timer overflowed
                                    {"host": ""},  # it served on every interface, said as "http://:PORT/"
                                    {"field_range_px": -1.0}, {"jpeg_quality": 0}, {"view_height_px": 10}])
def test_bad_params_are_refused(params: dict) -> None:
    with pytest.raises(ValueError):
        ViewerParams(**params)


def test_view_launch_file_adds_the_viewer_to_the_pipeline() -> None:
    specs = load_launch(REPO / "launch" / "view.yaml", {"port": 0, "fps": 15.0})
    kinds = [s.kind for s in specs]
    assert kinds[-1] == "viewer" and {"camera", "tracker", "interpolator", "slip_detector"} <= set(kinds)
    assert specs[-1].params["port"] == 0
    assert next(s for s in specs if s.kind == "camera").params["fps"] == 15.0
    assert specs[-1].respawn and specs[-1].max_retries == 3  # a taken port: it respawned every second for good


# -- the page in a real browser ----------------------------------------------------------
PROGRESS = "JSON.stringify(Object.assign({}, document.body ? document.body.dataset : {}))"


def _progress(browser: HeadlessChromium, ready: Callable[[dict[str, str]], bool]) -> dict[str, str]:
    """The page's data-* progress attributes on <body> (as `dataset` names them: slipPoints ...) once
    `ready` holds for them."""
    return json.loads(browser.wait_for(PROGRESS, lambda text: ready(json.loads(text))))


def test_page_in_headless_chromium_shows_frames_and_a_moving_slip_plot(
        tmp_path: Path, viewer: ViewerNode, pipeline: PublisherSocket) -> None:
    stop = threading.Event()

    def run_pipeline() -> None:
        k = 0
        while not stop.is_set():
            publish_frame(pipeline, k, 0.5 + 0.45 * math.sin(k / 5))
            k += 1
            time.sleep(0.02)

    thread = threading.Thread(target=run_pipeline, daemon=True)
    thread.start()
    try:
        wait_state(viewer, lambda s: s["slip"] is not None and len(s["slip"]["t_s"]) >= 3)
        with HeadlessChromium(tmp_path / "profile") as browser:
            browser.open(f"http://127.0.0.1:{viewer.port}/")
            first = _progress(browser, lambda p: int(p.get("polls", 0)) >= 2 and int(p["slipPoints"]) >= 3
                              and int(p["framesShown"]) >= 1 and int(p["fieldsShown"]) >= 1)
            second = _progress(browser, lambda p: float(p["lastT"]) > float(first["lastT"])  # the plot moved on
                               and int(p["slipPoints"]) > int(first["slipPoints"]))
            shot = browser.screenshot()
    finally:
        stop.set()
        thread.join(2.0)
    assert int(second["polls"]) > int(first["polls"]), (first, second)
    picture = cv2.imdecode(np.frombuffer(shot, np.uint8), cv2.IMREAD_COLOR)
    assert picture is not None and picture.shape[:2] == (800, 1280)
    frame_area = picture[60:450, 10:450]
    assert frame_area.std() > 20  # a camera frame with markers, not an empty panel
