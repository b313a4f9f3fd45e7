"""The `viewer` node: a live web page (default http://127.0.0.1:8765/) showing the camera
frame with the tracked markers and their displacement arrows, the displacement field as a
colour map with direction arrows, the slip probability over time, field and contact
figures, and every node's rate from `/status`.

The node keeps only the latest message of each topic (keep-last queues: a slow browser
never slows the pipeline). Pictures are drawn and encoded in the HTTP server's threads,
and only when a page asks for one and something new arrived since the last encoding.

Routes: ``/`` the page (`viewer_page.html`), ``/state.json`` (everything but the
pictures), ``/frame.jpg`` (frame + markers) and ``/field.jpg`` (field colour map). The
page polls ``/state.json`` `rate_hz` times a second and fetches a picture only when its
sequence number in the state changed.
"""
from __future__ import annotations

import collections
import errno
import ipaddress
import json
import threading
import time
from dataclasses import dataclass
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, Callable
from urllib.parse import urlsplit

import cv2
import numpy as np

from fv_algos.visualize import SlipHistory, draw_markers, render_field
from msgs import ContactSummary, DisplacementField, Image, MarkerArray, NodeStatus, SlipState
from nodes.node import Node

PAGE_FILE = Path(__file__).with_name("viewer_page.html")
IMAGE_BUFFER = 16  # recent frames kept so the markers are drawn on the frame they were found in
STATUS_QUEUE = 64  # /status comes from every node: keep-last 1 would drop other nodes' reports


@dataclass
class ViewerParams:
    host: str = "127.0.0.1"  # interface to serve on; the page has no login, so keep it local
    port: int = 8765  # TCP port; 0 = any free port (logged, and in NodeStatus counters["port"])
    rate_hz: float = 10.0  # page updates per second
    history_s: float = 20.0  # time span of the slip probability plot in s
    arrow_scale: float = 3.0  # marker arrow length per px of displacement
    field_range_px: float = 0.0  # top of the field colour scale in px; 0 = auto (at least 1 px)
    view_height_px: int = 480  # pictures are drawn at least this tall (small frames are zoomed)
    jpeg_quality: int = 85  # 1..100
    stale_s: float = 3.0  # a node silent on /status this long is shown as stale (dropped after 10x); so is /slip

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port {self.port} is not in 0..65535 (0 = any free port)")
        if not self.host.strip():  # it served on every interface, saying "live view on http://:PORT/"
            raise ValueError("host is empty: give an address (127.0.0.1 for this machine alone, 0.0.0.0 for every "
                             "interface)")
        if not 0.1 <= self.rate_hz <= 60:  # the page waits 1 / rate_hz s: 1e-9 overflowed its timer, polling flat out
            raise ValueError(f"rate_hz {self.rate_hz} is not in 0.1..60 (page updates per second)")
        for name in ("history_s", "arrow_scale", "stale_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} {getattr(self, name)} must be > 0")
        if self.field_range_px < 0:
            raise ValueError(f"field_range_px {self.field_range_px} must be >= 0 (0 = auto)")
        if not 64 <= self.view_height_px <= 2160:
            raise ValueError(f"view_height_px {self.view_height_px} is not in 64..2160")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality {self.jpeg_quality} is not in 1..100")


class _Encoded:
    """The last picture encoded for the clients, re-drawn only when its source changed."""

    def __init__(self) -> None:
        self._lock = threading.Lock()  # two clients asking at once: one draws, the other reuses
        self._key: Any = None
        self._data = b""

    def get(self, key: Any, render: Callable[[], bytes]) -> tuple[bytes, bool]:
        """(picture bytes, True when it was encoded for this call)."""
        with self._lock:
            if key == self._key:
                return self._data, False
            self._data, self._key = render(), key
            return self._data, True


def frame_picture(image: Image, markers: MarkerArray | None, arrow_scale: float, zoom: float,
                  legend: bool = True) -> np.ndarray:
    """The camera frame zoomed `zoom` times with the markers' displacement arrows
    (`fv_algos.visualize.draw_markers`); without markers when `markers` is None or was
    found in an image of another size. Returns (H * zoom, W * zoom, 3) uint8 BGR."""
    if markers is None or (markers.width, markers.height) not in ((image.width, image.height), (0, 0)):
        empty = np.zeros((0, 2))
        return draw_markers(image.data, empty, empty, zoom=zoom, encoding=image.encoding, legend=False)
    return draw_markers(image.data, markers.ref_px, markers.cur_px, markers.valid, arrow_scale=arrow_scale,
                        zoom=zoom, encoding=image.encoding, legend=legend)


