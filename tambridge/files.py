"""Atomic file writes: a temporary file in the same folder, fsynced, then renamed over the target.

An interrupted run therefore never leaves a file that looks whole under its final name.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator

from tambridge.errors import TambridgeError


@contextlib.contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed to ``path``, on error removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)
    os.close(handle)
    # mkstemp makes the file owner-only; results are meant to be shared like any file the user writes.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(temp_name, 0o666 & ~umask)
    temp_path = Path(temp_name)
    try:
        yield temp_path
        with open(temp_path, "rb") as written:
            os.fsync(written.fileno())
        os.replace(temp_path, path)
    finally:
        if temp_path.exists():
            temp_path.unlink()


def atomic_write_text(path: Path, text: str) -> None:
    """Write text to ``path`` atomically."""
    with atomic_path(path) as temp_path:
        temp_path.write_text(text)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write bytes to ``path`` atomically."""
    with atomic_path(path) as temp_path:
        temp_path.write_bytes(data)


UTF16_BOMS = (b"\xff\xfe", b"\xfe\xff")
UTF8_BOM = b"\xef\xbb\xbf"


def read_text_file(path: Path, error: type[TambridgeError] = TambridgeError) -> str:
    """The text of a UTF-8 file (a byte-order mark is dropped); any other encoding raises ``error`` naming the file,
    the encoding where it is recognisable (UTF-16), and the fix."""
    path = Path(path)
    if path.is_dir():
        raise error(f"{path}: is a folder, expected a text file")
    data = path.read_bytes()
    if data.startswith(UTF8_BOM):
        data = data[len(UTF8_BOM):]
    elif data.startswith(UTF16_BOMS):
        raise error(f"{path}: is UTF-16 text; save it as UTF-8 (e.g. iconv -f UTF-16 -t UTF-8)")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as decode_error:
        raise error(f"{path}: is not UTF-8 text (byte 0x{data[decode_error.start]:02x} at offset {decode_error.start}); "
                    "save it as UTF-8") from None
