"""Camera pose from 3D-2D matches: PnP-RANSAC, then motion-only refinement of eq. 1 with a Huber kernel."""

from __future__ import annotations

import cv2
import numba
import numpy as np

from tambridge.camera import pinhole_inverse_depth_numba
from tambridge.frontend.orb.dense_depth import (
    DenseTerm,
    dense_normal_equations_numba,
    dense_normal_equations_reference,
    kernel_arguments,
)
from tambridge.frontend.orb.reprojection import (
    MIN_DEPTH_M,
    chi2_thresholds,
    huber_weights,
    pose_jacobian,
    project_rgbd,
    project_rgbd_jacobian,
    residuals,
    row_weights,
)
from tambridge.geometry import exp_se3, exp_se3_numba, orthonormalised, transform_points



def solve_pnp_ransac(
    points_world: np.ndarray,
    keypoints_px: np.ndarray,
    K: np.ndarray,
    camera_from_world_guess: np.ndarray | None,
    reprojection_px: float,
    iterations: int,
) -> tuple[np.ndarray | None, np.ndarray]:
    """``(camera_from_world 4x4 or None, inlier mask (N,))`` from world points (N, 3) seen at keypoints (N, 2).

    cv2.solvePnPRansac with EPnP minimal sets; a guess (the motion prior) seeds the final refinement.
    """
    inliers_mask = np.zeros(len(points_world), bool)
    if len(points_world) < 6:
        return None, inliers_mask
    use_guess = camera_from_world_guess is not None
    rvec = cv2.Rodrigues(camera_from_world_guess[:3, :3])[0] if use_guess else None
    tvec = camera_from_world_guess[:3, 3].reshape(3, 1).copy() if use_guess else None
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        points_world.astype(np.float64), keypoints_px.astype(np.float64), K, None,
        rvec=rvec, tvec=tvec, useExtrinsicGuess=use_guess, iterationsCount=iterations,
        reprojectionError=reprojection_px, confidence=0.99, flags=cv2.SOLVEPNP_EPNP,
    )
    if not ok or inliers is None or len(inliers) < 6:
        return None, inliers_mask
    camera_from_world = np.eye(4)
    camera_from_world[:3, :3] = cv2.Rodrigues(rvec)[0]
    camera_from_world[:3, 3] = tvec.ravel()
    inliers_mask[inliers.ravel()] = True
    return camera_from_world, inliers_mask


@numba.njit(cache=True, nogil=True)
def _pose_normal_equations(rotation, translation, points_world, observations, weights, thresholds, active, robust, fx, fy, cx, cy):
    hessian = np.zeros((6, 6))
    gradient = np.zeros(6)
    chi2 = np.full(points_world.shape[0], np.inf)
    jacobian = np.zeros((3, 6))
    for i in range(points_world.shape[0]):
        x = rotation[0, 0] * points_world[i, 0] + rotation[0, 1] * points_world[i, 1] + rotation[0, 2] * points_world[i, 2] + translation[0]
        y = rotation[1, 0] * points_world[i, 0] + rotation[1, 1] * points_world[i, 1] + rotation[1, 2] * points_world[i, 2] + translation[1]
        z = rotation[2, 0] * points_world[i, 0] + rotation[2, 1] * points_world[i, 1] + rotation[2, 2] * points_world[i, 2] + translation[2]
        if z <= MIN_DEPTH_M:
            continue
        inv_z = 1.0 / z
        u, v = pinhole_inverse_depth_numba(x, y, inv_z, fx, fy, cx, cy)
        r0 = u - observations[i, 0]
        r1 = v - observations[i, 1]
        r2 = inv_z - observations[i, 2] if weights[i, 2] > 0 else 0.0
        value = weights[i, 0] * r0 * r0 + weights[i, 1] * r1 * r1 + weights[i, 2] * r2 * r2
        chi2[i] = value
        if not active[i]:
            continue
        kernel = 1.0
        if robust and value > thresholds[i]:
            kernel = np.sqrt(thresholds[i] / value)
        # d(u, v, 1/z)/d(point in camera), then times [I, -hat(p)] for the left update of the pose.
        projection = ((fx * inv_z, 0.0, -fx * x * inv_z * inv_z), (0.0, fy * inv_z, -fy * y * inv_z * inv_z), (0.0, 0.0, -inv_z * inv_z))
        residual = (r0, r1, r2)
        for row in range(3):
            a, b, c = projection[row]
            jacobian[row, 0], jacobian[row, 1], jacobian[row, 2] = a, b, c
            jacobian[row, 3], jacobian[row, 4], jacobian[row, 5] = -b * z + c * y, a * z - c * x, -a * y + b * x
            w = kernel * weights[i, row]
            if w == 0.0:
                continue
            for j in range(6):
                gradient[j] += w * jacobian[row, j] * residual[row]
                for k in range(j, 6):
                    hessian[j, k] += w * jacobian[row, j] * jacobian[row, k]
    for j in range(6):
        for k in range(j):
            hessian[j, k] = hessian[k, j]
    return hessian, gradient, chi2