def field_picture(field: DisplacementField, range_px: float, height_px: int, width_px: int = 0) -> np.ndarray:
    """The field's magnitude colour map with direction arrows and colour bar
    (`fv_algos.visualize.render_field`); range_px 0 = auto. Returns (height_px, W, 3) uint8 BGR."""
    return render_field(field.field, field.grid_x_px, field.grid_y_px, valid=field.valid, range_px=range_px,
                        height_px=height_px, width_px=width_px)


def _jpeg(image: np.ndarray, quality: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError(f"JPEG encoding of a {image.shape} image failed")
    return buf.tobytes()


def _finite(value: float) -> float | None:
    """`value` for JSON: None when NaN or infinite."""
    return float(value) if np.isfinite(value) else None


class ViewerNode(Node):
    """Serves the live view; see the module docstring."""

    Params = ViewerParams
    # `fv param set`: read for each picture (from the next frame on) or page update (the page polls at rate_hz)
    LIVE_PARAMS = frozenset({"rate_hz", "arrow_scale", "field_range_px", "view_height_px", "jpeg_quality", "stale_s"})

    def setup(self) -> None:
        p = self.params
        self.page = PAGE_FILE.read_bytes()
        self._lock = threading.Lock()  # guards everything below, shared with the HTTP threads
        self._images: collections.deque[Image] = collections.deque(maxlen=IMAGE_BUFFER)
        self._markers: MarkerArray | None = None
        self._field: DisplacementField | None = None
        self._contact: ContactSummary | None = None
        self._slip: SlipState | None = None
        self._slip_seen_s = 0.0  # when the latest /slip message came (monotonic s)
        self._slip_t0_ns = 0
        self._history = SlipHistory(p.history_s)
        self._statuses: dict[str, tuple[float, NodeStatus]] = {}
        self._frame_seq = 0
        self._field_seq = 0
        self._frame_jpeg = _Encoded()
        self._field_jpeg = _Encoded()
        self.counters.update(port=0, requests=0, frames_encoded=0, fields_encoded=0, client_errors=0)
        self.subscribe("camera/image", Image, self.on_image, depth=1)
        self.subscribe("markers", MarkerArray, self.on_markers, depth=1)
        self.subscribe("field", DisplacementField, self.on_field, depth=1)
        self.subscribe("contact", ContactSummary, self.on_contact, depth=1)
        self.subscribe("slip", SlipState, self.on_slip, depth=1)
        self.subscribe("/status", NodeStatus, self.on_status, depth=STATUS_QUEUE)
        self.server = self._serve()

    def _serve(self) -> _Server:
        host, port = self.params.host, self.params.port
        try:
            server = _Server((host, port), self)
        except OSError as exc:
            advice = ("choose another port (port:=0 in a launch, -p port=0 for fv node: any free one)"
                      if exc.errno == errno.EADDRINUSE else "check the host: an address of this machine")
            raise RuntimeError(f"viewer cannot listen on {host}:{port} ({exc.strerror or exc}); {advice}") from None
        self.port = int(server.server_address[1])
        self.counters["port"] = self.port
        threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.2}, name=f"{self.name}-http",
                         daemon=True).start()
        self.log.info("live view on http://%s:%d/", host if ":" not in host else f"[{host}]", self.port)
        if not _is_loopback(host):
            self.log.warning("serving on %s: anyone who can reach this host sees the page (it has no login)", host)
        return server

    def teardown(self) -> None:
        server: _Server | None = getattr(self, "server", None)
        if server is not None:
            server.shutdown()
            server.server_close()

    # -- subscriptions (executor thread): store the latest, nothing more ----------
    def on_image(self, msg: Image) -> None:
        with self._lock:
            self._images.append(msg)
            self._frame_seq += 1

    def on_markers(self, msg: MarkerArray) -> None:
        with self._lock:
            self._markers = msg
            self._frame_seq += 1

    def on_field(self, msg: DisplacementField) -> None:
        with self._lock:
            self._field = msg
            self._field_seq += 1

    def on_contact(self, msg: ContactSummary) -> None:
        with self._lock:
            self._contact = msg

    def on_slip(self, msg: SlipState) -> None:
        with self._lock:
            self._slip = msg
            self._slip_seen_s = time.monotonic()
            self._slip_t0_ns = self._slip_t0_ns or msg.stamp_ns
            self._history.add((msg.stamp_ns - self._slip_t0_ns) / 1e9, msg.probability, msg.slip)

    def on_status(self, msg: NodeStatus) -> None:
        with self._lock:
            self._statuses[msg.node] = (time.monotonic(), msg)

    # -- pictures and state (HTTP threads) -----------------------------------------
    def _frame_pair(self) -> tuple[int, Image | None, MarkerArray | None]:
        """(frame seq, frame, its markers): the frame the latest markers were found in
        when it is still buffered, else the latest frame without markers."""
        with self._lock:
            seq, markers = self._frame_seq, self._markers
            images = list(self._images)
        if not images:
            return seq, None, None
        if markers is not None:
            for image in reversed(images):
                if image.stamp_ns == markers.stamp_ns:
                    return seq, image, markers
        return seq, images[-1], None

    def frame_jpeg(self) -> bytes | None:
        """JPEG of the latest tracked frame with its markers; None before any frame."""
        seq, image, markers = self._frame_pair()
        if image is None:
            return None
        p = self.params

        def render() -> bytes:
            zoom = max(1.0, p.view_height_px / max(image.height, 1))  # small frames zoomed, never shrunk
            picture = frame_picture(image, markers, p.arrow_scale, zoom, legend=False)  # the page writes it
            return _jpeg(picture, p.jpeg_quality)

        data, fresh = self._frame_jpeg.get(seq, render)
        self.counters["frames_encoded"] += fresh
        return data

    def field_jpeg(self) -> bytes | None:
        """JPEG of the latest field's colour map; None before any field."""
        with self._lock:
            seq, field = self._field_seq, self._field
        if field is None:
            return None
        p = self.params

        def render() -> bytes:
            return _jpeg(field_picture(field, p.field_range_px, p.view_height_px), p.jpeg_quality)

        data, fresh = self._field_jpeg.get(seq, render)
        self.counters["fields_encoded"] += fresh
        return data

    def page_state(self) -> dict[str, Any]:
        """Everything the page shows but the pictures, JSON-ready."""
        p = self.params
        now = time.monotonic()
        with self._lock:
            for name in [n for n, (seen, _) in self._statuses.items() if now - seen > 10 * p.stale_s]:
                del self._statuses[name]
            images, markers, field = list(self._images), self._markers, self._field
            contact, slip, frame_seq, field_seq = self._contact, self._slip, self._frame_seq, self._field_seq
            slip_age_s = now - self._slip_seen_s
            samples = self._history.samples()
            statuses = list(self._statuses.values())
        return {
            "node": self.name, "bus": self.address.url,
            "config": {"rate_hz": p.rate_hz, "history_s": p.history_s, "arrow_scale": p.arrow_scale},
            "frame": _frame_state(frame_seq, images[-1], markers) if images else None,
            "field": _field_state(field_seq, field) if field is not None else None,
            "contact": _contact_state(contact) if contact is not None else None,
            "slip": _slip_state(slip, samples, slip_age_s, p.stale_s) if slip is not None else None,
            "nodes": [_node_state(st, now - seen, p.stale_s) for seen, st in statuses],
        }


