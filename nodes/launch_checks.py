"""Checks of node params that a launch has made already, so that its nodes do not make them again.

A costly check of a node's params (a simulated scene's mechanics: 0.5 to 2.4 s for 600 frames) runs in
the launcher when it reads the launch file, so that `fv launch --check` and the launch refuse a bad
input before anything starts, and it would run again in the node when the node builds its params, at
every start. The check notes what passed (`note_passed`) under a key that names the checked input by
its content; the launcher gives its nodes those keys (`env`, in `CHECKED_ENV`), and a node skips the
check of a key among them (`passed`): once per launch, a respawned node included. An input that has
changed since (a scene file edited while the launch runs) has another key, and is checked again."""
from __future__ import annotations

import os

CHECKED_ENV = "FV_CHECKED"  # the keys of the checks a launch saw pass, separated by spaces
_noted: set[str] = set()


def _given() -> set[str]:
    """The keys of the checks the launch that started this process saw pass (`CHECKED_ENV`)."""
    return set(os.environ.get(CHECKED_ENV, "").split())


def note_passed(key: str) -> None:
    """Note that the check named ``key`` (no spaces: its kind and a digest of its input) passed."""
    if not key or any(c.isspace() for c in key):
        raise ValueError(f"check key {key!r}: text without spaces")
    _noted.add(key)


def passed(key: str) -> bool:
    """Whether the check named ``key`` has passed in this process or in the launch that started it."""
    return key in _noted or key in _given()


def env() -> dict[str, str]:
    """The environment entry that gives a node the checks this process has seen pass ({} when none)."""
    keys = _noted | _given()
    return {CHECKED_ENV: " ".join(sorted(keys))} if keys else {}
