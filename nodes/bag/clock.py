"""`PlayClock`: when each recorded message is due during playback, with pause/resume."""
from __future__ import annotations

import threading
import time
from typing import Callable

STOP_CHECK_S = 0.1


class PlayClock:
    """Maps bag log time to monotonic time: due = origin + (bag_ns - bag0_ns) / rate.

    Time spent paused shifts the origin, so playback resumes where it stopped, and is summed in
    `paused_s`. Thread-safe: `toggle_pause()` may come from a signal handler or a keyboard thread.
    """

    def __init__(self, rate: float, paused: bool = False) -> None:
        if rate <= 0:
            raise ValueError(f"rate {rate} must be > 0")
        self.rate = rate
        self._cond = threading.Condition()
        self._paused = paused
        self._paused_at = time.monotonic()
        self._origin = time.monotonic()
        self._bag0_ns = 0
        self._pause_began = self._paused_at
        self._paused_total_s = 0.0

    @property
    def paused(self) -> bool:
        return self._paused

    @property
    def paused_s(self) -> float:
        """Seconds spent paused since this clock was made, the current pause included."""
        with self._cond:
            return self._paused_total_s + (time.monotonic() - self._pause_began if self._paused else 0.0)

    def start(self, bag0_ns: int) -> None:
        """Bag time `bag0_ns` is due now (or at resume when paused)."""
        with self._cond:
            self._bag0_ns = bag0_ns
            self._origin = self._paused_at = time.monotonic()

    def toggle_pause(self) -> bool:
        """Pause or resume; returns True when now paused."""
        with self._cond:
            now = time.monotonic()
            if self._paused:
                self._origin += now - self._paused_at
                self._paused_total_s += now - self._pause_began
            else:
                self._paused_at = self._pause_began = now
            self._paused = not self._paused
            self._cond.notify_all()
            return self._paused

    def wait(self, bag_ns: int | None, stopped: Callable[[], bool]) -> bool:
        """Block until bag time `bag_ns` is due (None: only while paused); False when
        `stopped()` turned true first (checked every STOP_CHECK_S)."""
        with self._cond:
            while not stopped():
                if self._paused:
                    self._cond.wait(STOP_CHECK_S)
                    continue
                if bag_ns is None:
                    return True
                remaining = self._origin + (bag_ns - self._bag0_ns) / 1e9 / self.rate - time.monotonic()
                if remaining <= 0:
                    return True
                self._cond.wait(min(remaining, STOP_CHECK_S))
            return False
