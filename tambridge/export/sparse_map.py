"""``sparse_map.npz``: what a run's frontend knows of the scene beyond its poses, for exporters.

One ``.npz`` of plain arrays (read with ``allow_pickle=False``): ``keyframe_ids`` and ``keyframe_frame_indices`` (K,) int64, ``points_world_m`` (P, 3) float64,
``point_colours`` (P, 3) uint8 RGB, and the points' observations ``observation_point_rows``,
``observation_keyframe_ids`` (O,) int64 and ``observation_keypoints_px`` (O, 2) float64 (see
:class:`~tambridge.frontend.contract.MapPointObservations`). The Open3D frontends keep no sparse map: P = O = 0.
"""

from __future__ import annotations

import dataclasses
import zipfile
from pathlib import Path

import numpy as np

from tambridge.camera import Camera
from tambridge.errors import ExportError
from tambridge.files import atomic_path
from tambridge.frontend.contract import FrontendResult, MapPointObservations
from tambridge.geometry import inverse, transform_points

SEEN_DEPTH_TOLERANCE = 0.05
"""A frame that is no keyframe is taken to see a map point where its measured depth at the point's pixel is within
this fraction of the point's depth: Kinect depth is noisy by about 1.5 % at 2 m, and a hidden point lies further."""


@dataclasses.dataclass
class SparseMap:
    """The contents of ``sparse_map.npz`` (see the module docstring); points in the world frame, metres."""

    keyframe_frame_indices: dict[int, int]
    points_world_m: np.ndarray
    point_colours: np.ndarray
    observations: MapPointObservations


def write_sparse_map(path: Path, result: FrontendResult) -> None:
    """Write ``result``'s keyframes and map points (with their observations) to ``path``; the sequence's folder is
    metrics.json's ``sequence``."""
    keyframe_ids = np.array(sorted(result.keyframe_frame_indices), np.int64)
    observations = result.map_point_observations
    arrays = {
        "keyframe_ids": keyframe_ids,
        "keyframe_frame_indices": np.array([result.keyframe_frame_indices[k] for k in keyframe_ids], np.int64),
        "points_world_m": np.asarray(result.map_points_world_m, np.float64).reshape(-1, 3),
        "point_colours": np.asarray(result.map_point_colours, np.uint8).reshape(-1, 3),
        "observation_point_rows": np.asarray(observations.point_rows, np.int64),
        "observation_keyframe_ids": np.asarray(observations.keyframe_ids, np.int64),
        "observation_keypoints_px": np.asarray(observations.keypoints_px, np.float64).reshape(-1, 2),
    }
    with atomic_path(path) as temp_path, open(temp_path, "wb") as handle:
        np.savez(handle, **arrays)


def read_sparse_map(path: Path) -> SparseMap:
    """Read :func:`write_sparse_map`'s file; a missing or damaged one raises :class:`ExportError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise ExportError(f"{path}: not found; runs of this version of 'tambridge reconstruct' write it, re-run the "
                          "reconstruction to export it")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
        return SparseMap(
            keyframe_frame_indices=dict(zip(arrays["keyframe_ids"].tolist(), arrays["keyframe_frame_indices"].tolist())),
            points_world_m=arrays["points_world_m"].reshape(-1, 3),
            point_colours=arrays["point_colours"].reshape(-1, 3),
            observations=MapPointObservations(arrays["observation_point_rows"], arrays["observation_keyframe_ids"],
                                              arrays["observation_keypoints_px"].reshape(-1, 2)),
        )
    except (KeyError, ValueError, OSError, zipfile.BadZipFile) as error:
        raise ExportError(f"{path}: not a sparse map of 'tambridge reconstruct' ({error}); re-run the reconstruction") from None


def points_seen(points_world_m: np.ndarray, world_from_camera: np.ndarray, camera: Camera,
                depth_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The map points a frame sees that its keypoints were not recorded for (it is no keyframe): rows (M,) of
    ``points_world_m`` (P, 3) in front of the frame at ``world_from_camera`` (4, 4), inside ``camera``'s image and
    where the frame's ``depth_m`` (H, W) metres measures them (:data:`SEEN_DEPTH_TOLERANCE`), with their pixels
    (M, 2) there."""
    points_camera_m = transform_points(inverse(world_from_camera), np.asarray(points_world_m, np.float64).reshape(-1, 3))
    z_m = points_camera_m[:, 2]
    in_front = z_m > 0
    pixels_px = camera.project(points_camera_m, np.where(in_front, z_m, 1.0))
    rows = np.flatnonzero(in_front & camera.in_image(pixels_px))
    columns, image_rows = np.round(pixels_px[rows]).astype(np.int64).T
    measured_m = depth_m[image_rows, columns]
    agree = (measured_m > 0) & (np.abs(z_m[rows] - measured_m) <= SEEN_DEPTH_TOLERANCE * measured_m)
    return rows[agree], pixels_px[rows[agree]]
