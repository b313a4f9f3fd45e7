"""Files written whole or not at all."""
from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path


def write_atomically(path: Path, write: Callable[[Path], None]) -> None:
    """Create ``path`` through ``write(tmp)`` on a temporary file beside it (named after this process,
    so processes sharing a cache never write the same file), then rename it into place: a reader sees
    the whole file or none. Missing folders are created."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        write(tmp)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
