"""The output folder of a run: refused when it holds results a user would lose, locked while a run writes into it,
and listed in a manifest so that ``--overwrite`` removes exactly what an earlier run wrote.

A folder holds a *finished* run when ``metrics.json`` is there (it is written last) and a *killed* one when a
checkpoint is there; either is kept unless the user says ``--overwrite`` (or ``--resume`` for a killed run).
``manifest.json`` names every file the run writes (relative paths); it is written before the first of them, so a
killed run's files are listed too.
"""

from __future__ import annotations

import enum
import json
import logging
import os
import socket
from pathlib import Path
from typing import Iterable

from tambridge.errors import TambridgeError
from tambridge.files import atomic_write_text, check_new_or_empty_folder

logger = logging.getLogger("tambridge.run_folder")

MANIFEST_NAME = "manifest.json"
LOCK_NAME = "run.lock"
FINISHED_MARKER = "metrics.json"
MANIFEST_FORMAT = "tambridge run manifest"


class OutputFolderError(TambridgeError):
    """The output folder cannot be used as asked: it holds results, is locked by another run, or is not a folder."""


class Start(enum.Enum):
    """How a run treats what its output folder already holds."""

    NEW = "new"
    """Refuse a folder with a finished or resumable run; replace an earlier run's other files."""
    OVERWRITE = "overwrite"
    """Remove the files an earlier run listed in its manifest first, whatever state it ended in."""
    RESUME = "resume"
    """Continue the killed run whose checkpoint is in the folder; keep its files."""


def check_output_folder(path: Path, start: Start, resumable: Iterable[str]) -> None:
    """Raise :class:`OutputFolderError` unless a run may write into ``path`` as ``start`` says. Reads only.

    ``resumable``: paths (relative to ``path``) whose presence means a killed run can be resumed (its checkpoint).
    """
    path = Path(path)
    # A folder of an earlier run may hold the user's own files beside it (they are left alone); any other
    # non-empty folder is not ours to write into, resume or overwrite (the current folder, after an unset shell
    # variable). A lock alone is a run that is starting.
    check_new_or_empty_folder(path, "", "tambridge run", [MANIFEST_NAME, FINISHED_MARKER, *resumable, LOCK_NAME],
                              OutputFolderError)
    if not path.is_dir():
        return
    read_manifest(path)
    if start is Start.OVERWRITE:
        return
    if start is Start.RESUME:
        if (path / FINISHED_MARKER).is_file():
            raise OutputFolderError(f"{path}: holds a finished run ({FINISHED_MARKER}); nothing to resume: pass "
                                    f"--overwrite to run it again, or give another -o")
        return
    if (path / FINISHED_MARKER).is_file():
        raise OutputFolderError(f"{path}: holds a finished run ({FINISHED_MARKER}); pass --overwrite to replace it, "
                                f"or give another -o")
    killed = [name for name in resumable if (path / name).is_file()]
    if killed:
        raise OutputFolderError(f"{path}: holds a killed run's checkpoint ({killed[0]}); pass --resume to continue it, "
                                f"--overwrite to start over, or give another -o")


def read_manifest(folder: Path) -> list[str]:
    """The relative paths an earlier run into ``folder`` listed (empty without a manifest)."""
    return list(_manifest_document(folder)["files"])


