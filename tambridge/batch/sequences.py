"""The sequences of a batch: folders, glob patterns or list files on the command line, each named by its folder."""

from __future__ import annotations

import dataclasses
import glob
from pathlib import Path
from typing import Sequence

from tambridge.errors import SequenceFormatError, TambridgeError
from tambridge.files import read_text_file
from tambridge.io.tum import check_sequence_folder

GLOB_CHARACTERS = set("*?[")


@dataclasses.dataclass(frozen=True)
class BatchSequence:
    """A sequence folder (absolute) and its name: the folder's name, which is also its output folder's."""

    name: str
    folder: Path


def resolve_sequences(arguments: Sequence[str]) -> list[BatchSequence]:
    """The sequences named by ``arguments``, in order, each once.

    An argument is a sequence folder; a glob pattern (``data/*``: the folders it matches, sorted); or a text file
    with one folder a line (blank lines and ``#`` comments skipped; relative paths are relative to the file's
    folder). A :class:`TambridgeError` names an argument that is none of these, a pattern that matches no folder, a
    folder that is no sequence (without rgb.txt or depth.txt), and two sequences of the same name (their outputs
    would share ``OUT/<name>/``).
    """
    folders: list[Path] = []
    for argument in arguments:
        folders += _folders(argument)
    if not folders:
        raise TambridgeError("no sequences given: name sequence folders, glob patterns or a text file of folders")
    by_name: dict[str, Path] = {}
    sequences = []
    for folder in folders:
        folder = folder.resolve()
        try:
            check_sequence_folder(folder)
        except SequenceFormatError:
            raise TambridgeError(f"{folder}: not a sequence folder (no rgb.txt or depth.txt); leave it out of the "
                                 f"batch's folders, patterns and list files") from None
        earlier = by_name.setdefault(folder.name, folder)
        if earlier != folder:
            raise TambridgeError(f"{earlier} and {folder}: two sequences named {folder.name!r} would write the same "
                                 f"output folder; rename one of them")
        if folder not in {sequence.folder for sequence in sequences}:
            sequences.append(BatchSequence(folder.name, folder))
    return sequences


def _folders(argument: str) -> list[Path]:
    path = Path(argument)
    if path.is_dir():
        return [path]
    if path.is_file():
        return _listed_folders(path)
    if GLOB_CHARACTERS & set(argument):
        matches = sorted(Path(match) for match in glob.glob(argument) if Path(match).is_dir())
        if not matches:
            raise TambridgeError(f"{argument}: the pattern matches no folder")
        return matches
    raise TambridgeError(f"{argument}: no such folder, list file or glob pattern")


def _listed_folders(list_file: Path) -> list[Path]:
    folders = []
    for number, line in enumerate(read_text_file(list_file).splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        folder = list_file.parent / line
        if not folder.is_dir():
            raise TambridgeError(f"{list_file}:{number}: {line!r} is not a folder; the file lists one sequence folder a "
                                 f"line (relative to the file's folder)")
        folders.append(folder)
    return folders
