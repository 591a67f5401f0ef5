"""Bundle adjustment (paper eq. 2): Levenberg-Marquardt over keyframe poses and map points, Schur-reduced.

The normal equations are split into camera blocks (6 per variable keyframe) and point blocks (3 per point);
points are eliminated first (Schur complement, Triggs et al. 2000, sec. 6.1), the reduced camera system is
solved densely (a local BA has tens of keyframes, a global one hundreds), then points are back-substituted.
Residuals are the RGB-D reprojection of :mod:`~tambridge.frontend.orb.reprojection` with an optional Huber kernel
(threshold = the chi2 95% quantile of the observation's degrees of freedom, as ORB-SLAM). The cost reported
is Ceres' convention, ``0.5 * sum(rho(chi2))``, so it can be compared with pycolmap's bundle adjustment.
"""

from __future__ import annotations

import dataclasses

import numba
import numpy as np
import scipy.linalg
from threadpoolctl import ThreadpoolController

from tambridge.camera import pinhole_inverse_depth_numba
from tambridge.frontend.orb.dense_depth import DenseTerm, dense_pair_cost, dense_pair_normal_equations
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
from tambridge.geometry import exp_se3

# Once open3d or pycolmap is loaded (their OpenMP runtime), multi-threaded OpenBLAS factorisations run
# far slower (threads spin against each other); one thread is fast.
_THREADPOOLS = ThreadpoolController()


@dataclasses.dataclass
class BundleProblem:
    """Cameras, points and the observations tying them.

    ``camera_from_world`` (C, 4, 4); ``points_world`` (P, 3); observation o sees point ``observation_point[o]``
    from camera ``observation_camera[o]`` at ``observations[o]`` = (u, v, 1/z) (1/z NaN without depth),
    with pixel information ``inv_sigma2[o]``; ``depth_noise_per_m`` is k of sigma_z = k z^2 (0: no depth rows,
    plain reprojection BA). ``fixed_cameras`` (C,) bool keeps those poses constant (fix at least one, or the
    problem has a free gauge). A camera sees a point at most once.
    """

    camera_from_world: np.ndarray
    points_world: np.ndarray
    observation_camera: np.ndarray
    observation_point: np.ndarray
    observations: np.ndarray
    inv_sigma2: np.ndarray
    fixed_cameras: np.ndarray
    K: np.ndarray
    depth_noise_per_m: float
    # Point-to-plane depth edges between cameras (tambridge/frontend/orb/dense_depth.py): each pairs a camera's
    # depth samples with another camera's vertex and normal maps.
    depth_pairs: tuple[DepthPair, ...] = ()

    def __post_init__(self) -> None:
        n = len(self.observation_camera)
        assert self.camera_from_world.shape[1:] == (4, 4), self.camera_from_world.shape
        assert self.points_world.ndim == 2 and self.points_world.shape[1] == 3, self.points_world.shape
        assert self.observation_point.shape == (n,) and self.observations.shape == (n, 3), self.observations.shape
        assert self.inv_sigma2.shape == (n,) and self.fixed_cameras.shape == (len(self.camera_from_world),)


@dataclasses.dataclass
class DepthPair:
    """The dense depth term of camera ``camera``'s depth samples against camera ``reference``'s depth: ``term``
    holds both (its ``reference_from_world`` is ignored: the problem's pose of ``reference`` is used)."""

    camera: int
    reference: int
    term: DenseTerm


def _pairs_cost(pairs, camera_from_world: np.ndarray, cells: list[np.ndarray] | None = None) -> float:
    """0.5 * the depth edges' robust cost (the BA cost's convention); with ``cells`` (one (M,) array per edge, from
    :func:`_add_pairs`) the samples keep those associations."""
    return 0.5 * sum(dense_pair_cost(camera_from_world[pair.camera], camera_from_world[pair.reference], pair.term,
                                     None if cells is None else cells[i])
                     for i, pair in enumerate(pairs))


