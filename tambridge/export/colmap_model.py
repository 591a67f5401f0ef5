"""A run as a COLMAP sparse model (``cameras``, ``images``, ``points3D`` .bin, and .txt on request).

pycolmap builds the model and writes it, so the files are exactly COLMAP's (its current version also writes
``rigs`` and ``frames``: one trivial rig, one frame per image). Conventions changed on the way: COLMAP stores
``cam_from_world`` (ours are ``world_from_camera``, both in OpenCV's camera frame), and its pixel coordinates
start at the image's top-left corner, so that pixel centres sit at ``+0.5`` of ours (:mod:`tambridge.camera`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pycolmap

from tambridge.camera import Camera
from tambridge.errors import ExportError
from tambridge.geometry import inverse

COLMAP_PIXEL_OFFSET = 0.5
"""COLMAP's pixel coordinates minus ours (OpenCV's): COLMAP puts the top-left pixel's centre at (0.5, 0.5)."""

CAMERA_ID = 1

MIN_TRACK_LENGTH = 2
"""Images a point's track needs (COLMAP triangulates from two); a point seen in fewer of the exported images has none."""


@dataclasses.dataclass
class ModelImage:
    """One image of the model: its file name, its pose ``world_from_camera`` (4, 4), and the points it sees: rows
    ``point_rows`` (M,) of the model's points at pixels ``pixels_px`` (M, 2) of the image (our convention)."""

    name: str
    world_from_camera: np.ndarray
    point_rows: np.ndarray
    pixels_px: np.ndarray


def colmap_camera(camera: Camera) -> pycolmap.Camera:
    """COLMAP's camera of ``camera``: PINHOLE without distortion, OPENCV for k1 k2 p1 p2, FULL_OPENCV when k3 (or
    k4..k6) is set; OpenCV's thin-prism and tilt terms have no COLMAP model and are refused."""
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx + COLMAP_PIXEL_OFFSET, camera.cy + COLMAP_PIXEL_OFFSET
    coefficients = list(camera.distortion) + [0.0] * max(0, 8 - len(camera.distortion))
    if any(abs(c) > 0 for c in coefficients[8:]):
        raise ExportError(f"distortion {camera.distortion} has thin-prism or tilt terms, which no COLMAP camera model "
                          "holds; export with --images undistort")
    if not camera.has_distortion:
        model, params = "PINHOLE", [fx, fy, cx, cy]
    elif all(c == 0 for c in coefficients[4:8]):
        model, params = "OPENCV", [fx, fy, cx, cy, *coefficients[:4]]
    else:
        model, params = "FULL_OPENCV", [fx, fy, cx, cy, *coefficients[:8]]
    return pycolmap.Camera(camera_id=CAMERA_ID, model=model, width=camera.width, height=camera.height, params=params)


def build_model(camera: Camera, images: list[ModelImage], points_world_m: np.ndarray,
                point_colours: np.ndarray) -> pycolmap.Reconstruction:
    """A COLMAP model of ``images`` (ids 1, 2, ... in order), all in ``camera``, and of the points (P, 3) world
    metres with colours (P, 3) uint8 RGB, in row order, each with the images that see it as its track (none when
    fewer than :data:`MIN_TRACK_LENGTH` do)."""
    model = pycolmap.Reconstruction()
    model.add_camera_with_trivial_rig(colmap_camera(camera))
    tracks = [pycolmap.Track() for _ in range(len(points_world_m))]
    for image_id, image in enumerate(images, start=1):
        keypoints = np.asarray(image.pixels_px, np.float64).reshape(-1, 2) + COLMAP_PIXEL_OFFSET
        colmap_image = pycolmap.Image(name=image.name, keypoints=keypoints, camera_id=CAMERA_ID, image_id=image_id)
        camera_from_world = inverse(image.world_from_camera)
        model.add_image_with_trivial_frame(colmap_image, pycolmap.Rigid3d(camera_from_world[:3]))
        for point_index, row in enumerate(np.asarray(image.point_rows).tolist()):
            tracks[row].add_element(image_id, point_index)
    # add_point3D links each track element's 2D point to the new 3D point. COLMAP's bundle adjustment refuses a
    # track of one image: such a point keeps its position and colour (an initial point for training), not the track.
    for position, colour, track in zip(points_world_m, point_colours, tracks):
        model.add_point3D(np.asarray(position, np.float64), track if track.length() >= MIN_TRACK_LENGTH else pycolmap.Track(),
                          np.asarray(colour, np.uint8))
    return model


def write_model(model: pycolmap.Reconstruction, folder: Path, text: bool = False) -> None:
    """Write ``model`` into ``folder`` (made if needed) in COLMAP's binary format, and its text format with ``text``."""
    folder.mkdir(parents=True, exist_ok=True)
    model.write_binary(str(folder))
    if text:
        model.write_text(str(folder))