def _manifest_document(folder: Path) -> dict:
    """``folder``'s manifest, checked (``files`` empty without one); errors name it and say what to do."""
    manifest = Path(folder) / MANIFEST_NAME
    if not manifest.is_file():
        return {"files": []}
    try:
        document = json.loads(manifest.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise OutputFolderError(f"{manifest}: not a tambridge manifest ({error}); remove the folder's files by hand or "
                                "give another -o") from None
    if not isinstance(document, dict) or document.get("format") != MANIFEST_FORMAT or \
            not all(isinstance(name, str) for name in document.get("files", [None])):
        raise OutputFolderError(f"{manifest}: not a tambridge manifest; remove the folder's files by hand or give "
                                "another -o")
    for name in document["files"]:
        relative = Path(name)
        if relative.is_absolute() or ".." in relative.parts:
            raise OutputFolderError(f"{manifest}: lists {name!r}, outside its folder; remove the folder's files by hand")
    return document


def check_not_a_runs_own_file(path: Path, option: str) -> None:
    """Raise :class:`OutputFolderError` (one line naming ``option`` and ``path``) where ``path`` is a file a run wrote:
    listed in the manifest of the nearest folder above it that has one, and not added since by another command
    (:func:`add_to_manifest`), which may write it again; the manifest and the lock themselves likewise."""
    path = Path(path).resolve()
    folder = next((parent for parent in path.parents if (parent / MANIFEST_NAME).is_file()), None)
    if folder is None:
        return
    relative, document = str(path.relative_to(folder)), _manifest_document(folder)
    if relative in (MANIFEST_NAME, LOCK_NAME) or (relative in document["files"] and relative not in _added(document)):
        raise OutputFolderError(f"{option} {path}: is a file of the run in {folder} (its {MANIFEST_NAME} lists it); "
                                "name another file")


def _added(document: dict) -> list[str]:
    """The files of a manifest ``document`` that commands after the run added (:func:`add_to_manifest`)."""
    added = document.get("added", [])
    return [name for name in added if isinstance(name, str)] if isinstance(added, list) else []


def is_listed(folder: Path, path: Path) -> bool:
    """Whether ``path`` is a file the run in ``folder`` (or a command since, such as ``export-mesh``) listed in its
    manifest: one that may be written again."""
    folder, path = Path(folder).resolve(), Path(path).resolve()
    return folder in path.parents and str(path.relative_to(folder)) in read_manifest(folder)


def add_to_manifest(folder: Path, written: Path) -> None:
    """List ``written`` (a file another command wrote into the run folder ``folder``, such as ``export-mesh``'s
    mesh.obj) in the folder's manifest, so that ``--overwrite`` removes it with the run; nothing without a manifest."""
    folder, written = Path(folder).resolve(), Path(written).resolve()
    if not (folder / MANIFEST_NAME).is_file() or folder not in written.parents:
        return
    document = _manifest_document(folder)
    relative = str(written.relative_to(folder))
    if relative not in document["files"]:
        document = {"format": MANIFEST_FORMAT, "files": [*document["files"], relative],
                    "added": [*_added(document), relative]}
        atomic_write_text(folder / MANIFEST_NAME, json.dumps(document, indent=2) + "\n")


class RunFolder:
    """A run's output folder while the run writes into it: locked (``run.lock`` holds the owner's host and PID, so a
    killed run's stale lock is recognised) and listed in ``manifest.json``. Use as a context manager."""

    def __init__(self, path: Path, start: Start, files: Iterable[str]) -> None:
        """``files``: every path (relative to ``path``) the run may write, recorded in the manifest."""
        self.path = Path(path)
        self.start = start
        self.files = list(dict.fromkeys(files))

    def __enter__(self) -> "RunFolder":
        self.path.mkdir(parents=True, exist_ok=True)
        self._lock()
        try:
            earlier = read_manifest(self.path)
            if self.start is not Start.RESUME:
                # The earlier run's files go (all of them with --overwrite; with a plain start only an unfinished
                # run's, which check_output_folder allowed), and nothing that no run listed.
                for name in dict.fromkeys([*earlier, *self.files]):
                    if name != LOCK_NAME:
                        (self.path / name).unlink(missing_ok=True)
            self._write_manifest([*earlier, *self.files] if self.start is Start.RESUME else self.files)
        except BaseException:
            self._unlock()
            raise
        return self

    def __exit__(self, *exc_info) -> None:
        self._unlock()

    def _write_manifest(self, files: list[str]) -> None:
        document = {"format": MANIFEST_FORMAT, "files": list(dict.fromkeys(files))}
        atomic_write_text(self.path / MANIFEST_NAME, json.dumps(document, indent=2) + "\n")

    def _lock(self) -> None:
        lock = self.path / LOCK_NAME
        owner = f"{socket.gethostname()} {os.getpid()}\n"
        for _ in range(2):
            try:
                descriptor = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                if _lock_is_live(lock):
                    raise OutputFolderError(f"{self.path}: another run ({lock.read_text().strip()}) is writing into it "
                                            f"(see {lock}); wait for it or give another -o") from None
                logger.warning("%s: removing the stale lock of a run that is no longer running", lock)
                lock.unlink(missing_ok=True)
                continue
            with os.fdopen(descriptor, "w") as handle:
                handle.write(owner)
            return
        raise OutputFolderError(f"{lock}: could not take the lock; remove it if no run is writing into {self.path}")

    def _unlock(self) -> None:
        (self.path / LOCK_NAME).unlink(missing_ok=True)


def _lock_is_live(lock: Path) -> bool:
    """Whether the run named in ``lock`` still runs: same host and its PID alive (another host's lock counts as live:
    its PIDs cannot be checked from here)."""
    try:
        host, pid = lock.read_text().split()
        pid = int(pid)
    except (OSError, ValueError):
        return False  # a lock its owner did not finish writing: the owner was killed while taking it
    if host != socket.gethostname():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