def _add_pairs(pairs, camera_from_world, variable_index, h_cc, b_c):
    """Adds the depth edges' diagonal blocks to ``h_cc``, ``b_c`` in place; returns their off-diagonal blocks
    ``[(va, vb, H_ab (6, 6))]`` between two variable cameras, each edge's associations (``cells``, (M,) each) and
    the edges' cost there (as :func:`_pairs_cost`)."""
    off_diagonal = []
    cells = []
    cost = 0.0
    for pair in pairs:
        cells.append(np.empty(len(pair.term.samples_camera_m), np.int64))
        hessian, gradient, pair_cost, _ = dense_pair_normal_equations(camera_from_world[pair.camera],
                                                                      camera_from_world[pair.reference], pair.term,
                                                                      cells[-1])
        cost += 0.5 * pair_cost
        index = (variable_index[pair.camera], variable_index[pair.reference])
        for side, v in enumerate(index):
            if v >= 0:
                h_cc[v] += hessian[6 * side:6 * side + 6, 6 * side:6 * side + 6]
                b_c[v] -= gradient[6 * side:6 * side + 6]
        if index[0] >= 0 and index[1] >= 0:
            off_diagonal.append((index[0], index[1], hessian[:6, 6:]))
    return off_diagonal, cells, cost


@dataclasses.dataclass(frozen=True)
class BundleOptions:
    """``iterations``: the most LM steps tried, rejected ones included (as Ceres counts them; each costs a reduced
    system). ``robust``: Huber kernel on each observation's chi2 (else plain least squares)."""

    iterations: int = 10
    robust: bool = True
    initial_damping: float = 1e-4
    relative_tolerance: float = 1e-10


@dataclasses.dataclass
class BundleSolution:
    """Refined ``camera_from_world`` (C, 4, 4) and ``points_world`` (P, 3), the robust cost before and after (the
    depth edges' samples associated at each), and ``outliers`` (O,): the observations whose chi2 at the solution
    lies beyond the 95% quantile (or behind the camera)."""

    camera_from_world: np.ndarray
    points_world: np.ndarray
    initial_cost: float
    final_cost: float
    outliers: np.ndarray


@numba.njit(cache=True, nogil=True)
def _observation_residual(rotation, translation, point, observation, fx, fy, cx, cy):
    """Camera-frame point and residual (predicted - observed) of one observation."""
    x = rotation[0, 0] * point[0] + rotation[0, 1] * point[1] + rotation[0, 2] * point[2] + translation[0]
    y = rotation[1, 0] * point[0] + rotation[1, 1] * point[1] + rotation[1, 2] * point[2] + translation[1]
    z = rotation[2, 0] * point[0] + rotation[2, 1] * point[1] + rotation[2, 2] * point[2] + translation[2]
    inv_z = 1.0 / z if z > MIN_DEPTH_M else 1.0
    u, v = pinhole_inverse_depth_numba(x, y, inv_z, fx, fy, cx, cy)
    r0 = u - observation[0]
    r1 = v - observation[1]
    r2 = inv_z - observation[2] if observation[2] == observation[2] else 0.0  # NaN: no depth
    return x, y, z, r0, r1, r2


@numba.njit(cache=True, nogil=True)
def _evaluate_kernel(rotations, translations, points, obs_camera, obs_point, observations, weights, thresholds, robust, fx, fy, cx, cy):
    cost = 0.0
    chi2 = np.empty(obs_camera.shape[0])
    for o in range(obs_camera.shape[0]):
        c, p = obs_camera[o], obs_point[o]
        x, y, z, r0, r1, r2 = _observation_residual(rotations[c], translations[c], points[p], observations[o], fx, fy, cx, cy)
        if z <= MIN_DEPTH_M:
            chi2[o] = np.inf
            continue
        value = weights[o, 0] * r0 * r0 + weights[o, 1] * r1 * r1 + weights[o, 2] * r2 * r2
        chi2[o] = value
        if robust and value > thresholds[o]:
            cost += 2.0 * np.sqrt(thresholds[o] * value) - thresholds[o]
        else:
            cost += value
    return 0.5 * cost, chi2


