"""Timestamped camera trajectories and the TUM text format (``timestamp tx ty tz qx qy qz qw``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from tambridge.errors import TrajectoryFormatError
from tambridge.files import atomic_write_text, read_text_file
from tambridge.geometry import poses_along, poses_from_tum, tum_from_pose

QUATERNION_NORM_TOLERANCE = 0.01
"""How far from 1 a file's quaternion norm may lie: rounding to TUM's 4 decimals moves it by about 2e-4; further off,
the columns are most likely not ``qx qy qz qw``."""


@dataclasses.dataclass
class Trajectory:
    """Poses at times: ``timestamps_s`` (N,) float64 increasing, ``world_from_camera`` (N, 4, 4) float64."""

    timestamps_s: np.ndarray
    world_from_camera: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps_s = np.asarray(self.timestamps_s, dtype=np.float64)
        self.world_from_camera = np.asarray(self.world_from_camera, dtype=np.float64).reshape(-1, 4, 4)
        assert self.timestamps_s.shape == (len(self.world_from_camera),), (
            self.timestamps_s.shape,
            self.world_from_camera.shape,
        )

    def __len__(self) -> int:
        return len(self.timestamps_s)

    @property
    def positions_m(self) -> np.ndarray:
        """Camera centres in the world frame, (N, 3)."""
        return self.world_from_camera[:, :3, 3]

    def nearest(self, timestamps_s: np.ndarray) -> "Trajectory":
        """The poses whose timestamps lie nearest to each of ``timestamps_s`` (M,), with their own timestamps (ties
        go to the earlier pose)."""
        timestamps_s = np.asarray(timestamps_s, dtype=np.float64)
        after = np.clip(np.searchsorted(self.timestamps_s, timestamps_s), 1, max(len(self) - 1, 1))
        before = after - 1
        if len(self) == 1:
            rows = np.zeros(len(timestamps_s), np.int64)
        else:
            later_is_nearer = self.timestamps_s[after] - timestamps_s < timestamps_s - self.timestamps_s[before]
            rows = np.where(later_is_nearer, after, before)
        return Trajectory(self.timestamps_s[rows], self.world_from_camera[rows])

    def bridged(self, localised: np.ndarray) -> "Trajectory":
        """The trajectory with every pose not ``localised`` (N,) bool that lies between two localised ones moved onto
        the SE(3) geodesic between the nearest localised poses before and after it, at its time (constant velocity
        over the gap); poses before the first or after the last localised one stay as they are. A frame a tracker
        could not place otherwise keeps a prediction from the past alone, which runs off wherever the camera turned
        during the gap."""
        localised = np.asarray(localised, bool)
        assert localised.shape == (len(self),), (localised.shape, len(self))
        anchors = np.flatnonzero(localised)
        if len(anchors) < 2:
            return Trajectory(self.timestamps_s.copy(), self.world_from_camera.copy())
        gaps = np.flatnonzero(~localised)
        gaps = gaps[(gaps > anchors[0]) & (gaps < anchors[-1])]
        world_from_camera = self.world_from_camera.copy()
        if len(gaps):
            world_from_camera[gaps] = poses_along(self.timestamps_s[anchors], self.world_from_camera[anchors],
                                                  self.timestamps_s[gaps])
        return Trajectory(self.timestamps_s.copy(), world_from_camera)


def parse_tum_trajectory(text: str, source: str) -> Trajectory:
    """Parse TUM trajectory text; ``source`` names the file in errors. Lines starting with ``#`` are comments; the
    poses are sorted by time, and a time listed twice must repeat its pose (the repeat is dropped)."""
    timestamps, values_of_lines, numbers = [], [], []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise TrajectoryFormatError(f"{source} line {number}: expected 8 columns 'timestamp tx ty tz qx qy qz qw', got {len(parts)}")
        try:
            values = np.array([float(p) for p in parts])
        except ValueError:
            word = next(p for p in parts if not _is_number(p))
            raise TrajectoryFormatError(f"{source} line {number}: {word!r} is not a number; a TUM line holds 8 numbers "
                                        "'timestamp tx ty tz qx qy qz qw'") from None
        if not np.all(np.isfinite(values)):
            raise TrajectoryFormatError(f"{source} line {number}: non-finite value (nan or inf); fix or remove the line")
        quaternion = values[4:8]
        with np.errstate(over="ignore"):
            norm = np.linalg.norm(quaternion)
        if not np.isfinite(norm) or abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            shown = "too large to square" if not np.isfinite(norm) else f"{norm:.4g}"
            raise TrajectoryFormatError(f"{source} line {number}: quaternion qx qy qz qw has norm {shown}, not 1; the "
                                        "columns must be 'timestamp tx ty tz qx qy qz qw' (a unit quaternion last)")
        timestamps.append(values[0])
        values_of_lines.append(values)
        numbers.append(number)
    if not timestamps:
        raise TrajectoryFormatError(f"{source}: no poses (empty file or only comments)")
    order = np.argsort(timestamps, kind="stable")
    timestamps = np.array(timestamps)[order]
    values_of_lines = np.array(values_of_lines)[order]
    numbers = np.array(numbers)[order]
    repeated = np.flatnonzero(np.diff(timestamps) == 0) + 1
    for index in repeated:
        if not np.array_equal(values_of_lines[index], values_of_lines[index - 1]):
            first, second = sorted((numbers[index - 1], numbers[index]))
            raise TrajectoryFormatError(f"{source} line {second}: time {float(timestamps[index])!r} is already on line {first} "
                                        "with another pose; list each time once")
    keep = np.ones(len(timestamps), bool)
    keep[repeated] = False
    kept = values_of_lines[keep]
    quaternions = kept[:, 4:8] / np.linalg.norm(kept[:, 4:8], axis=1, keepdims=True)
    return Trajectory(timestamps[keep], poses_from_tum(kept[:, 1:4], quaternions))


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_tum_trajectory(path: Path) -> Trajectory:
    """Read a TUM trajectory file (:func:`parse_tum_trajectory`)."""
    path = Path(path)
    if path.is_dir():
        inside = f" ({path / 'trajectory.txt'}, say)" if (path / "trajectory.txt").is_file() else ""
        raise TrajectoryFormatError(f"{path}: is a folder; pass a TUM trajectory file{inside}")
    if not path.is_file():
        raise TrajectoryFormatError(f"{path}: trajectory file not found")
    return parse_tum_trajectory(read_text_file(path, TrajectoryFormatError), str(path))


def format_tum_trajectory(trajectory: Trajectory) -> str:
    """TUM text of a trajectory, one ``timestamp tx ty tz qx qy qz qw`` line per pose."""
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for timestamp, pose in zip(trajectory.timestamps_s, trajectory.world_from_camera):
        position, quaternion = tum_from_pose(pose)
        values = " ".join(f"{v:.9f}" for v in (*position, *quaternion))
        lines.append(f"{timestamp:.6f} {values}")
    return "\n".join(lines) + "\n"


def write_tum_trajectory(path: Path, trajectory: Trajectory) -> None:
    """Write a trajectory in TUM format atomically."""
    atomic_write_text(Path(path), format_tum_trajectory(trajectory))
