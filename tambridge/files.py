"""Atomic file writes: a temporary file in the same folder, fsynced, then renamed over the target.

An interrupted run therefore never leaves a file that looks whole under its final name.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Hashable, Iterable, Iterator

import yaml

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


@contextlib.contextmanager
def staged_folder(path: Path) -> Iterator[Path]:
    """Yield a hidden folder beside ``path`` (a folder yet to be made or an empty one: the caller checks); on success
    it is renamed to ``path``, on error or a stop removed, so that a writer that fails leaves nothing behind."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent))
    try:
        yield staging
        if path.exists():
            path.rmdir()
        os.rename(staging, path)
    finally:
        if staging.exists():
            shutil.rmtree(staging)


def atomic_write_text(path: Path, text: str) -> None:
    """Write text to ``path`` atomically."""
    with atomic_path(path) as temp_path:
        temp_path.write_text(text)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write bytes to ``path`` atomically."""
    with atomic_path(path) as temp_path:
        temp_path.write_bytes(data)


def deepest_existing(path: Path) -> Path:
    """``path`` where it exists, else its nearest ancestor that does (a name too long to look up counts as absent)."""
    path = Path(path)
    while not os.path.exists(path) and path != path.parent:
        path = path.parent
    return path


def check_name_lengths(path: Path, where: str, error: type[TambridgeError] = TambridgeError) -> None:
    """Raise ``error`` (one line starting with ``where``) where a part of ``path`` below its deepest existing folder
    is longer than that folder's file system allows a name (``NAME_MAX``), or the whole path than it allows a path
    (``PATH_MAX``). Checked before anything else looks the path up (the system's own error would not say which part)
    and before anything is made (the folders above it would be left behind empty)."""
    absolute = Path(os.path.abspath(path))
    existing = deepest_existing(absolute)
    if not os.path.isdir(existing):
        return  # a file where a folder should be: the caller's next check says so
    name_max, path_max = os.pathconf(existing, "PC_NAME_MAX"), os.pathconf(existing, "PC_PATH_MAX")
    for part in absolute.relative_to(existing).parts:
        if 0 < name_max < len(os.fsencode(part)):  # pathconf gives -1 where the system sets no limit
            raise error(f"{where}: its part {part[:24]}... is {len(os.fsencode(part))} bytes, more than the "
                        f"{name_max} a name may have here; give a shorter path")
    if 0 < path_max <= len(os.fsencode(str(absolute))):
        raise error(f"{where}: is {len(os.fsencode(str(absolute)))} bytes long, more than the {path_max - 1} a path "
                    f"may have here; give a shorter path")


def check_new_or_empty_folder(path: Path, option: str = "", holds: str | None = None, marks: Iterable[str] = (),
                              error: type[TambridgeError] = TambridgeError) -> None:
    """Raise ``error`` (one line naming ``option`` and ``path``) unless ``path`` is a folder yet to be made, an empty
    one, or one holding any of the files ``marks`` names: what an earlier output of the same command (``holds``, in
    words) leaves there. A folder of other files is the user's, not a command's to write into."""
    path = Path(path)
    where = f"{option} {path}" if option else f"{path}"
    check_name_lengths(path, where, error)
    if path.exists() and not path.is_dir():
        raise error(f"{where}: is a file; give a folder")
    if not path.is_dir():
        return
    entries = sorted(entry.name for entry in path.iterdir())
    if entries and not any((path / mark).is_file() for mark in marks):
        listed = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
        if holds is None:
            raise error(f"{where}: is not empty ({listed}); give a new or empty folder")
        raise error(f"{where}: is not empty and holds no {holds} ({listed}); give a new or empty folder, or an "
                    f"earlier {holds}'s")


def check_output_file(path: Path, option: str, inputs: Iterable[Path] = (),
                      outputs: Iterable[tuple[str, Path]] = ()) -> None:
    """Raise :class:`TambridgeError` (one line naming ``option`` and ``path``) unless ``path`` can take a new file
    without touching ``inputs``: not one of them, not a folder, in a folder that exists or can be made, and not one of
    the command's other ``outputs`` (option, path). Called before any work, so that a bad output path fails before the
    work and before other outputs are written."""
    path = Path(path)
    check_name_lengths(path, f"{option} {path}")
    for source in inputs:
        if Path(source).exists() and path.exists() and path.resolve() == Path(source).resolve():
            raise TambridgeError(f"{option} {path}: is an input of this command; name another file")
    for other_option, other in outputs:
        if path.resolve() == Path(other).resolve():
            raise TambridgeError(f"{option} {path}: is also the {other_option} file; name two different files")
    if path.is_dir():
        raise TambridgeError(f"{option} {path}: is a folder; name a file")
    parent = deepest_existing(path.parent)
    if not parent.is_dir():
        raise TambridgeError(f"{option} {path}: {parent} is a file, not a folder; name a file in a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise TambridgeError(f"{option} {path}: cannot write in {parent}; name a file in a folder you can write")


CONFIGS_FOLDER = Path(__file__).resolve().parents[1] / "configs"
"""The checkout's presets (``*.yaml``) and camera files (``cameras/*.yaml``), beside the package (an editable
install's, as the README's set-up makes)."""


def find_config_file(path: Path, subfolder: str = "") -> Path:
    """``path`` where it exists; else the checkout's file that it names, so that the README's commands work from any
    folder: a bare name with or without ``.yaml`` (``fast``, ``7scenes_kinect.yaml``) in ``configs/<subfolder>``,
    or a path from the checkout's root (``configs/fast.yaml``); else ``path`` as given (its reader names it)."""
    path = Path(path)
    if path.is_file() or path.is_absolute():
        return path
    if len(path.parts) == 1:
        candidate = CONFIGS_FOLDER / subfolder / (path.name if path.suffix else f"{path.name}.yaml")
    else:
        candidate = CONFIGS_FOLDER.parent / path
    return candidate if candidate.is_file() else path


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a mapping that gives a key twice (PyYAML keeps the last one unseen)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            # Merge keys (<<) bring other keys in, which the mapping's own may override, as YAML allows.
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=deep)
            if not isinstance(key, Hashable):
                continue  # the constructor below refuses it, as yaml.safe_load does
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"key {key!r} is given twice", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep)


def load_yaml(text: str):
    """``yaml.safe_load`` of ``text``, refusing a key given twice in a mapping (a :class:`yaml.YAMLError`)."""
    return yaml.load(text, Loader=_UniqueKeyLoader)


def config_file_names(subfolder: str = "") -> str:
    """The names of the checkout's ``configs/<subfolder>/*.yaml`` and where they lie, for error messages."""
    names = ", ".join(sorted(path.stem for path in (CONFIGS_FOLDER / subfolder).glob("*.yaml"))) or "none"
    return f"{names} in {CONFIGS_FOLDER / subfolder}"


def yaml_error_line(error: Exception) -> str:
    """A YAML parser's error in one line: what is wrong and where (line and column, 1-based)."""
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    mark = getattr(error, "problem_mark", None)
    return problem if mark is None else f"{problem} at line {mark.line + 1}, column {mark.column + 1}"


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
