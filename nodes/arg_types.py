"""Command-line argument types shared by the ``fv`` commands: argparse names the flag and the bad
value when one of these refuses it."""
from __future__ import annotations

import argparse


def positive_float(text: str) -> float:
    """A number > 0 (seconds, rates)."""
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text} is not > 0")
    return value


def positive_int(text: str) -> int:
    """A whole number >= 1 (process counts)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} is not >= 1")
    return value
