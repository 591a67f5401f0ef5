"""SE(3) maths: the one module where rotations and rigid transforms are converted.

Numpy arrays throughout, with one twin per other array kind where a caller needs it: :func:`exp_se3_torch`
(differentiable) and :func:`exp_se3_numba` (inside numba kernels).

Tangent vectors are ordered ``(rho, phi)``: translation part first, rotation part second, so that
``exp(xi) = [[exp_so3(phi), V(phi) rho], [0, 1]]`` (Barfoot, "State Estimation for Robotics", eq. 7.83).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numba
import numpy as np
from scipy.spatial.transform import Rotation

if TYPE_CHECKING:
    import torch


def hat(phi: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix of a 3-vector: ``hat(a) @ b == cross(a, b)``. (3,) -> (3, 3)."""
    x, y, z = phi
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """Exponential map of a twist ``xi = (rho, phi)`` (6,) to a 4x4 rigid transform."""
    xi = np.asarray(xi, dtype=np.float64)
    rho, phi = xi[:3], xi[3:]
    angle = np.linalg.norm(phi)
    phi_hat = hat(phi)
    if angle < 1e-8:
        rotation = np.eye(3) + phi_hat
        v = np.eye(3) + 0.5 * phi_hat
    else:
        a = np.sin(angle) / angle
        b = (1.0 - np.cos(angle)) / angle**2
        c = (1.0 - a) / angle**2
        rotation = np.eye(3) + a * phi_hat + b * phi_hat @ phi_hat
        v = np.eye(3) + b * phi_hat + c * phi_hat @ phi_hat
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = v @ rho
    return out


@numba.njit(cache=True, nogil=True)
def exp_se3_numba(xi):
    """:func:`exp_se3` for numba kernels (that one is its reference): twist (6,) float64 -> (4, 4)."""
    phi_hat = np.zeros((3, 3))
    phi_hat[0, 1], phi_hat[0, 2], phi_hat[1, 2] = -xi[5], xi[4], -xi[3]
    phi_hat[1, 0], phi_hat[2, 0], phi_hat[2, 1] = xi[5], -xi[4], xi[3]
    angle = np.sqrt(xi[3] * xi[3] + xi[4] * xi[4] + xi[5] * xi[5])
    if angle < 1e-8:
        rotation = np.eye(3) + phi_hat
        v = np.eye(3) + 0.5 * phi_hat
    else:
        a = np.sin(angle) / angle
        b = (1.0 - np.cos(angle)) / angle**2
        c = (1.0 - a) / angle**2
        phi_hat2 = phi_hat @ phi_hat
        rotation = np.eye(3) + a * phi_hat + b * phi_hat2
        v = np.eye(3) + b * phi_hat + c * phi_hat2
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = v @ np.ascontiguousarray(xi[:3])
    return out


def log_se3(transform: np.ndarray) -> np.ndarray:
    """Logarithm of a 4x4 rigid transform to a twist ``(rho, phi)`` (6,); inverse of :func:`exp_se3`."""
    phi = log_so3(transform[:3, :3])
    angle = np.linalg.norm(phi)
    phi_hat = hat(phi)
    if angle < 1e-8:
        v_inv = np.eye(3) - 0.5 * phi_hat
    else:
        half = 0.5 * angle
        v_inv = (
            np.eye(3)
            - 0.5 * phi_hat
            + (1.0 - half * np.cos(half) / np.sin(half)) / angle**2 * phi_hat @ phi_hat
        )
    return np.concatenate([v_inv @ transform[:3, 3], phi])


def log_so3(rotations: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3), axis times angle in radians, of rotation matrices (..., 3, 3): the SO(3) logarithm
    (the rotation part of :func:`log_se3`)."""
    rotations = np.asarray(rotations, np.float64)
    return Rotation.from_matrix(rotations.reshape(-1, 3, 3)).as_rotvec().reshape(rotations.shape[:-2] + (3,))


def exp_so3(rotation_vectors: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3): the inverse of :func:`log_so3`."""
    rotation_vectors = np.asarray(rotation_vectors, np.float64)
    matrices = Rotation.from_rotvec(rotation_vectors.reshape(-1, 3)).as_matrix()
    return matrices.reshape(rotation_vectors.shape[:-1] + (3, 3))