@numba.njit(cache=True, nogil=True)
def _linearise_kernel(rotations, translations, points, obs_camera, obs_point, observations, weights, thresholds, robust,
                      variable_index, n_variable, fx, fy, cx, cy):
    n_obs, n_points = obs_camera.shape[0], points.shape[0]
    h_cc = np.zeros((n_variable, 6, 6))
    b_c = np.zeros((n_variable, 6))
    h_pp = np.zeros((n_points, 3, 3))
    b_p = np.zeros((n_points, 3))
    h_cp = np.zeros((n_obs, 6, 3))
    j_c = np.zeros((3, 6))
    j_p = np.zeros((3, 3))
    for o in range(n_obs):
        c, p = obs_camera[o], obs_point[o]
        rotation = rotations[c]
        x, y, z, r0, r1, r2 = _observation_residual(rotation, translations[c], points[p], observations[o], fx, fy, cx, cy)
        if z <= MIN_DEPTH_M:
            continue
        value = weights[o, 0] * r0 * r0 + weights[o, 1] * r1 * r1 + weights[o, 2] * r2 * r2
        kernel = 1.0
        if robust and value > thresholds[o]:
            kernel = np.sqrt(thresholds[o] / value)
        inv_z = 1.0 / z
        projection = ((fx * inv_z, 0.0, -fx * x * inv_z * inv_z), (0.0, fy * inv_z, -fy * y * inv_z * inv_z), (0.0, 0.0, -inv_z * inv_z))
        residual = (r0, r1, r2)
        v = variable_index[c]
        for row in range(3):
            a, b, cc = projection[row]
            # camera: d(prediction)/d(point in camera) @ [I, -hat(p_c)]; point: d(prediction)/d(p_c) @ R.
            j_c[row, 0], j_c[row, 1], j_c[row, 2] = a, b, cc
            j_c[row, 3], j_c[row, 4], j_c[row, 5] = -b * z + cc * y, a * z - cc * x, -a * y + b * x
            for k in range(3):
                j_p[row, k] = a * rotation[0, k] + b * rotation[1, k] + cc * rotation[2, k]
        for row in range(3):
            w = kernel * weights[o, row]
            if w == 0.0:
                continue
            r = residual[row]
            for i in range(3):
                b_p[p, i] -= w * j_p[row, i] * r
                for k in range(3):
                    h_pp[p, i, k] += w * j_p[row, i] * j_p[row, k]
            if v < 0:
                continue
            for i in range(6):
                b_c[v, i] -= w * j_c[row, i] * r
                for k in range(6):
                    h_cc[v, i, k] += w * j_c[row, i] * j_c[row, k]
                for k in range(3):
                    h_cp[o, i, k] += w * j_c[row, i] * j_p[row, k]
    return h_cc, b_c, h_pp, b_p, h_cp


def linearise_reference(problem: "BundleProblem", weights: np.ndarray, thresholds: np.ndarray, robust: bool, variable_index: np.ndarray):
    """Slow twin of the linearisation kernel, from the shared vectorised Jacobians: ``(H_cc, b_c, H_pp, b_p, H_cp)``."""
    rotation = problem.camera_from_world[problem.observation_camera, :3, :3]
    points_camera = np.einsum("nij,nj->ni", rotation, problem.points_world[problem.observation_point]) \
        + problem.camera_from_world[problem.observation_camera, :3, 3]
    in_front = points_camera[:, 2] > MIN_DEPTH_M
    safe = np.where(in_front[:, None], points_camera, np.array([0.0, 0.0, 1.0]))
    residual, chi2 = residuals(project_rgbd(safe, problem.K), problem.observations, weights)
    row_weight = weights * in_front[:, None]
    if robust:
        row_weight = row_weight * huber_weights(np.where(in_front, chi2, 0.0), thresholds)[:, None]
    projection = project_rgbd_jacobian(safe, problem.K)
    camera_jacobian = pose_jacobian(safe, projection)
    point_jacobian = np.einsum("nij,njk->nik", projection, rotation)
    n_variable = int((variable_index >= 0).sum())
    variable = variable_index[problem.observation_camera]
    h_cc, b_c = np.zeros((n_variable, 6, 6)), np.zeros((n_variable, 6))
    h_pp, b_p = np.zeros((len(problem.points_world), 3, 3)), np.zeros((len(problem.points_world), 3))
    h_cp = np.zeros((len(residual), 6, 3))
    for o in range(len(residual)):
        w = row_weight[o]
        j_c, j_p, p = camera_jacobian[o], point_jacobian[o], problem.observation_point[o]
        h_pp[p] += j_p.T @ (w[:, None] * j_p)
        b_p[p] -= j_p.T @ (w * residual[o])
        if variable[o] >= 0:
            h_cc[variable[o]] += j_c.T @ (w[:, None] * j_c)
            b_c[variable[o]] -= j_c.T @ (w * residual[o])
            h_cp[o] = j_c.T @ (w[:, None] * j_p)
    return h_cc, b_c, h_pp, b_p, h_cp


