"""Text files read as UTF-8, with an error that names the file and the line."""
from __future__ import annotations

from pathlib import Path


def read_utf8(path: Path, hint: str = "") -> str:
    """The text of ``path``, UTF-8 with or without the byte-order mark some editors and spreadsheets write.

    Raises:
        ValueError: "<path> line <n>: not UTF-8 text (<reason>, byte 0x..): save it as UTF-8<hint>",
            for the first byte that is not UTF-8.
        OSError: the file cannot be read.
    """
    raw = path.read_bytes()
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise ValueError(f"{path} line {line}: not UTF-8 text ({exc.reason}, byte {raw[exc.start]:#04x}): save it as "
                         f"UTF-8{hint}") from None
