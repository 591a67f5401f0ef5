"""The real sequences the benchmarks read: where they are looked for, how to get a missing one, and the camera
files to read them with where the folder's own is not the best reading."""

from __future__ import annotations

import argparse
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

FR1_XYZ = "rgbd_dataset_freiburg1_xyz"
"""The whole TUM fr1/xyz (798 colour frames, motion-capture ground truth), under its usual folder name."""
FR1_XYZ_FIRST37 = "tum_fr1_xyz_first37"
KITCHEN = "7scenes_redkitchen_0-699"

DATA_FOLDERS = (ROOT.parent / "shared" / "data", ROOT.parent / "data")
"""Where ``--data`` looks by default: ``shared/data`` and ``data`` beside the repository."""

# How to get each sequence, for the one-line message when it is missing.
HOW_TO_GET = {
    FR1_XYZ: ("`tambridge download fr1/xyz --to DIR` (TUM's page: https://cvg.cit.tum.de/data/datasets/rgbd-dataset/"
              "download), or GitHub neha191091/3d_scan_exercises at commit 0229f5f, folder "
              "Exercise_1/data/rgbd_dataset_freiburg1_xyz"),
    FR1_XYZ_FIRST37: f"the first 37 colour frames of {FR1_XYZ} (with their depth and ground truth)",
    KITCHEN: "7-Scenes redkitchen seq-01 frames 0-699 in the TUM layout (https://www.microsoft.com/en-us/research/"
             "project/rgb-d-dataset-7-scenes/)",
}

# 7-Scenes colour is not registered to depth and the folder's camera.txt describes only the depth camera: with
# this file colour is resampled into the depth camera (tambridge/io/registration.py).
CAMERA_FILES = {KITCHEN: ROOT / "configs" / "cameras" / "7scenes_kinect.yaml"}


class MissingSequence(SystemExit):
    """A benchmark's sequence is in none of the data folders; the message names them and how to get it."""


def find_sequence(name: str, data: list[Path] | tuple[Path, ...] = DATA_FOLDERS) -> Path:
    """The folder of sequence ``name``: ``name`` itself when it is a folder (a path given in full), else the first
    ``data`` folder holding a sub-folder of that name; :class:`MissingSequence` (a one-line message) when none does."""
    if Path(name).is_dir() and (Path(name) / "rgb.txt").is_file():
        return Path(name)
    for folder in data:
        if (Path(folder) / name / "rgb.txt").is_file():
            return Path(folder) / name
    where = ", ".join(str(folder) for folder in data)
    how = f" (get it with {HOW_TO_GET[Path(name).name]})" if Path(name).name in HOW_TO_GET else ""
    raise MissingSequence(f"{Path(name).name}: not found in {where}; put it into one of them or name its folder "
                          f"with --data{how}")


def add_data_argument(parser: argparse.ArgumentParser) -> None:
    """``--data``: the folders :func:`find_sequence` looks in (default :data:`DATA_FOLDERS`)."""
    parser.add_argument("--data", type=Path, nargs="*", default=list(DATA_FOLDERS),
                        help="folders holding the sequences, each under its folder name")


def add_sequence_arguments(parser: argparse.ArgumentParser, default_sequence: str) -> None:
    """``--data`` and ``--sequence`` for a benchmark of one sequence (give both to :func:`find_sequence`)."""
    add_data_argument(parser)
    parser.add_argument("--sequence", default=default_sequence, help="folder name under --data, or a path")


def camera_file_for(sequence: Path, registered_colour: bool = True) -> Path | None:
    """The camera file to read ``sequence`` with (None: the folder's own); ``registered_colour=False`` is the
    ablation that reads colour pixel for pixel with depth, as the folder's camera.txt says."""
    return CAMERA_FILES.get(Path(sequence).name) if registered_colour else None


def merge_rows(old: list[dict], new: list[dict], keys: tuple[str, ...]) -> list[dict]:
    """``old`` rows with those ``new`` re-measured (same values at ``keys``) replaced, in place, and the other new
    rows appended: a benchmark run on a subset keeps the rest of its JSON."""
    def key(row: dict) -> tuple:
        return tuple(row.get(k) for k in keys)

    fresh = {key(row): row for row in new}
    merged = [fresh.pop(key(row), row) for row in old]
    return merged + [row for row in new if key(row) in fresh]