@numba.njit(cache=True, nogil=True)
def _inverse_3x3(a, out):
    """``out`` (3, 3) = the inverse of ``a`` (3, 3) by its adjugate: a LAPACK call per point block costs more than
    the arithmetic."""
    c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    c01 = a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]
    c02 = a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]
    c10 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    c11 = a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]
    c12 = a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]
    c20 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    c21 = a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]
    c22 = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    inverse_det = 1.0 / (a[0, 0] * c00 + a[0, 1] * c10 + a[0, 2] * c20)
    out[0, 0], out[0, 1], out[0, 2] = c00 * inverse_det, c01 * inverse_det, c02 * inverse_det
    out[1, 0], out[1, 1], out[1, 2] = c10 * inverse_det, c11 * inverse_det, c12 * inverse_det
    out[2, 0], out[2, 1], out[2, 2] = c20 * inverse_det, c21 * inverse_det, c22 * inverse_det


@numba.njit(cache=True, nogil=True)
def _reduced_system(h_cc, b_c, h_pp, b_p, h_cp, damping, obs_point, obs_variable, point_start, order):
    """Damped Schur complement: ``(S (6V, 6V), rhs (6V,), inverse damped H_pp (P, 3, 3))``;
    :func:`reduced_system_reference` is its slow twin."""
    n_variable, n_points = h_cc.shape[0], h_pp.shape[0]
    h_pp_inverse = np.empty_like(h_pp)
    block = np.empty((3, 3))
    for p in range(n_points):
        block[:] = h_pp[p]
        for i in range(3):
            block[i, i] += damping * h_pp[p, i, i] + 1e-12
        _inverse_3x3(block, h_pp_inverse[p])
    reduced = np.zeros((6 * n_variable, 6 * n_variable))
    rhs = np.zeros(6 * n_variable)
    for v in range(n_variable):
        for i in range(6):
            rhs[6 * v + i] = b_c[v, i]
            for k in range(6):
                reduced[6 * v + i, 6 * v + k] = h_cc[v, i, k]
            reduced[6 * v + i, 6 * v + i] += damping * h_cc[v, i, i] + 1e-12
    y_blocks = np.zeros_like(h_cp)
    for o in range(obs_point.shape[0]):
        v = obs_variable[o]
        if v < 0:
            continue
        inverse = h_pp_inverse[obs_point[o]]
        for i in range(6):
            for k in range(3):
                y_blocks[o, i, k] = h_cp[o, i, 0] * inverse[0, k] + h_cp[o, i, 1] * inverse[1, k] + h_cp[o, i, 2] * inverse[2, k]
        bp = b_p[obs_point[o]]
        for i in range(6):
            rhs[6 * v + i] -= y_blocks[o, i, 0] * bp[0] + y_blocks[o, i, 1] * bp[1] + y_blocks[o, i, 2] * bp[2]
    # S[va, vb] -= Y_a @ H_cp_b^T for every pair of observations (a, b) of the same point from variable cameras
    # (``order`` lists only those, grouped by point); S is symmetric, so the upper triangle is mirrored.
    for p in range(point_start.shape[0] - 1):
        for ia in range(point_start[p], point_start[p + 1]):
            a = order[ia]
            va = obs_variable[a]
            for ib in range(point_start[p], point_start[p + 1]):
                b = order[ib]
                vb = obs_variable[b]
                if vb < va:
                    continue
                for i in range(6):
                    y0, y1, y2 = y_blocks[a, i, 0], y_blocks[a, i, 1], y_blocks[a, i, 2]
                    row = 6 * va + i
                    for j in range(6):
                        reduced[row, 6 * vb + j] -= y0 * h_cp[b, j, 0] + y1 * h_cp[b, j, 1] + y2 * h_cp[b, j, 2]
    for va in range(n_variable):
        for vb in range(va + 1, n_variable):
            for i in range(6):
                for j in range(6):
                    reduced[6 * vb + j, 6 * va + i] = reduced[6 * va + i, 6 * vb + j]
    return reduced, rhs, h_pp_inverse


