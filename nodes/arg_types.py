"""Command-line argument types shared by the ``fv`` commands: argparse names the flag and the bad
value when one of these refuses it."""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path


def positive_float(text: str) -> float:
    """A finite number > 0 (seconds, rates)."""
    value = float(text)
    if not 0 < value < math.inf:
        raise argparse.ArgumentTypeError(f"{text} is not a finite number > 0")
    return value


def non_negative_float(text: str) -> float:
    """A finite number >= 0 (0 often meaning "the default" or "off")."""
    value = float(text)
    if not 0 <= value < math.inf:
        raise argparse.ArgumentTypeError(f"{text} is not a finite number >= 0")
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


MAX_SEED = 2**63 - 1  # torch.manual_seed and numpy's generators take every seed up to this


def random_seed(text: str) -> int:
    """A random seed: a whole number from 0 to `MAX_SEED`."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"{text} is not a seed from 0 to 2**63 - 1")
    return value


def _writable(folder: Path) -> None:
    """ArgumentTypeError when ``folder``, or the nearest of its parents that exists, is a file or cannot be
    written into: checked before a long job, so that it does not end unable to save its result."""
    existing = folder.absolute()
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise argparse.ArgumentTypeError(f"{existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{existing} is not writable")


def output_file(text: str) -> Path:
    """A file to write: not an existing folder, and its folder can be created and written."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder, not a file")
    _writable(path.parent)
    return path


def output_with_suffix(*suffixes: str):
    """An argparse type: an :func:`output_file` whose name ends in one of ``suffixes`` (".png"), checked
    before the work whose result it is to hold."""
    def check(text: str) -> Path:
        if Path(text).suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(f"{text} must end in {' or '.join(suffixes)}")
        return output_file(text)
    return check


def output_folder(text: str) -> Path:
    """A folder to write into: not an existing file, and it can be created and written."""
    path = Path(text)
    _writable(path)
    return path
