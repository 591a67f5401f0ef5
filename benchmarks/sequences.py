"""Camera files the benchmarks read the real sequences with, where the folder's own is not the best reading."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# 7-Scenes colour is not registered to depth and the folder's camera.txt describes only the depth camera: with
# this file colour is resampled into the depth camera (tambridge/io/registration.py).
CAMERA_FILES = {"7scenes_redkitchen_0-699": ROOT / "configs" / "cameras" / "7scenes_kinect.yaml"}


def camera_file_for(sequence: Path, registered_colour: bool = True) -> Path | None:
    """The camera file to read ``sequence`` with (None: the folder's own); ``registered_colour=False`` is the
    ablation that reads colour pixel for pixel with depth, as the folder's camera.txt says."""
    return CAMERA_FILES.get(Path(sequence).name) if registered_colour else None
