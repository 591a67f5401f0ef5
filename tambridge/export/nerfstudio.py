"""A run as nerfstudio training data: ``transforms.json`` beside the images, depth maps and a point cloud it names.

nerfstudio's conventions, as its own COLMAP conversion writes them: ``transform_matrix`` is ``world_from_camera``
in OpenGL's camera frame (x right, y up, z backwards: ours with y and z negated), and pixel coordinates start at
the image's top-left corner, pixel centres at ``+0.5`` of ours (as COLMAP's). Distortion is OpenCV's
(``k1 k2 k3 k4 p1 p2``, nerfstudio's ``OPENCV`` model, which has no rational terms).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh

from tambridge.camera import Camera
from tambridge.errors import ExportError

OPENGL_FROM_OPENCV_CAMERA = np.diag([1.0, -1.0, -1.0, 1.0])
"""Our (OpenCV) camera axes into OpenGL's: y and z flip. Its own inverse."""

NERFSTUDIO_PIXEL_OFFSET = 0.5
"""nerfstudio's pixel coordinates minus ours: its rays pass through pixel ``(column + 0.5, row + 0.5)``."""


def transform_matrix(world_from_camera: np.ndarray) -> np.ndarray:
    """nerfstudio's ``transform_matrix`` (4, 4) of our ``world_from_camera`` (4, 4): the OpenGL camera's pose."""
    return np.asarray(world_from_camera, np.float64) @ OPENGL_FROM_OPENCV_CAMERA


def camera_entries(camera: Camera) -> dict:
    """The intrinsics keys of ``transforms.json`` for images of ``camera`` (``OPENCV`` with distortion, else
    ``PINHOLE``); OpenCV coefficients beyond k1 k2 p1 p2 k3 (rational, thin-prism, tilt) are refused."""
    coefficients = list(camera.distortion) + [0.0] * max(0, 5 - len(camera.distortion))
    if any(abs(c) > 0 for c in coefficients[5:]):
        raise ExportError(f"distortion {camera.distortion} has terms beyond k1 k2 p1 p2 k3, which nerfstudio's OPENCV "
                          "model lacks; export with --images undistort")
    k1, k2, p1, p2, k3 = coefficients[:5]
    return {
        "camera_model": "OPENCV" if camera.has_distortion else "PINHOLE",
        "w": camera.width, "h": camera.height,
        "fl_x": camera.fx, "fl_y": camera.fy,
        "cx": camera.cx + NERFSTUDIO_PIXEL_OFFSET, "cy": camera.cy + NERFSTUDIO_PIXEL_OFFSET,
        "k1": k1, "k2": k2, "k3": k3, "k4": 0.0, "p1": p1, "p2": p2,
    }


def transforms(camera: Camera, image_paths: list[str], world_from_camera: np.ndarray, depth_paths: list[str] | None,
               ply_path: str | None) -> dict:
    """The contents of ``transforms.json``: ``camera``'s intrinsics, one frame per image (paths relative to the
    file's folder) at its ``world_from_camera`` (N, 4, 4), with its depth map where given, and the point cloud."""
    frames = []
    for index, (path, pose) in enumerate(zip(image_paths, world_from_camera)):
        frame = {"file_path": path, "transform_matrix": transform_matrix(pose).tolist()}
        if depth_paths is not None:
            frame["depth_file_path"] = depth_paths[index]
        frames.append(frame)
    contents = camera_entries(camera)
    # The poses are in an upright world already (z up): nerfstudio's default would turn it so that z is the
    # cameras' mean up, 40 degrees off for a camera looking down at a desk.
    contents["orientation_override"] = "none"
    if ply_path is not None:
        contents["ply_file_path"] = ply_path
    contents["frames"] = frames
    return contents


def write_transforms(path: Path, contents: dict) -> None:
    path.write_text(json.dumps(contents, indent=2) + "\n")


def write_point_cloud(path: Path, points_world_m: np.ndarray, colours: np.ndarray) -> None:
    """A binary PLY of points (P, 3) metres with colours (P, 3) uint8 RGB, which nerfstudio's splatfacto reads."""
    rgba = np.concatenate([np.asarray(colours, np.uint8).reshape(-1, 3), np.full((len(colours), 1), 255, np.uint8)], axis=1)
    path.write_bytes(trimesh.PointCloud(np.asarray(points_world_m, np.float64).reshape(-1, 3), colors=rgba).export(file_type="ply"))
