"""Headless Chromium driven over the DevTools protocol on a pipe (`--remote-debugging-pipe`): the
page runs in real time and the test reads it when it is ready, with a deadline on every step.

Chromium's one-shot modes (`--dump-dom` / `--screenshot` with `--virtual-time-budget`) now and
then never exit on a busy 2-core machine (three hangs in a row failed a CI run), and without a
virtual-time budget they dump the page at its load event, before it has polled anything."""
from __future__ import annotations

import base64
import fcntl
import json
import os
import select
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any, Callable

import pytest

from tests.nodes.conftest import kill_group

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"


class BrowserTimeout(AssertionError):
    """A DevTools reply or a page condition did not come within its deadline."""


class HeadlessChromium:
    """One headless Chromium with one page; use as a context manager (every process it starts is
    killed on exit). Messages are JSON, each ended by a NUL byte: written to the browser's fd 3,
    read from its fd 4."""

    def __init__(self, profile: Path, width: int = 1280, height: int = 800, timeout_s: float = 20.0) -> None:
        if not Path(CHROMIUM).exists():
            pytest.skip("headless Chromium not found (apt-get install chromium)")
        self.timeout_s = timeout_s
        to_browser, self._to_browser = os.pipe()
        self._from_browser, from_browser = os.pipe()
        args = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--disable-dev-shm-usage", "--remote-debugging-pipe", f"--user-data-dir={profile}",
                f"--window-size={width},{height}", "about:blank"]

        def onto_fds_3_and_4() -> None:  # in the child, before exec: where Chromium looks for its pipe
            high = [fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (to_browser, from_browser)]
            for fd, target in zip(high, (3, 4)):
                os.dup2(fd, target)

        self.proc = subprocess.Popen(args, pass_fds=(3, 4), preexec_fn=onto_fds_3_and_4, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL, start_new_session=True)
        os.close(to_browser)
        os.close(from_browser)
        self._buffer = b""
        self._next_id = 0
        self._session = ""
        self._size = (width, height)

    def __enter__(self) -> HeadlessChromium:
        return self

    def __exit__(self, *exc: object) -> None:
        kill_group(self.proc, 0.5)
        os.close(self._to_browser)
        os.close(self._from_browser)

    def call(self, method: str, session: bool = True, **params: Any) -> dict:
        """Send one DevTools command (to the open page when `session`) and return its result."""
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params}
        if session and self._session:
            message["sessionId"] = self._session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + self.timeout_s
        while True:
            reply = self._read(deadline, method)
            if reply.get("id") != self._next_id:
                continue  # an event, or a reply to nothing we wait for
            if "error" in reply:
                raise AssertionError(f"DevTools {method}: {reply['error']}")
            return reply["result"]

    def _read(self, deadline: float, what: str) -> dict:
        """The next NUL-ended message from the browser, or BrowserTimeout at `deadline`."""
        while b"\0" not in self._buffer:
            left = deadline - time.monotonic()
            ready, _, _ = select.select([self._from_browser], [], [], max(left, 0.0))
            if not ready:
                raise BrowserTimeout(f"no DevTools reply to {what} within {self.timeout_s} s")
            chunk = os.read(self._from_browser, 1 << 16)
            if not chunk:
                raise AssertionError(f"Chromium closed its DevTools pipe during {what} "
                                     f"(exit code {self.proc.poll()})")
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def open(self, url: str) -> None:
        """Open `url` in a new page of the browser's window size; later calls go to that page."""
        target = self.call("Target.createTarget", session=False, url="about:blank")["targetId"]
        self._session = self.call("Target.attachToTarget", session=False, targetId=target, flatten=True)["sessionId"]
        width, height = self._size
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)
        self.call("Page.navigate", url=url)

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (JSON-serialisable values only)."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        if "exceptionDetails" in result:
            raise AssertionError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def wait_for(self, expression: str, ready: Callable[[Any], bool]) -> Any:
        """Evaluate `expression` every 0.1 s until `ready(value)`; that value, or BrowserTimeout."""
        deadline = time.monotonic() + self.timeout_s
        while True:
            value = self.evaluate(expression)
            if ready(value):
                return value
            if time.monotonic() > deadline:
                raise BrowserTimeout(f"{expression} never became ready within {self.timeout_s} s: last {value!r}")
            time.sleep(0.1)

    def screenshot(self) -> bytes:
        """A PNG of the page at the window size."""
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