def inverse(transform: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform (exact, without a general matrix inverse)."""
    out = np.eye(4)
    out[:3, :3] = transform[:3, :3].T
    out[:3, 3] = -transform[:3, :3].T @ transform[:3, 3]
    return out


def rotation_angles_deg(transforms: np.ndarray) -> np.ndarray:
    """Angles (...,) in degrees of the rotations of 4x4 transforms (..., 4, 4) or 3x3 rotations (..., 3, 3), from
    their traces."""
    traces = np.trace(transforms[..., :3, :3], axis1=-2, axis2=-1)
    return np.degrees(np.arccos(np.clip((traces - 1.0) / 2.0, -1.0, 1.0)))


def rotation_angle_deg(transform: np.ndarray) -> float:
    """Angle (degrees) of the rotation of a 4x4 transform (or a 3x3 rotation)."""
    return float(rotation_angles_deg(transform))


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation (3, 3) nearest (Frobenius) to a 3x3 ``matrix``, by SVD. Of a sum of rotations it is their chordal
    mean."""
    u, _, vt = np.linalg.svd(matrix)
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


def rotation_onto(rotations_a: np.ndarray, rotations_b: np.ndarray) -> np.ndarray:
    """The rotation Q (3, 3) that best maps rotations ``rotations_b`` onto ``rotations_a`` (N, 3, 3) from the left,
    minimising sum_i |A_i - Q B_i|^2 (Frobenius): the chordal mean of ``A_i B_i^T``."""
    return nearest_rotation(np.einsum("nij,nkj->ik", rotations_a, rotations_b))


def orthonormalised(transform: np.ndarray) -> np.ndarray:
    """The 4x4 rigid transform with the rotation nearest (Frobenius) to ``transform``'s 3x3 block.

    Chains of products (a pose from the previous one times a motion) drift off SO(3) by rounding; this
    puts them back.
    """
    out = transform.copy()
    out[:3, :3] = nearest_rotation(transform[:3, :3])
    return out


def transform_points(a_from_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points ``(N, 3)`` in frame b; returns ``(N, 3)`` in frame a."""
    return points_b @ a_from_b[:3, :3].T + a_from_b[:3, 3]


def poses_from_tum(positions_m: np.ndarray, quaternions_xyzw: np.ndarray) -> np.ndarray:
    """4x4 ``world_from_camera`` (..., 4, 4) from TUM lines' ``tx ty tz`` (..., 3) and ``qx qy qz qw`` (..., 4)."""
    positions_m, quaternions_xyzw = np.asarray(positions_m, np.float64), np.asarray(quaternions_xyzw, np.float64)
    out = np.broadcast_to(np.eye(4), positions_m.shape[:-1] + (4, 4)).copy()
    rotations = Rotation.from_quat(quaternions_xyzw.reshape(-1, 4)).as_matrix()
    out[..., :3, :3] = rotations.reshape(positions_m.shape[:-1] + (3, 3))
    out[..., :3, 3] = positions_m
    return out


def tum_from_pose(world_from_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(position_m (3,), quaternion_xyzw (4,) with qw >= 0)`` of a 4x4 pose."""
    quaternion = Rotation.from_matrix(world_from_camera[:3, :3]).as_quat()
    if quaternion[3] < 0:
        quaternion = -quaternion
    return world_from_camera[:3, 3].copy(), quaternion


def look_at(eye_m: np.ndarray, target_m: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """``world_from_camera`` of an OpenCV camera at ``eye_m`` looking at ``target_m``.

    The camera's z axis points at the target, its y axis (image down) is opposite to ``up``.
    """
    forward = np.asarray(target_m, float) - np.asarray(eye_m, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    out = np.eye(4)
    out[:3, :3] = np.stack([right, down, forward], axis=1)
    out[:3, 3] = eye_m
    return out


def interpolate_pose(pose_a: np.ndarray, pose_b: np.ndarray, fraction: float) -> np.ndarray:
    """Pose a fraction of the way from ``pose_a`` to ``pose_b`` along the SE(3) geodesic (both 4x4)."""
    return pose_a @ exp_se3(fraction * log_se3(inverse(pose_a) @ pose_b))


def poses_along(times_s: np.ndarray, world_from_poses: np.ndarray, query_times_s: np.ndarray) -> np.ndarray:
    """(Q, 4, 4) poses at ``query_times_s`` (Q,) on the path through ``world_from_poses`` (N, 4, 4), N >= 2, taken
    at increasing ``times_s`` (N,): between two poses on their SE(3) geodesic at constant velocity
    (:func:`interpolate_pose`), before the first and after the last on the end pair's geodesic continued at its
    velocity (constant-velocity extrapolation)."""
    times_s = np.asarray(times_s, np.float64)
    assert len(times_s) >= 2 and np.all(np.diff(times_s) > 0), times_s
    segments = np.clip(np.searchsorted(times_s, query_times_s, side="right") - 1, 0, len(times_s) - 2)
    return np.stack([interpolate_pose(world_from_poses[i], world_from_poses[i + 1],
                                      (time - times_s[i]) / (times_s[i + 1] - times_s[i]))
                     for i, time in zip(segments, np.asarray(query_times_s, np.float64))])


def exp_se3_torch(xi: "torch.Tensor") -> "torch.Tensor":
    """Differentiable twin of :func:`exp_se3` for a torch twist ``(rho, phi)`` (6,) -> (4, 4), same dtype/device.

    Near ``phi = 0`` the coefficients use their Taylor series in ``angle**2`` so that the value and its
    gradient stay exact at the identity (where the Fusion Bridge evaluates pose gradients).
    """
    import torch

    rho, phi = xi[:3], xi[3:]
    angle_sq = (phi * phi).sum()
    small = angle_sq < 1e-4
    safe_sq = torch.where(small, torch.ones_like(angle_sq), angle_sq)
    angle = torch.sqrt(safe_sq)
    a = torch.where(small, 1.0 - angle_sq / 6.0 + angle_sq**2 / 120.0, torch.sin(angle) / angle)
    b = torch.where(small, 0.5 - angle_sq / 24.0 + angle_sq**2 / 720.0, (1.0 - torch.cos(angle)) / safe_sq)
    c = torch.where(small, 1.0 / 6.0 - angle_sq / 120.0 + angle_sq**2 / 5040.0, (1.0 - a) / safe_sq)
    zero = torch.zeros_like(angle_sq)
    phi_hat = torch.stack(
        [
            torch.stack([zero, -phi[2], phi[1]]),
            torch.stack([phi[2], zero, -phi[0]]),
            torch.stack([-phi[1], phi[0], zero]),
        ]
    )
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    phi_hat_sq = phi_hat @ phi_hat
    rotation = eye + a * phi_hat + b * phi_hat_sq
    v = eye + b * phi_hat + c * phi_hat_sq
    top = torch.cat([rotation, (v @ rho)[:, None]], dim=1)
    bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=xi.dtype, device=xi.device)
    return torch.cat([top, bottom], dim=0)