def _frame_state(seq: int, image: Image, markers: MarkerArray | None) -> dict[str, Any]:
    out = {"seq": seq, "stamp_ns": image.stamp_ns, "width": image.width, "height": image.height,
           "encoding": image.encoding, "markers": None}
    if markers is not None:
        out["markers"] = {"tracked": int(np.count_nonzero(markers.valid)), "total": int(len(markers.valid))}
    return out


def _field_state(seq: int, msg: DisplacementField) -> dict[str, Any]:
    mag = np.asarray(msg.field[..., 2], np.float64)
    finite = mag[np.isfinite(mag)]
    return {"seq": seq, "stamp_ns": msg.stamp_ns, "rows": int(mag.shape[0]), "cols": int(mag.shape[1]),
            "valid": bool(msg.valid), "max_px": _finite(finite.max()) if finite.size else None,
            "mean_px": _finite(finite.mean()) if finite.size else None, "markers_used": msg.n_markers_used,
            "markers": msg.n_markers, "method": msg.method, "units": msg.units}


def _contact_state(msg: ContactSummary) -> dict[str, Any]:
    return {"in_contact": bool(msg.in_contact), "area_share": _finite(msg.area_share),
            "centre_px": [_finite(msg.centre_x_px), _finite(msg.centre_y_px)],
            "shear_px": [_finite(msg.shear_x_px), _finite(msg.shear_y_px)],
            "rotation_rad": _finite(msg.rotation_rad), "divergence": _finite(msg.divergence)}


def _slip_state(msg: SlipState, samples: list[tuple[float, float, bool]], age_s: float,
                stale_s: float) -> dict[str, Any]:
    """The latest decision, its plot's samples, and how old it is (`age_s`: s since it came): `stale` when
    none came for `stale_s` s (the page said "SLIP p=1.00" in red for good after the slip detector had gone)."""
    return {"probability": float(msg.probability), "slip": bool(msg.slip), "valid": bool(msg.valid),
            "age_s": round(age_s, 2), "stale": age_s > stale_s,
            "threshold": float(msg.threshold), "model": msg.model,
            "latency_ms": (msg.pub_ns - msg.stamp_ns) / 1e6 if msg.pub_ns and msg.stamp_ns else None,
            "t_s": [round(t, 4) for t, _, _ in samples], "p": [round(q, 4) for _, q, _ in samples],
            "decision": [int(s) for _, _, s in samples]}


