"""The final trajectory smoothed under a motion model: frames between keyframes lose their frame-to-frame jitter.

Each frame is tracked on its own, so its pose carries its own error: on TUM fr1/xyz the tracked poses jump by
millimetres from one frame to the next where the motion capture moves smoothly (docs/benchmarks.md, "A smoothed
trajectory"). With smoothing on, the trajectory is re-estimated after tracking as the path that best explains the
tracked poses under a white-noise-acceleration motion model: per run of consecutive tracked frames, positions ``x``
minimise

    sum_i |x_i - y_i|^2 / sigma_p^2  +  sum_i |a_i(x)|^2 / sigma_a^2,

``y`` the tracked positions and ``a_i`` the acceleration at frame ``i`` by finite differences over the frames' own
times (a Whittaker smoother; the same least squares as a Rauch-Tung-Striebel smoother of a constant-velocity model,
solved at once). Orientations are smoothed the same way on their path of rotation vectors: the small increments
``log(R_{i+1} R_i^T)`` are summed into a path, the path smoothed, and each frame's rotation turned by the difference
(first order in the corrections, which are tenths of a degree). Keyframes, whose poses bundle adjustment estimated
with every observation of the map, stay where they are and the frames between move towards a smooth path through
them (a mapping view the bridge took from a frame near its keyframe moves with the frames). Frames not tracked
(lost, bridged) stay as they are and split the runs. The poses each frame got online (``TrackResult``) are not
changed: only the trajectory written after tracking.

Tracked poses err mostly along two motions an image cannot tell from standing still: a sideways step with the
turn that keeps the scene in view. A change off them moves the image, and the map renders worse from it. So by
default (``along_image_ambiguity``) each frame keeps only the part of its change along those two motions at the
depth of the scene it sees.

It is on by default: the smoothed poses lie nearer the motion capture of TUM fr1/xyz and KinectFusion's poses of
7-Scenes, and the map seen from them renders about as well as from the tracked ones (docs/benchmarks.md, "A
smoothed trajectory"). ``enabled: false`` writes the tracked poses.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from tambridge.frontend.contract import FrontendResult
from tambridge.geometry import exp_se3, exp_so3, inverse, log_se3, log_so3
from tambridge.settings import POSITIVE, setting
from tambridge.trajectory import Trajectory

logger = logging.getLogger(__name__)


@dataclasses.dataclass
class SmoothingConfig:
    """The motion model the final trajectory is smoothed under (module docstring)."""

    # On by default: nearer a motion capture, for a few hundredths of a dB in renders at the poses (docs/benchmarks.md).
    enabled: bool = setting(True, "smooth the final trajectory's frames between keyframes under a motion model")
    position_sigma_m: float = setting(0.002, "noise of a tracked frame's position (m)", POSITIVE)
    acceleration_sigma_m_s2: float = setting(2.0, "the camera's acceleration the motion model expects (m/s^2)",
                                             POSITIVE)
    rotation_sigma_deg: float = setting(0.1, "noise of a tracked frame's orientation (deg)", POSITIVE)
    angular_acceleration_sigma_deg_s2: float = setting(100.0, "the camera's angular acceleration the motion model "
                                                              "expects (deg/s^2)", POSITIVE)
    # The whole change moves the images off the map, which then renders worse from the smoothed poses; kept along the
    # ambiguity, the change hardly does (docs/benchmarks.md, "A smoothed trajectory").
    along_image_ambiguity: bool = setting(True, "keep each frame's change only along the two motions its image "
                                                "cannot tell from standing still at its median depth (a sideways "
                                                "step with the turn that keeps the scene in view; false: the whole "
                                                "change)")


def acceleration_operator(times_s: np.ndarray) -> scipy.sparse.csr_matrix:
    """(N - 2, N) sparse: row ``i`` maps values at ``times_s`` (N,) (increasing, seconds) to their second derivative
    at ``times_s[i + 1]`` by divided differences (exact for quadratics), per second squared."""
    times_s = np.asarray(times_s, np.float64)
    count = len(times_s)
    if count < 3:
        return scipy.sparse.csr_matrix((0, count))
    before, after = np.diff(times_s)[:-1], np.diff(times_s)[1:]
    middle = 0.5 * (before + after)
    rows = np.repeat(np.arange(count - 2), 3)
    columns = (np.arange(count - 2)[:, None] + np.arange(3)).ravel()
    values = np.stack([1.0 / (before * middle), -(1.0 / before + 1.0 / after) / middle, 1.0 / (after * middle)],
                      axis=1).ravel()
    return scipy.sparse.csr_matrix((values, (rows, columns)), shape=(count - 2, count))


def smooth_path(times_s: np.ndarray, path: np.ndarray, fixed: np.ndarray, sigma: float,
                acceleration_sigma: float) -> np.ndarray:
    """The path (N, D) closest to ``path`` (N, D) at ``times_s`` (N,) with the least acceleration, weighed by
    ``sigma`` and ``acceleration_sigma`` (module docstring), where ``fixed`` (N,) bool rows keep their values
    exactly. A sparse solve, linear in N; :func:`smooth_path_reference` is its slow twin."""
    path = np.asarray(path, np.float64)
    fixed = np.asarray(fixed, bool)
    assert path.ndim == 2 and len(path) == len(times_s) == len(fixed), (path.shape, len(times_s), len(fixed))
    free = np.flatnonzero(~fixed)
    if len(path) < 3 or len(free) == 0:
        return path.copy()
    acceleration = acceleration_operator(times_s) / acceleration_sigma
    # Normal equations of the cost; fixed rows move to the right-hand side.
    system = (scipy.sparse.identity(len(path), format="csr") / sigma**2 + acceleration.T @ acceleration).tocsr()
    right = path / sigma**2
    kept = np.flatnonzero(fixed)
    free_rows = system[free]
    right_free = right[free] - free_rows[:, kept] @ path[kept]
    out = path.copy()
    solved = scipy.sparse.linalg.spsolve(free_rows[:, free].tocsc(), right_free)
    out[free] = solved.reshape(len(free), -1)
    return out


def smooth_path_reference(times_s: np.ndarray, path: np.ndarray, fixed: np.ndarray, sigma: float,
                          acceleration_sigma: float) -> np.ndarray:
    """Slow twin of :func:`smooth_path`: the cost's weighted residual rows stacked densely, every acceleration
    written out from the frames' times, solved by least squares over the free rows."""
    path = np.asarray(path, np.float64)
    count = len(path)
    free = np.flatnonzero(~np.asarray(fixed, bool))
    if count < 3 or len(free) == 0:
        return path.copy()
    rows, targets = [], []
    for i in range(count):
        row = np.zeros(count)
        row[i] = 1.0 / sigma
        rows.append(row)
        targets.append(path[i] / sigma)
    for i in range(1, count - 1):
        velocity_before = np.zeros(count)
        velocity_before[[i - 1, i]] = [-1.0, 1.0]
        velocity_before /= times_s[i] - times_s[i - 1]
        velocity_after = np.zeros(count)
        velocity_after[[i, i + 1]] = [-1.0, 1.0]
        velocity_after /= times_s[i + 1] - times_s[i]
        acceleration = (velocity_after - velocity_before) / (0.5 * (times_s[i + 1] - times_s[i - 1]))
        rows.append(acceleration / acceleration_sigma)
        targets.append(np.zeros(path.shape[1]))
    matrix, targets = np.array(rows), np.array(targets)
    kept = np.setdiff1d(np.arange(count), free)
    targets = targets - matrix[:, kept] @ path[kept]
    out = path.copy()
    out[free] = np.linalg.lstsq(matrix[:, free], targets, rcond=None)[0]
    return out


