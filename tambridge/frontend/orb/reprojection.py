"""The RGB-D reprojection model shared by motion-only refinement and bundle adjustment (paper eqs. 1-2).

An observation of a map point is ``(u, v, 1/z)``: the keypoint in pixels and, where the keypoint has depth
z, its inverse depth (NaN without depth: that row then carries no weight). Predictions are the same three
numbers for the point in the camera frame; residuals are ``predicted - observed``. The pixel rows are
weighted by ``1 / sigma^2`` of the keypoint's octave (sigma = scale^octave pixels); the inverse-depth row by
``1 / k^2`` where ``k`` is the sensor's depth noise coefficient (sigma_z = k z^2, so sigma of 1/z is k;
Khoshelham & Elberink 2012 for the Kinect). This is our RGB-D BA: depth enters as its own residual, so
depth noise and pixel noise are weighed by their own models (ORB-SLAM2 instead folds depth into a virtual
right-image coordinate with a fixed baseline, which makes depth count for little at 3 m).
Poses are ``camera_from_world`` and are updated on the left: ``camera_from_world <- exp(delta) @ camera_from_world``
with ``delta = (rho, phi)`` as in :mod:`tambridge.geometry`.
"""

from __future__ import annotations

import numpy as np

from tambridge.camera import pinhole_inverse_depth

# Points nearer the camera plane than this (metres, camera z) are treated as behind it: no residual, chi2 = inf.
MIN_DEPTH_M = 1e-3
# chi-square 95% quantiles for 2 and 3 degrees of freedom: outlier thresholds (ORB-SLAM).
CHI2_MONO = 5.991
CHI2_RGBD = 7.815


def rgbd_observations(keypoints_px: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """(N, 3) ``(u, v, 1/z)`` from keypoints (N, 2) and their depth (N,) (0 = none -> NaN)."""
    inverse_depth = np.full(len(depth_m), np.nan)
    has_depth = depth_m > 0
    inverse_depth[has_depth] = 1.0 / depth_m[has_depth]
    return np.column_stack([keypoints_px, inverse_depth])


def project_rgbd(points_camera: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Predicted ``(u, v, 1/z)`` (N, 3) of camera-frame points (N, 3) with positive z."""
    inv_z = 1.0 / points_camera[:, 2]
    u, v = pinhole_inverse_depth(points_camera[:, 0], points_camera[:, 1], inv_z, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    return np.column_stack([u, v, inv_z])


def project_rgbd_jacobian(points_camera: np.ndarray, K: np.ndarray) -> np.ndarray:
    """d(u, v, 1/z) / d(point in camera) (N, 3, 3)."""
    x, y, z = points_camera.T
    inv_z = 1.0 / z
    inv_z2 = inv_z * inv_z
    fx, fy = K[0, 0], K[1, 1]
    jacobian = np.zeros((len(points_camera), 3, 3))
    jacobian[:, 0, 0] = fx * inv_z
    jacobian[:, 0, 2] = -fx * x * inv_z2
    jacobian[:, 1, 1] = fy * inv_z
    jacobian[:, 1, 2] = -fy * y * inv_z2
    jacobian[:, 2, 2] = -inv_z2
    return jacobian


def pose_jacobian(points_camera: np.ndarray, projection_jacobian: np.ndarray) -> np.ndarray:
    """d(prediction) / d(delta) (N, 3, 6) for the left update ``exp(delta) @ camera_from_world``.

    d(exp(delta) p)/d(delta) = [I, -hat(p)] at delta = 0.
    """
    x, y, z = points_camera.T
    n = len(points_camera)
    point_by_delta = np.zeros((n, 3, 6))
    point_by_delta[:, 0, 0] = point_by_delta[:, 1, 1] = point_by_delta[:, 2, 2] = 1.0
    # -hat(p) = [[0, z, -y], [-z, 0, x], [y, -x, 0]]
    point_by_delta[:, 0, 4], point_by_delta[:, 0, 5] = z, -y
    point_by_delta[:, 1, 3], point_by_delta[:, 1, 5] = -z, x
    point_by_delta[:, 2, 3], point_by_delta[:, 2, 4] = y, -x
    return np.einsum("nij,njk->nik", projection_jacobian, point_by_delta)


def row_weights(observations: np.ndarray, inv_sigma2: np.ndarray, depth_noise_per_m: float) -> np.ndarray:
    """(N, 3) information per residual row: ``1/sigma^2`` on u and v; ``1/k^2`` on 1/z where there is depth.

    ``depth_noise_per_m`` is k (sigma_z = k z^2); 0 leaves depth out (plain reprojection BA).
    """
    weights = np.repeat(inv_sigma2[:, None], 3, axis=1).astype(np.float64)
    if depth_noise_per_m > 0:
        weights[:, 2] = np.where(np.isnan(observations[:, 2]), 0.0, 1.0 / depth_noise_per_m**2)
    else:
        weights[:, 2] = 0.0
    return weights


def residuals(predicted: np.ndarray, observations: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(residual (N, 3) with NaN depth rows zeroed, chi2 (N,) = sum of weight * residual^2)``."""
    residual = np.where(weights > 0, predicted - np.nan_to_num(observations), 0.0)
    return residual, np.einsum("ni,ni->n", weights * residual, residual)


def chi2_thresholds(weights: np.ndarray) -> np.ndarray:
    """Outlier threshold per observation (N,): 3 dof where the depth row counts, else 2."""
    return np.where(weights[:, 2] > 0, CHI2_RGBD, CHI2_MONO)


def huber_weights(chi2: np.ndarray, delta2: np.ndarray) -> np.ndarray:
    """IRLS weights rho'(s) of the Huber loss on the squared error s (N,): 1 inside delta^2, delta/sqrt(s) beyond."""
    return np.where(chi2 <= delta2, 1.0, np.sqrt(delta2 / np.maximum(chi2, 1e-300)))