def reduced_system_reference(h_cc, b_c, h_pp, b_p, h_cp, damping, obs_point, obs_variable):
    """Slow twin of :func:`_reduced_system` from the whole damped normal equations, dense:
    ``S = H_cc - H_cp H_pp^-1 H_cp^T`` and ``rhs = b_c - H_cp H_pp^-1 b_p``, with ``(S, rhs, H_pp^-1 (P, 3, 3))``."""
    n_variable, n_points = len(h_cc), len(h_pp)
    damped_h_pp = h_pp + (damping * np.diagonal(h_pp, axis1=1, axis2=2)[:, :, None] + 1e-12) * np.eye(3)
    h_pp_inverse = np.linalg.inv(damped_h_pp)
    h_cc_full = np.zeros((6 * n_variable, 6 * n_variable))
    for v in range(n_variable):
        h_cc_full[6 * v:6 * v + 6, 6 * v:6 * v + 6] = h_cc[v] + np.diag(damping * np.diag(h_cc[v]) + 1e-12)
    h_cp_full = np.zeros((6 * n_variable, 3 * n_points))
    for o in np.flatnonzero(obs_variable >= 0):
        v, p = obs_variable[o], obs_point[o]
        h_cp_full[6 * v:6 * v + 6, 3 * p:3 * p + 3] += h_cp[o]
    h_pp_inverse_full = np.zeros((3 * n_points, 3 * n_points))
    for p in range(n_points):
        h_pp_inverse_full[3 * p:3 * p + 3, 3 * p:3 * p + 3] = h_pp_inverse[p]
    y = h_cp_full @ h_pp_inverse_full
    return h_cc_full - y @ h_cp_full.T, b_c.reshape(-1) - y @ b_p.reshape(-1), h_pp_inverse


@numba.njit(cache=True, nogil=True)
def _back_substitute(delta_cameras, h_pp_inverse, b_p, h_cp, obs_point, obs_variable):
    """Point steps ``H_pp^-1 (b_p - sum_o H_cp_o^T delta_c)`` (P, 3)."""
    rhs = b_p.copy()
    for o in range(obs_point.shape[0]):
        v = obs_variable[o]
        if v < 0:
            continue
        for k in range(3):
            for i in range(6):
                rhs[obs_point[o], k] -= h_cp[o, i, k] * delta_cameras[v, i]
    out = np.empty_like(rhs)
    for p in range(rhs.shape[0]):
        for k in range(3):
            out[p, k] = h_pp_inverse[p, k, 0] * rhs[p, 0] + h_pp_inverse[p, k, 1] * rhs[p, 1] + h_pp_inverse[p, k, 2] * rhs[p, 2]
    return out


def _intrinsics(K: np.ndarray) -> tuple[float, float, float, float]:
    return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])


def _evaluate(problem: BundleProblem, camera_from_world, points_world, weights, thresholds, robust) -> tuple[float, np.ndarray]:
    """``(0.5 * sum(rho(chi2)), chi2 (O,))``; observations behind their camera have chi2 = inf and no cost."""
    return _evaluate_kernel(
        np.ascontiguousarray(camera_from_world[:, :3, :3]), np.ascontiguousarray(camera_from_world[:, :3, 3]),
        np.ascontiguousarray(points_world), problem.observation_camera, problem.observation_point,
        problem.observations, weights, thresholds, robust, *_intrinsics(problem.K),
    )


def _cost(problem: BundleProblem, camera_from_world, points_world, weights, thresholds, robust,
          cells: list[np.ndarray] | None = None) -> float:
    """The BA cost: the observations' ``0.5 * sum(rho(chi2))`` plus the depth edges' (always robust) cost, their
    samples associated anew or, with ``cells``, as there."""
    return _evaluate(problem, camera_from_world, points_world, weights, thresholds, robust)[0] \
        + _pairs_cost(problem.depth_pairs, camera_from_world, cells)


def bundle_cost(problem: BundleProblem, camera_from_world=None, points_world=None, robust=False) -> float:
    """``0.5 * sum(rho(chi2))`` at the given (default: the problem's) cameras and points, plus the depth edges'
    (always robust) cost."""
    weights = row_weights(problem.observations, problem.inv_sigma2, problem.depth_noise_per_m)
    return _cost(
        problem, problem.camera_from_world if camera_from_world is None else camera_from_world,
        problem.points_world if points_world is None else points_world, weights, chi2_thresholds(weights), robust,
    )