def smoothed_trajectory(trajectory: Trajectory, fixed: np.ndarray, tracked: np.ndarray,
                        config: SmoothingConfig) -> Trajectory:
    """``trajectory`` smoothed (module docstring) in each run of consecutive ``tracked`` (N,) frames with increasing
    times, keeping the ``fixed`` (N,) frames' poses; frames not tracked keep theirs."""
    fixed, tracked = np.asarray(fixed, bool), np.asarray(tracked, bool)
    assert fixed.shape == tracked.shape == (len(trajectory),), (fixed.shape, tracked.shape, len(trajectory))
    world_from_camera = trajectory.world_from_camera.copy()
    # A run starts at a tracked frame after an untracked one, or after a time that is not earlier than its own.
    starts_run = tracked & ~np.concatenate([[False], tracked[:-1] & (np.diff(trajectory.timestamps_s) > 0)])
    starts = np.flatnonzero(starts_run)
    for start, next_start in zip(starts, np.append(starts[1:], len(tracked))):
        end = start + int(np.argmin(np.append(tracked[start:next_start], False)))
        if end - start < 3:
            continue  # no acceleration to weigh
        times_s, poses = trajectory.timestamps_s[start:end], world_from_camera[start:end]
        world_from_camera[start:end, :3, 3] = smooth_path(times_s, poses[:, :3, 3], fixed[start:end],
                                                          config.position_sigma_m, config.acceleration_sigma_m_s2)
        rotations = poses[:, :3, :3].copy()
        # The rotation-vector path: summed world-frame increments; its smoothed form minus it turns each frame.
        increments = log_so3(rotations[1:] @ np.swapaxes(rotations[:-1], 1, 2))
        rotation_path = np.concatenate([np.zeros((1, 3)), np.cumsum(increments, axis=0)])
        smoothed = smooth_path(times_s, rotation_path, fixed[start:end], np.radians(config.rotation_sigma_deg),
                               np.radians(config.angular_acceleration_sigma_deg_s2))
        world_from_camera[start:end, :3, :3] = exp_so3(smoothed - rotation_path) @ rotations
    return Trajectory(trajectory.timestamps_s.copy(), world_from_camera)


