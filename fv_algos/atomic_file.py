"""Files written whole or not at all."""
from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np


_writing: set[Path] = set()  # the temporary files this process is writing
T = TypeVar("T")


def write_atomically(path: Path, write: Callable[[Path], T]) -> T:
    """Create ``path`` through ``write(tmp)`` on a temporary file beside it (named after this process,
    so processes sharing a cache never write the same file), then rename it into place: a reader sees
    the whole file or none. Missing folders are created. Returns what ``write`` returned."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp{path.suffix}")
    _writing.add(tmp)
    try:
        result = write(tmp)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
        _writing.discard(tmp)
    return result


def remove_partial_files() -> None:
    """Remove the temporary files of the writes under way in this process: for a process about to be ended
    by a signal's default action, which runs no `finally` (a terminated worker left a `*.tmp.npz` beside the
    cache it was filling)."""
    for tmp in list(_writing):
        tmp.unlink(missing_ok=True)


def write_image(path: Path, image: np.ndarray) -> None:
    """Write ``image`` ((H, W) or (H, W, 3) BGR uint8) whole or not at all, in the format ``path``'s suffix
    names (.png, .jpg ...). OSError naming ``path`` when it cannot be written (OpenCV only returns False,
    e.g. on a full disk, so a caller that did not look said it wrote a file that is not there)."""
    import cv2  # here, not above: the interpolator's process imports this module without OpenCV

    def write(tmp: Path) -> None:
        if not cv2.imwrite(str(tmp), image):
            raise OSError(f"cannot write the image {path} (a full disk, a read-only or special folder?)")

    write_atomically(Path(path), write)