def solve_bundle_adjustment(problem: BundleProblem, options: BundleOptions = BundleOptions()) -> BundleSolution:
    """Minimise the (robust) RGB-D reprojection error over variable cameras and all points, by LM: at most
    ``options.iterations`` steps, each rejected one raising the damping and each accepted one relinearising. The
    depth edges' samples keep the associations of the last linearisation through the steps tried from it (see
    :mod:`~tambridge.frontend.orb.dense_depth`): the cost those steps are judged by is then smooth."""
    n_cameras = len(problem.camera_from_world)
    camera_from_world = problem.camera_from_world.copy()
    points_world = problem.points_world.copy()
    weights = row_weights(problem.observations, problem.inv_sigma2, problem.depth_noise_per_m)
    thresholds = chi2_thresholds(weights)
    variable_index = np.full(n_cameras, -1, np.int64)
    n_variable = int((~problem.fixed_cameras).sum())
    variable_index[~problem.fixed_cameras] = np.arange(n_variable)
    obs_variable = variable_index[problem.observation_camera]
    # Observations from variable cameras grouped by point: the pairs that fill the Schur complement.
    order = np.flatnonzero(obs_variable >= 0)
    order = order[np.argsort(problem.observation_point[order], kind="stable")]
    point_start = np.searchsorted(problem.observation_point[order], np.arange(len(points_world) + 1))

    cost = _cost(problem, camera_from_world, points_world, weights, thresholds, options.robust)
    initial_cost = cost
    damping = options.initial_damping
    steps = 0
    while steps < options.iterations:
        h_cc, b_c, h_pp, b_p, h_cp = _linearise_kernel(
            np.ascontiguousarray(camera_from_world[:, :3, :3]), np.ascontiguousarray(camera_from_world[:, :3, 3]),
            points_world, problem.observation_camera, problem.observation_point, problem.observations, weights,
            thresholds, options.robust, variable_index, n_variable, *_intrinsics(problem.K),
        )
        off_diagonal, cells, pairs_cost = _add_pairs(problem.depth_pairs, camera_from_world, variable_index, h_cc,
                                                     b_c)
        if problem.depth_pairs and steps > 0:
            # The cost here with the new associations, which the steps from here are held to (at the start, ``cost``
            # was taken with the associations made here).
            cost = _evaluate(problem, camera_from_world, points_world, weights, thresholds, options.robust)[0] \
                + pairs_cost
        improved = False
        while steps < options.iterations:
            steps += 1
            reduced, rhs, h_pp_inverse = _reduced_system(h_cc, b_c, h_pp, b_p, h_cp, damping,
                                                          problem.observation_point, obs_variable, point_start, order)
            for va, vb, block in off_diagonal:
                reduced[6 * va:6 * va + 6, 6 * vb:6 * vb + 6] += block
                reduced[6 * vb:6 * vb + 6, 6 * va:6 * va + 6] += block.T
            if n_variable:
                with _THREADPOOLS.limit(limits=1, user_api="blas"):
                    try:
                        delta_cameras = scipy.linalg.cho_solve(scipy.linalg.cho_factor(reduced), rhs).reshape(-1, 6)
                    except (np.linalg.LinAlgError, ValueError):
                        delta_cameras = np.linalg.lstsq(reduced, rhs, rcond=None)[0].reshape(-1, 6)
            else:
                delta_cameras = np.zeros((0, 6))
            delta_points = _back_substitute(delta_cameras, h_pp_inverse, b_p, h_cp, problem.observation_point, obs_variable)
            candidate_cameras = camera_from_world.copy()
            for camera in np.flatnonzero(variable_index >= 0):
                candidate_cameras[camera] = exp_se3(delta_cameras[variable_index[camera]]) @ camera_from_world[camera]
            candidate_points = points_world + delta_points
            candidate_cost = _cost(problem, candidate_cameras, candidate_points, weights, thresholds, options.robust,
                                   cells)
            if candidate_cost < cost:
                relative_decrease = (cost - candidate_cost) / max(cost, 1e-300)
                camera_from_world, points_world = candidate_cameras, candidate_points
                cost = candidate_cost
                damping = max(damping / 3.0, 1e-12)
                improved = True
                break
            damping *= 4.0
        if not improved or relative_decrease < options.relative_tolerance:
            break
    if problem.depth_pairs:  # ``cost`` held the last linearisation's associations
        cost = _cost(problem, camera_from_world, points_world, weights, thresholds, options.robust)
    final_chi2 = _evaluate(problem, camera_from_world, points_world, weights, thresholds, False)[1]
    return BundleSolution(
        camera_from_world=camera_from_world,
        points_world=points_world,
        initial_cost=initial_cost,
        final_cost=cost,
        outliers=~(final_chi2 <= thresholds),
    )