def pose_normal_equations(
    camera_from_world: np.ndarray, points_world: np.ndarray, observations: np.ndarray, weights: np.ndarray,
    thresholds: np.ndarray, active: np.ndarray, robust: bool, K: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton system of the pose over the ``active`` (N,) observations: ``(H (6, 6), g (6,), chi2 (N,))``.

    ``weights`` (N, 3) are :func:`row_weights`; with ``robust`` each observation is down-weighted by Huber's
    IRLS factor at ``thresholds`` (N,). ``chi2`` is computed for every observation (inf behind the camera).
    The update is ``delta = -H^-1 g``, applied as ``exp(delta) @ camera_from_world``.
    """
    return _pose_normal_equations(
        np.ascontiguousarray(camera_from_world[:3, :3]), np.ascontiguousarray(camera_from_world[:3, 3]),
        np.ascontiguousarray(points_world, np.float64), np.ascontiguousarray(observations, np.float64),
        np.ascontiguousarray(weights, np.float64), np.ascontiguousarray(thresholds, np.float64),
        np.ascontiguousarray(active, np.bool_), robust, K[0, 0], K[1, 1], K[0, 2], K[1, 2],
    )


def pose_normal_equations_reference(camera_from_world, points_world, observations, weights, thresholds, active, robust, K):
    """Slow twin of :func:`pose_normal_equations`, with the shared vectorised Jacobians of ``reprojection``."""
    points_camera = transform_points(camera_from_world, points_world)
    in_front = points_camera[:, 2] > MIN_DEPTH_M
    safe = np.where(in_front[:, None], points_camera, np.array([0.0, 0.0, 1.0]))
    residual, chi2 = residuals(project_rgbd(safe, K), observations, weights)
    chi2 = np.where(in_front, chi2, np.inf)
    row_weight = weights * (active & in_front)[:, None]
    if robust:
        row_weight = row_weight * huber_weights(np.where(in_front, chi2, 0.0), thresholds)[:, None]
    jacobian = pose_jacobian(safe, project_rgbd_jacobian(safe, K))
    weighted = jacobian * row_weight[:, :, None]
    return np.einsum("nri,nrj->ij", weighted, jacobian), np.einsum("nri,nr->i", weighted, residual), chi2


@numba.njit(cache=True, nogil=True)
def _refine_camera_from_world_kernel(camera_from_world, points_world, observations, weights, thresholds, rounds,
                                     iterations, fx, fy, cx, cy, reference_from_world, samples, reference_points,
                                     normals, stride, dense_fx, dense_fy, dense_cx, dense_cy, sample_weight, noise,
                                     huber, max_distance):
    n = points_world.shape[0]
    inliers = np.ones(n, np.bool_)
    none_active = np.zeros(n, np.bool_)
    for round_index in range(rounds):
        robust = round_index < rounds - 1
        for _ in range(iterations):
            if inliers.sum() < 3:
                break
            hessian, gradient, _ = _pose_normal_equations(
                np.ascontiguousarray(camera_from_world[:3, :3]), np.ascontiguousarray(camera_from_world[:3, 3]),
                points_world, observations, weights, thresholds, inliers, robust, fx, fy, cx, cy)
            if samples.shape[0] > 0:
                dense_hessian, dense_gradient, _, _ = dense_normal_equations_numba(
                    camera_from_world, reference_from_world, samples, reference_points, normals, stride,
                    dense_fx, dense_fy, dense_cx, dense_cy, sample_weight, noise, huber, max_distance)
                hessian = hessian + dense_hessian
                gradient = gradient + dense_gradient
            try:
                delta = -np.linalg.solve(hessian + 1e-9 * np.eye(6), gradient)
            except Exception:  # noqa: BLE001 - numba catches no narrower class; a singular system ends the round
                break
            camera_from_world = exp_se3_numba(delta) @ camera_from_world
            if np.sqrt((delta * delta).sum()) < 1e-6:
                break
        chi2 = _pose_normal_equations(
            np.ascontiguousarray(camera_from_world[:3, :3]), np.ascontiguousarray(camera_from_world[:3, 3]),
            points_world, observations, weights, thresholds, none_active, False, fx, fy, cx, cy)[2]
        inliers = chi2 <= thresholds
        if inliers.sum() < 10:
            break
    return camera_from_world, inliers


def refine_camera_from_world(
    camera_from_world: np.ndarray,
    points_world: np.ndarray,
    observations: np.ndarray,
    inv_sigma2: np.ndarray,
    K: np.ndarray,
    depth_noise_per_m: float,
    rounds: int = 4,
    iterations: int = 10,
    dense: DenseTerm | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Motion-only refinement: Gauss-Newton on the Huber-robust RGB-D reprojection error (ORB-SLAM's PoseOptimization).

    ``points_world`` (N, 3) are fixed; ``observations`` (N, 3) are ``(u, v, 1/z)`` (see
    :mod:`~tambridge.frontend.orb.reprojection`); ``inv_sigma2`` (N,); ``depth_noise_per_m`` k of sigma_z = k z^2
    (0: no depth rows). Each round optimises over the current inliers, then re-classifies every match by its
    chi2 (95% quantile); the last round drops the Huber kernel. ``dense`` adds the point-to-plane depth term of
    :mod:`~tambridge.frontend.orb.dense_depth` to every Gauss-Newton step (it keeps its Huber kernel; it does
    not take part in the inlier classification). Returns ``(camera_from_world 4x4, inliers (N,))``.
    The whole loop runs in one numba kernel (it runs twice per tracked frame, and the Python around each
    Gauss-Newton step cost more than the step); :func:`refine_camera_from_world_reference` is its slow twin.
    """
    weights = row_weights(observations, inv_sigma2, depth_noise_per_m)
    camera_from_world, inliers = _refine_camera_from_world_kernel(
        np.array(camera_from_world, np.float64), np.ascontiguousarray(points_world, np.float64),
        np.ascontiguousarray(observations, np.float64), np.ascontiguousarray(weights, np.float64),
        np.ascontiguousarray(chi2_thresholds(weights), np.float64), rounds, iterations, K[0, 0], K[1, 1], K[0, 2], K[1, 2],
        *kernel_arguments(dense),
    )
    # Frame poses chain (prior = motion @ previous pose): keep the rounding of exp products off SO(3) from growing.
    return orthonormalised(camera_from_world), inliers


def refine_camera_from_world_reference(
    camera_from_world: np.ndarray,
    points_world: np.ndarray,
    observations: np.ndarray,
    inv_sigma2: np.ndarray,
    K: np.ndarray,
    depth_noise_per_m: float,
    rounds: int = 4,
    iterations: int = 10,
    dense: DenseTerm | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Slow twin of :func:`refine_camera_from_world`: the same loop in Python over :func:`pose_normal_equations_reference`."""
    weights = row_weights(observations, inv_sigma2, depth_noise_per_m)
    thresholds = chi2_thresholds(weights)
    inliers = np.ones(len(points_world), bool)
    for round_index in range(rounds):
        robust = round_index < rounds - 1
        for _ in range(iterations):
            if inliers.sum() < 3:
                break
            hessian, gradient, _ = pose_normal_equations_reference(camera_from_world, points_world, observations, weights,
                                                                   thresholds, inliers, robust, K)
            if dense is not None and len(dense.samples_camera_m):
                dense_hessian, dense_gradient, _, _ = dense_normal_equations_reference(camera_from_world, dense)
                hessian, gradient = hessian + dense_hessian, gradient + dense_gradient
            try:
                delta = -np.linalg.solve(hessian + 1e-9 * np.eye(6), gradient)
            except np.linalg.LinAlgError:
                break
            camera_from_world = exp_se3(delta) @ camera_from_world
            if np.linalg.norm(delta) < 1e-6:
                break
        chi2 = pose_normal_equations_reference(camera_from_world, points_world, observations, weights, thresholds,
                                               np.zeros(len(points_world), bool), False, K)[2]
        inliers = chi2 <= thresholds
        if inliers.sum() < 10:
            break
    return orthonormalised(camera_from_world), inliers
