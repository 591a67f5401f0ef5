"""Folders of colour and depth images without TUM's index files, as Open3D's RealSense recorder and reconstruction
system, Redwood and many recorders write them: ``color/000000.jpg`` beside ``depth/000000.png``, and perhaps
Open3D's ``camera_intrinsic.json``. :func:`write_tum_index` writes the ``rgb.txt`` and ``depth.txt`` (and, from
such a JSON, the ``camera.yaml``) that make the folder a TUM-layout sequence, in place: the images stay where they are.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import yaml

from tambridge.camera import sensor_from_mapping
from tambridge.errors import CameraConfigError, SequenceFormatError
from tambridge.files import atomic_write_text

COLOUR_FOLDERS = ("rgb", "color", "colour", "image")
"""Names a recorder gives its colour images' folder (TUM's first); the depth images' is ``depth``."""
DEPTH_FOLDER = "depth"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
OPEN3D_INTRINSIC_FILES = ("camera_intrinsic.json", "intrinsic.json")
"""Where Open3D's recorder and reconstruction system keep a ``PinholeCameraIntrinsic`` as JSON."""


@dataclasses.dataclass
class ImageFolders:
    """A folder's colour image folder (``colour_folder``, its name) and its colour and depth images, paired by file
    name without its suffix (``rgb_names`` (N,) and ``depth_names`` (N,), paths relative to the folder, in frame
    order), the colour images without a depth image of their name (``rgb_only``, TUM lists them in rgb.txt alone),
    Open3D's intrinsics file if there is one, and whether camera.yaml is to be made from it (``camera_from_open3d``:
    there is one and the folder has no camera.yaml of its own, which is kept)."""

    folder: Path
    colour_folder: str
    rgb_names: list[str]
    depth_names: list[str]
    rgb_only: list[str]
    open3d_intrinsic: Path | None
    camera_from_open3d: bool


