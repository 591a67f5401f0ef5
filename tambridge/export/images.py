"""The images (and depth maps) of an exported run, and the camera they are in.

``copy`` and ``link`` hand on the sequence's own colour files, so their camera is the sensor's, distortion and
all; ``undistort`` writes the frames as the run saw them (undistorted, colour resampled into the depth camera
for an unregistered sensor), cropped to :func:`undistorted_window`: no pixel without data, and the principal point at
the image's centre, in a pinhole camera. The run's keypoints are pixels of its frames: :func:`pixels_in_images`
moves them into the exported images. Pixels follow OpenCV's convention (:mod:`tambridge.camera`).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import cv2
import numpy as np

from tambridge.camera import Camera
from tambridge.errors import ExportError
from tambridge.io.tum import RgbdSequence
from tambridge.settings import Choice

DEPTH_PER_METRE = 1000.0
"""Depth maps are written as 16-bit PNGs in millimetres (0 = no depth), the unit nerfstudio assumes by default."""


class ImageMode(Choice):
    """How the exported images are made from the sequence's colour files."""

    copy = "copy"
    link = "link"
    undistort = "undistort"


def undistorted_window(sequence: RgbdSequence) -> tuple[int, int, int, int]:
    """``(top, bottom, left, right)``: the largest window of the run's frames inside ``sequence.valid_region`` (every
    pixel has data: no black border where undistortion or colour registration sampled outside the sensor's image)
    whose centre lies within half a pixel of the principal point. The INRIA 3DGS trainer, for one, ignores COLMAP's
    principal point and takes the image's centre; fr1's cy is 15 px off it."""
    top, bottom, left, right = sequence.valid_region
    camera = sequence.camera
    rows = _centred_span(camera.cy, top, bottom)
    columns = _centred_span(camera.cx, left, right)
    if rows is None or columns is None:
        raise ExportError(f"{sequence.folder}: the principal point ({camera.cx:.1f}, {camera.cy:.1f}) lies outside the "
                          f"pixels the frames have data for (rows {top}-{bottom}, columns {left}-{right}); check cx and cy in the "
                          "camera file")
    return rows[0], rows[1], columns[0], columns[1]


def _centred_span(centre_px: float, start: int, stop: int) -> tuple[int, int] | None:
    """The longest ``[first, last)`` inside ``[start, stop)`` whose middle, ``(first + last - 1) / 2``, is within half a
    pixel of ``centre_px``; None when none is."""
    for length in range(stop - start, 0, -1):
        nearest = int(np.floor(centre_px - (length - 1) / 2 + 0.5))
        # A centre on a half pixel is as near to the span one lower.
        for first in (nearest, nearest - 1):
            if start <= first and first + length <= stop and abs(first + (length - 1) / 2 - centre_px) <= 0.5:
                return first, first + length
    return None


def image_camera(sequence: RgbdSequence, mode: ImageMode) -> Camera:
    """The camera of the images ``mode`` gives: the sensor's (with its distortion) for copy and link, the run's
    undistorted pinhole camera cropped to :func:`undistorted_window` for undistort; copying an unregistered sensor's
    colour is refused."""
    if mode == ImageMode.undistort:
        return sequence.camera.cropped(*undistorted_window(sequence))
    if sequence.sensor.colour_camera is not None:
        raise ExportError(f"{sequence.folder}: colour is not registered to depth, so its images are not in the run's "
                          "camera; export with --images undistort (colour resampled into the depth camera)")
    return sequence.sensor.camera


def pixels_in_images(pixels_px: np.ndarray, sequence: RgbdSequence, mode: ImageMode) -> np.ndarray:
    """Pixels (N, 2) of the run's frames (undistorted) in the images ``mode`` exports: shifted into the window of
    undistort, or the same rays through the sensor's distortion (OpenCV's model) for copy and link."""
    pixels_px = np.asarray(pixels_px, np.float64).reshape(-1, 2)
    if mode == ImageMode.undistort:
        top, _, left, _ = undistorted_window(sequence)
        return pixels_px - np.array([left, top], np.float64)
    camera = image_camera(sequence, mode)
    if not camera.has_distortion or len(pixels_px) == 0:
        return pixels_px.copy()
    rays = camera.undistorted().backproject(pixels_px, 1.0)
    distorted, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K,
                                     np.asarray(camera.distortion, np.float64))
    return distorted.reshape(-1, 2)


def write_frames(sequence: RgbdSequence, frame_indices: list[int], names: list[str], mode: ImageMode,
                 image_dir: Path, depth_dir: Path | None = None) -> None:
    """Write frame ``frame_indices[i]``'s colour to ``image_dir / names[i]`` as ``mode`` says and, with ``depth_dir``,
    its depth there under the same name as a millimetre PNG (:data:`DEPTH_PER_METRE`), in the images' camera."""
    image_dir.mkdir(parents=True, exist_ok=True)
    if depth_dir is not None:
        depth_dir.mkdir(parents=True, exist_ok=True)
    window = undistorted_window(sequence) if mode == ImageMode.undistort else None
    for index, name in zip(frame_indices, names):
        if window is not None:
            frame = sequence[index]
            top, bottom, left, right = window
            _write_png(image_dir / name, cv2.cvtColor(frame.rgb[top:bottom, left:right], cv2.COLOR_RGB2BGR))
            depth_m = frame.depth_m[top:bottom, left:right] if depth_dir is not None else None
        else:
            source = sequence.rgb_paths[index].resolve()
            if not source.is_file():
                raise ExportError(f"{source}: listed in {sequence.folder / 'rgb.txt'} but not found; the sequence "
                                  "changed since the run")
            if mode == ImageMode.link:
                os.symlink(source, image_dir / name)
            else:
                shutil.copyfile(source, image_dir / name)
            # The sensor's own depth image, registered to its colour image (distortion and all).
            depth_m = sequence.read_depth_m(sequence.depth_paths[index]) if depth_dir is not None else None
        if depth_m is not None:
            _write_png(depth_dir / Path(name).with_suffix(".png").name,
                       np.clip(np.round(depth_m * DEPTH_PER_METRE), 0, 65535).astype(np.uint16))


def image_name(frame_index: int, mode: ImageMode, sequence: RgbdSequence) -> str:
    """The exported image's file name: the frame index, with the colour file's suffix where it is copied as is."""
    suffix = ".png" if mode == ImageMode.undistort else sequence.rgb_paths[frame_index].suffix.lower()
    return f"{frame_index:06d}{suffix}"


def _write_png(path: Path, image: np.ndarray) -> None:
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise ExportError(f"{path}: OpenCV could not encode the image")
    path.write_bytes(encoded.tobytes())