def along_image_ambiguity(world_from_tracked: np.ndarray, world_from_smoothed: np.ndarray,
                          scene_depth_m: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) world_from_camera: each smoothed pose's change from its tracked pose kept only along the two
    motions that leave an image of a scene at ``scene_depth_m`` (N,) metres (finite, positive) where it was: a
    sideways step with the turn that keeps the optical axis's point in view (t_x with w_y = -t_x / z; t_y with
    w_x = t_y / z; small twists in the tracked camera's frame, projected orthogonally, metres against radians). The
    rest of the change (along the viewing axis, the roll, and whatever moves the image) is dropped. Tracked poses
    err mostly along those two motions, which the images cannot see; a change off them the images do see
    (docs/benchmarks.md, "A smoothed trajectory")."""
    count = len(world_from_tracked)
    assert world_from_tracked.shape == world_from_smoothed.shape == (count, 4, 4), world_from_smoothed.shape
    scene_depth_m = np.asarray(scene_depth_m, dtype=np.float64)
    assert scene_depth_m.shape == (count,) and (scene_depth_m > 0).all(), scene_depth_m
    out = np.empty_like(world_from_tracked)
    for row, (tracked, smoothed, depth_m) in enumerate(zip(world_from_tracked, world_from_smoothed, scene_depth_m)):
        twist = log_se3(inverse(tracked) @ smoothed)
        step_x = np.array([depth_m, -1.0]) / np.hypot(depth_m, 1.0)  # (t_x, w_y)
        step_y = np.array([depth_m, 1.0]) / np.hypot(depth_m, 1.0)  # (t_y, w_x)
        t_x, w_y = (twist[[0, 4]] @ step_x) * step_x
        t_y, w_x = (twist[[1, 3]] @ step_y) * step_y
        out[row] = tracked @ exp_se3(np.array([t_x, t_y, 0.0, w_x, w_y, 0.0]))
    return out


def median_depth_m(depth_m: np.ndarray) -> float:
    """The median measured depth (m) of a depth image (H, W) over every 4th pixel of every 4th row; NaN where none
    of them has a depth."""
    samples = depth_m[::4, ::4]
    measured = samples[samples > 0]
    return float(np.median(measured)) if measured.size else float("nan")


def smoothed_result(result: FrontendResult, config: SmoothingConfig, scene_depths_m: np.ndarray) -> FrontendResult:
    """The frontend's result with its trajectory smoothed (:func:`smoothed_trajectory`) about its keyframes (culled
    ones included: the map's Gaussians stay anchored to them), matched by timestamp, and with
    ``config.along_image_ambiguity`` each change kept along the image's ambiguity (:func:`along_image_ambiguity`) at
    ``scene_depths_m`` (N,), the depth (m) of the scene each row's frame sees (:func:`median_depth_m`; NaN: it
    measured none); as given where ``config.enabled`` is off. A moving frame without depth takes the median of the
    other moving frames' (1 m where none has one), and the log says so."""
    if not config.enabled:
        return result
    fixed = np.isin(result.trajectory.timestamps_s, result.keyframe_trajectory.timestamps_s)
    smoothed = smoothed_trajectory(result.trajectory, fixed, result.tracked, config)
    if config.along_image_ambiguity:
        world_from_tracked = result.trajectory.world_from_camera
        assert len(scene_depths_m) == len(world_from_tracked), (len(scene_depths_m), len(world_from_tracked))
        moved = np.flatnonzero((smoothed.world_from_camera != world_from_tracked).any(axis=(1, 2)))
        depths_m = np.asarray(scene_depths_m, dtype=np.float64)[moved]
        measured = np.isfinite(depths_m) & (depths_m > 0)
        if not measured.all():
            fallback_m = float(np.median(depths_m[measured])) if measured.any() else 1.0
            logger.warning("smoothing: %d moving frame(s) measured no depth (the first: frame %d); they take %.2f m "
                           "for the image's ambiguity", int((~measured).sum()), int(moved[~measured][0]), fallback_m)
            depths_m[~measured] = fallback_m
        smoothed.world_from_camera[moved] = along_image_ambiguity(world_from_tracked[moved],
                                                                  smoothed.world_from_camera[moved], depths_m)
    return dataclasses.replace(result, trajectory=smoothed)