def _frame_order(name: str) -> tuple:
    """Sort key of an image name: its digits as numbers (``frame10`` after ``frame9``), the rest as text; the name
    itself breaks ties (``010`` and ``10``)."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)], name


def _images(folder: Path) -> dict[str, str]:
    """Image files of ``folder`` by their name without suffix."""
    return {path.stem: path.name for path in folder.iterdir() if path.suffix.lower() in IMAGE_SUFFIXES and path.is_file()}


def find_image_folders(folder: Path) -> ImageFolders | None:
    """The colour and depth image folders of ``folder`` (see :data:`COLOUR_FOLDERS`), None where it has none."""
    folder = Path(folder)
    colour = next((folder / name for name in COLOUR_FOLDERS if (folder / name).is_dir()), None)
    if colour is None or not (folder / DEPTH_FOLDER).is_dir():
        return None
    colour_images, depth_images = _images(colour), _images(folder / DEPTH_FOLDER)
    paired = sorted(set(colour_images) & set(depth_images), key=_frame_order)
    unpaired = sorted(set(colour_images) - set(depth_images), key=_frame_order)
    intrinsic = next((folder / name for name in OPEN3D_INTRINSIC_FILES if (folder / name).is_file()), None)
    camera_from_open3d = intrinsic is not None and not (folder / "camera.yaml").exists()
    return ImageFolders(folder, colour.name, [f"{colour.name}/{colour_images[stem]}" for stem in paired],
                        [f"{DEPTH_FOLDER}/{depth_images[stem]}" for stem in paired],
                        [f"{colour.name}/{colour_images[stem]}" for stem in unpaired], intrinsic, camera_from_open3d)


def camera_values_from_open3d(path: Path, depth_scale: float) -> dict:
    """camera.yaml's values from Open3D's ``PinholeCameraIntrinsic`` JSON (``width``, ``height`` and the 3x3
    ``intrinsic_matrix`` column by column), with ``depth_scale`` (depth units per metre, which the JSON lacks)."""
    try:
        values = json.loads(Path(path).read_text())
        width, height = int(values["width"]), int(values["height"])
        matrix = [float(value) for value in values["intrinsic_matrix"]]
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise CameraConfigError(f"{path}: not Open3D's camera intrinsics (width, height, intrinsic_matrix): {error}") from None
    if len(matrix) != 9 or matrix[1] or matrix[2] or matrix[3] or matrix[5] or matrix[8] != 1.0:
        raise CameraConfigError(f"{path}: intrinsic_matrix must hold the 9 entries of fx 0 0, 0 fy 0, cx cy 1 (column "
                                f"by column), got {matrix}")
    return {"width": width, "height": height, "fx": matrix[0], "fy": matrix[4], "cx": matrix[6], "cy": matrix[7],
            "depth_scale": float(depth_scale)}


def write_tum_index(folder: Path, rate_hz: float, depth_scale: float | None = None) -> ImageFolders:
    """Write ``folder``'s rgb.txt and depth.txt (frame i at ``i / rate_hz`` seconds, in name order) and, where the
    folder has Open3D's intrinsics, camera.yaml with ``depth_scale``; everything is checked before anything is
    written, and files already there are never replaced."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SequenceFormatError(f"{folder}: not a folder; pass the folder that holds the color/ and depth/ folders")
    images = find_image_folders(folder)
    if images is None:
        raise SequenceFormatError(f"{folder}: no colour image folder ({', '.join(COLOUR_FOLDERS)}) beside a "
                                  f"{DEPTH_FOLDER}/ folder; pass the folder that holds both")
    if not images.rgb_names:
        raise SequenceFormatError(f"{folder}: no colour image has a depth image of the same name in {DEPTH_FOLDER}/ "
                                  "(for example color/000000.jpg and depth/000000.png); rename them to pair")
    if not rate_hz > 0:
        raise SequenceFormatError(f"--rate {rate_hz}: the camera's frames per second must be above 0")
    targets = ["rgb.txt", "depth.txt"]
    if images.camera_from_open3d:
        if depth_scale is None:
            raise CameraConfigError(f"{images.open3d_intrinsic}: holds no depth scale; pass --depth-scale (depth units "
                                    "per metre: 1000 for millimetres, Open3D's and RealSense's default)")
        camera_values = camera_values_from_open3d(images.open3d_intrinsic, depth_scale)
        sensor_from_mapping(camera_values, images.open3d_intrinsic)  # its values checked as a camera file's
        targets.append("camera.yaml")
    elif depth_scale is not None:
        raise CameraConfigError(f"{folder}: --depth-scale goes into a camera.yaml made from Open3D's "
                                f"{' or '.join(OPEN3D_INTRINSIC_FILES)}, which this folder lacks or has beside its own "
                                "camera.yaml; give depth_scale in camera.yaml")
    existing = [name for name in targets if (folder / name).exists()]
    if existing:
        raise SequenceFormatError(f"{folder / existing[0]}: already there; remove it to write it again")
    frames = sorted([(name, True) for name in images.rgb_names] + [(name, False) for name in images.rgb_only],
                    key=lambda item: _frame_order(Path(item[0]).stem))
    stamps = {name: index / rate_hz for index, (name, _) in enumerate(frames)}
    header = f"# written by 'tambridge index' from {folder.resolve().name}: frame i at i / {rate_hz:g} s\n# timestamp filename\n"
    atomic_write_text(folder / "rgb.txt", header + "".join(f"{stamps[name]:.6f} {name}\n" for name, _ in frames))
    atomic_write_text(folder / "depth.txt", header + "".join(
        f"{stamps[rgb]:.6f} {depth}\n" for rgb, depth in zip(images.rgb_names, images.depth_names)))
    if images.camera_from_open3d:
        atomic_write_text(folder / "camera.yaml", f"# from {images.open3d_intrinsic.name} by 'tambridge index'\n"
                          + yaml.safe_dump(camera_values, sort_keys=False))
    return images