def _node_state(st: NodeStatus, age_s: float, stale_s: float) -> dict[str, Any]:
    return {"name": st.node, "state": "stale" if age_s > stale_s else st.state, "message": st.message,
            "rate_hz": _finite(st.rate_hz), "proc_ms_mean": _finite(st.proc_ms_mean),
            "proc_ms_p99": _finite(st.proc_ms_p99), "cpu_percent": _finite(st.cpu_percent), "drops": st.drops,
            "gaps": st.gaps, "errors": st.errors, "rss_mb": st.rss_bytes / 1e6, "age_s": round(age_s, 2)}


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class _Server(ThreadingHTTPServer):
    """The viewer's HTTP server: one daemon thread per connection."""

    daemon_threads = True

    def __init__(self, address: tuple[str, int], viewer: ViewerNode) -> None:
        self.viewer = viewer
        super().__init__(address, _Handler)

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A connection that failed outside a request (reset while sending one): counted."""
        self.viewer.counters["client_errors"] += 1
        self.viewer.log.debug("connection from %s failed", client_address, exc_info=True)


class _Handler(BaseHTTPRequestHandler):
    """One HTTP connection of the viewer (keep-alive, so a polling page reuses it)."""

    protocol_version = "HTTP/1.1"
    server_version = "fv-viewer"
    server: _Server

    def do_GET(self) -> None:  # noqa: N802 (the http.server name)
        viewer = self.server.viewer
        viewer.counters["requests"] += 1
        path = urlsplit(self.path).path
        try:
            asked = urlsplit("//" + (self.headers.get("Host") or "")).hostname or ""
            if _is_loopback(viewer.params.host) and not _is_loopback(asked):
                # DNS rebinding: a web page of another site whose name resolves to 127.0.0.1 may not read this one
                self._send(HTTPStatus.FORBIDDEN, "text/plain", f"Host {asked!r} is not this machine\n".encode())
            elif path in ("/", "/index.html"):
                self._send(HTTPStatus.OK, "text/html; charset=utf-8", viewer.page)
            elif path == "/state.json":
                body = json.dumps(viewer.page_state(), separators=(",", ":"), allow_nan=False).encode()
                self._send(HTTPStatus.OK, "application/json", body)
            elif path in ("/frame.jpg", "/field.jpg"):
                data = viewer.frame_jpeg() if path == "/frame.jpg" else viewer.field_jpeg()
                if data is None:
                    topic = viewer.resolve("camera/image" if path == "/frame.jpg" else "field")
                    self._send(HTTPStatus.NOT_FOUND, "text/plain", f"no {topic} message yet\n".encode())
                else:
                    self._send(HTTPStatus.OK, "image/jpeg", data)
            else:
                self._send(HTTPStatus.NOT_FOUND, "text/plain", f"no such page: {path}\n".encode())
        except (BrokenPipeError, ConnectionResetError):
            viewer.counters["client_errors"] += 1  # the client went away mid-answer
            self.close_connection = True
        except Exception as exc:  # a bad message must not take the page down
            viewer.warn(f"{path}: {type(exc).__name__}: {exc}")
            try:
                self._send(HTTPStatus.INTERNAL_SERVER_ERROR, "text/plain", f"{type(exc).__name__}: {exc}\n".encode())
            except OSError:
                self.close_connection = True

    _head_only = False  # answering HEAD: headers only (one handler serves a keep-alive connection's requests)

    def do_HEAD(self) -> None:  # noqa: N802: what GET would answer, without the body (HTTP requires it)
        self._head_only = True
        try:
            self.do_GET()
        finally:
            self._head_only = False

    def _refuse_method(self) -> None:
        self.send_response(HTTPStatus.METHOD_NOT_ALLOWED)  # the page is read only
        self.send_header("Allow", "GET, HEAD")
        self.send_header("Content-Length", "0")
        self._end_headers()

    def _end_headers(self) -> None:
        """End the answer's headers; close the connection after it when the request came with a body.
        The viewer reads none, and a body left on a kept-alive connection was read as the next request:
        a page of another site POSTed one holding `GET /state.json` with a loopback Host, and had 200."""
        if self.headers.get("Content-Length", "0").strip() != "0" or "Transfer-Encoding" in self.headers:
            self.send_header("Connection", "close")  # (sets close_connection)
        self.end_headers()

    do_POST = do_PUT = do_DELETE = do_PATCH = _refuse_method  # noqa: N815 (the http.server names)

    def _send(self, status: HTTPStatus, content_type: str, body: bytes) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self._end_headers()
        if not self._head_only:
            self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (the http.server signature)
        self.server.viewer.log.debug("%s %s", self.address_string(), format % args)
