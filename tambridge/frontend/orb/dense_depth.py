"""Dense point-to-plane depth term of the motion-only refinement (projective ICP against a keyframe's depth).

The reference keyframe's depth becomes a vertex map and a normal map in its camera frame, on a grid of every
``stride``-th pixel (:func:`dense_reference`). The current frame contributes its valid depth pixels on a coarser
grid, back-projected into its camera frame (:func:`dense_samples`). For the pose ``camera_from_world`` of the
current frame, a sample ``p`` goes to the reference camera, ``p_ref = reference_from_world @ world_from_camera @
p``, is projected there and associated with the vertex ``q`` and normal ``n`` of the grid cell it falls in; its
residual is ``r = n . (q - p_ref)`` (metres). Samples off the reference's valid depth, or beyond ``max_distance_m``
when they are associated, have none (an association held, below, is not gated again). Each residual is whitened by
the depth noise of both ends, ``sigma^2 = k^2 (z_ref^4 + z^4)``, weighted by ``weight / M`` (M samples: the whole
term weighs as ``weight`` whitened residuals, however many pixels it samples, so ORB's matches lead where they are
many) and down-weighted by Huber's kernel at ``huber_sigmas``. Bundle adjustment holds each sample's association
(its cell, or none) through the steps tried from one linearisation, as ICP does, and makes it again at the next
(:func:`dense_pair_normal_equations`, :func:`dense_pair_cost`): associating anew inside a step makes the cost jump
wherever a sample changes cell, so that near the minimum steps of any size could raise it. Poses update on the left
as in :mod:`~tambridge.frontend.orb.reprojection`: ``camera_from_world <- exp(delta) @ camera_from_world``; then
``dr/d(delta) = [m, p x m]`` with ``m = R^T n`` (``R`` the rotation of reference_from_camera).
"""

from __future__ import annotations

import dataclasses

import numba
import numpy as np

from tambridge.camera import pinhole, pinhole_numba, pinhole_ray
from tambridge.frontend.orb.reprojection import MIN_DEPTH_M
from tambridge.geometry import exp_se3, inverse, orthonormalised, transform_points

# Neighbouring depths differing by more than this fraction of the depth are a depth edge: no normal there.
EDGE_RATIO = 0.05


@dataclasses.dataclass
class DenseReference:
    """A keyframe's depth as ``points_camera_m`` and unit ``normals`` (h, w, 3) on every ``stride``-th pixel,
    in the keyframe's camera frame; normals are zero where the depth or its neighbours are missing or jump."""

    keyframe_id: int
    stride: int
    points_camera_m: np.ndarray
    normals: np.ndarray


@dataclasses.dataclass
class DenseTerm:
    """Everything the refinement needs for the point-to-plane term of one frame (see the module docstring).

    ``reference_from_world`` (4, 4) is the reference keyframe's camera_from_world; ``samples_camera_m`` (M, 3)
    the current frame's depth samples in its camera frame; ``K`` (3, 3) the depth camera's intrinsics.
    """

    reference: DenseReference
    reference_from_world: np.ndarray
    samples_camera_m: np.ndarray
    K: np.ndarray
    weight: float
    depth_noise_per_m: float
    huber_sigmas: float
    max_distance_m: float

    @property
    def sample_weight(self) -> float:
        """The factor on each sample's whitened squared residual: ``weight / M``."""
        return self.weight / max(1, len(self.samples_camera_m))


def _backproject_grid(depth_m: np.ndarray, K: np.ndarray, stride: int, min_depth_m: float, max_depth_m: float) -> np.ndarray:
    """(h, w, 3) camera-frame points of every ``stride``-th pixel of ``depth_m`` (H, W); zero where the depth is
    missing or outside ``[min_depth_m, max_depth_m]``."""
    z = depth_m[::stride, ::stride].astype(np.float64)
    z = np.where(np.isfinite(z) & (z >= min_depth_m) & (z <= max_depth_m), z, 0.0)
    rows, columns = np.mgrid[0:depth_m.shape[0]:stride, 0:depth_m.shape[1]:stride]
    x, y = pinhole_ray(columns.astype(np.float64), rows.astype(np.float64), K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    return np.stack([x * z, y * z, z], axis=-1)


def dense_reference(keyframe_id: int, depth_m: np.ndarray, K: np.ndarray, stride: int,
                    min_depth_m: float, max_depth_m: float) -> DenseReference:
    """Vertex and normal maps of a keyframe's depth (H, W) in metres; normals by central differences over the
    grid's neighbours, facing the camera."""
    points = _backproject_grid(depth_m, K, stride, min_depth_m, max_depth_m)
    z = points[..., 2]
    normals = np.zeros_like(points)
    dx = points[1:-1, 2:] - points[1:-1, :-2]
    dy = points[2:, 1:-1] - points[:-2, 1:-1]
    normal = np.cross(dx, dy)
    length = np.linalg.norm(normal, axis=-1)
    centre = z[1:-1, 1:-1]
    neighbours = np.stack([z[1:-1, 2:], z[1:-1, :-2], z[2:, 1:-1], z[:-2, 1:-1]])
    smooth = (centre > 0) & np.all(neighbours > 0, axis=0) & np.all(np.abs(neighbours - centre) <= EDGE_RATIO * centre, axis=0)
    ok = smooth & (length > 0)
    normal = np.where(ok[..., None], normal / np.where(length > 0, length, 1.0)[..., None], 0.0)
    # Face the camera: n . p < 0.
    facing = np.sign(-np.einsum("ijk,ijk->ij", normal, points[1:-1, 1:-1]))
    normals[1:-1, 1:-1] = normal * np.where(facing == 0, 1.0, facing)[..., None]
    return DenseReference(keyframe_id, stride, points, normals)


def dense_samples(depth_m: np.ndarray, K: np.ndarray, stride: int, min_depth_m: float, max_depth_m: float) -> np.ndarray:
    """(M, 3) camera-frame points of the valid depths (H, W) on every ``stride``-th pixel."""
    points = _backproject_grid(depth_m, K, stride, min_depth_m, max_depth_m).reshape(-1, 3)
    return np.ascontiguousarray(points[points[:, 2] > 0])


@numba.njit(cache=True, nogil=True)
def _dense_system(camera_from_world, reference_from_world, samples, reference_points, normals, stride, fx, fy, cx, cy,
                  sample_weight, noise, huber, max_distance, with_reference, with_system, cells, reuse_cells):
    """Point-to-plane Gauss-Newton system over the camera's update (size 6) or, ``with_reference``, over
    ``[delta_camera, delta_reference]`` (size 12): ``(H, g, cost, associated count)``; without ``with_system``
    H and g stay zero (the cost alone). ``cells`` (M,) int64 holds each sample's association as the flat index
    ``row * w + column`` of its reference cell, -1 for none: with ``reuse_cells`` the samples keep those (and no
    distance gate applies), otherwise they are associated here and, where ``cells`` is not empty, written to it."""
    size = 12 if with_reference else 6
    hessian = np.zeros((size, size))
    gradient = np.zeros(size)
    cost = 0.0
    count = 0
    # reference_from_camera = reference_from_world @ inverse(camera_from_world)
    rotation = np.zeros((3, 3))
    translation = reference_from_world[:3, 3].copy()
    for a in range(3):
        for b in range(3):
            for c in range(3):
                rotation[a, b] += reference_from_world[a, c] * camera_from_world[b, c]
    for a in range(3):
        for b in range(3):
            translation[a] -= rotation[a, b] * camera_from_world[b, 3]
    height, width = normals.shape[0], normals.shape[1]
    jacobian = np.zeros(size)
    for i in range(samples.shape[0]):
        px, py, pz = samples[i, 0], samples[i, 1], samples[i, 2]
        x = rotation[0, 0] * px + rotation[0, 1] * py + rotation[0, 2] * pz + translation[0]
        y = rotation[1, 0] * px + rotation[1, 1] * py + rotation[1, 2] * pz + translation[1]
        z = rotation[2, 0] * px + rotation[2, 1] * py + rotation[2, 2] * pz + translation[2]
        if reuse_cells:
            if cells[i] < 0:
                continue
            row, column = cells[i] // width, cells[i] % width
        else:
            if cells.shape[0] > 0:
                cells[i] = -1
            if z <= MIN_DEPTH_M:
                continue
            u, v = pinhole_numba(x, y, z, fx, fy, cx, cy)
            column = int(np.floor(u / stride + 0.5))
            row = int(np.floor(v / stride + 0.5))
            if column < 0 or row < 0 or column >= width or row >= height:
                continue
        nx, ny, nz = normals[row, column, 0], normals[row, column, 1], normals[row, column, 2]
        if nx == 0.0 and ny == 0.0 and nz == 0.0:
            continue
        qx, qy, qz = reference_points[row, column, 0], reference_points[row, column, 1], reference_points[row, column, 2]
        residual = nx * (qx - x) + ny * (qy - y) + nz * (qz - z)
        if not reuse_cells:
            if abs(residual) > max_distance:
                continue
            if cells.shape[0] > 0:
                cells[i] = row * width + column
        sigma2 = noise * noise * (qz * qz * qz * qz + pz * pz * pz * pz)
        whitened2 = residual * residual / sigma2
        kernel = 1.0
        if whitened2 > huber * huber:
            kernel = huber / np.sqrt(whitened2)
            cost += sample_weight * (2.0 * huber * np.sqrt(whitened2) - huber * huber)
        else:
            cost += sample_weight * whitened2
        count += 1
        if not with_system:
            continue
        # m = R^T n: the normal in the current camera; J = [m, p x m].
        mx = rotation[0, 0] * nx + rotation[1, 0] * ny + rotation[2, 0] * nz
        my = rotation[0, 1] * nx + rotation[1, 1] * ny + rotation[2, 1] * nz
        mz = rotation[0, 2] * nx + rotation[1, 2] * ny + rotation[2, 2] * nz
        jacobian[0], jacobian[1], jacobian[2] = mx, my, mz
        jacobian[3], jacobian[4], jacobian[5] = py * mz - pz * my, pz * mx - px * mz, px * my - py * mx
        if with_reference:
            # Moving the reference by exp(delta) moves p_ref = (x, y, z) by rho + phi x p_ref: J = -[n, p_ref x n].
            jacobian[6], jacobian[7], jacobian[8] = -nx, -ny, -nz
            jacobian[9], jacobian[10], jacobian[11] = -(y * nz - z * ny), -(z * nx - x * nz), -(x * ny - y * nx)
        w = kernel * sample_weight / sigma2
        for j in range(size):
            gradient[j] += w * jacobian[j] * residual
            for k in range(j, size):
                hessian[j, k] += w * jacobian[j] * jacobian[k]
    for j in range(size):
        for k in range(j):
            hessian[j, k] = hessian[k, j]
    return hessian, gradient, cost, count


@numba.njit(cache=True, nogil=True)
def dense_normal_equations_numba(camera_from_world, reference_from_world, samples, reference_points, normals, stride,
                                 fx, fy, cx, cy, sample_weight, noise, huber, max_distance):
    """Point-to-plane Gauss-Newton system ``(H (6, 6), g (6,), cost, associated count)``; see the module docstring."""
    return _dense_system(camera_from_world, reference_from_world, samples, reference_points, normals, stride,
                         fx, fy, cx, cy, sample_weight, noise, huber, max_distance, False, True, np.empty(0, np.int64),
                         False)


def kernel_arguments(term: DenseTerm | None) -> tuple:
    """The dense term as the kernels' positional arguments after ``camera_from_world`` (an empty term if None)."""
    if term is None:
        return (np.eye(4), np.zeros((0, 3)), np.zeros((1, 1, 3)), np.zeros((1, 1, 3)), 1, 1.0, 1.0, 0.0, 0.0, 0.0,
                1.0, 1.0, 0.0)
    K = term.K
    return (np.ascontiguousarray(term.reference_from_world, np.float64), np.ascontiguousarray(term.samples_camera_m, np.float64),
            np.ascontiguousarray(term.reference.points_camera_m, np.float64), np.ascontiguousarray(term.reference.normals, np.float64),
            int(term.reference.stride), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), term.sample_weight,
            term.depth_noise_per_m, term.huber_sigmas, term.max_distance_m)


def dense_normal_equations(camera_from_world: np.ndarray, term: DenseTerm) -> tuple[np.ndarray, np.ndarray, float, int]:
    """``(H (6, 6), g (6,), robust cost, associated samples)`` of the term at ``camera_from_world``, associations
    made at this pose; the update is ``delta = -H^-1 g`` (with any other term's system added)."""
    return dense_normal_equations_numba(np.ascontiguousarray(camera_from_world, np.float64), *kernel_arguments(term))


@dataclasses.dataclass
class DepthAlignment:
    """The pose the depth term alone gives a frame (:func:`align_depth`): ``camera_from_world`` (4, 4);
    ``associated_share``, the share of the frame's samples associated with the reference's surface there;
    ``conditioning``, the smallest eigenvalue of the term's Gauss-Newton matrix over its largest (rotation in
    radians, translation in metres): near 0 where the surface leaves a motion free, as a single plane leaves the
    slide along it and the turn about its normal."""

    camera_from_world: np.ndarray
    associated_share: float
    conditioning: float


def align_depth(camera_from_world: np.ndarray, term: DenseTerm, iterations: int = 30) -> DepthAlignment:
    """Gauss-Newton on the depth term alone from ``camera_from_world`` (4, 4), re-associating at every step, for at
    most ``iterations`` steps (projective ICP against the reference keyframe's surface)."""
    pose = np.array(camera_from_world, np.float64)
    for _ in range(iterations):
        hessian, gradient, _, _ = dense_normal_equations(pose, term)
        try:
            delta = -np.linalg.solve(hessian + 1e-9 * np.eye(6), gradient)
        except np.linalg.LinAlgError:
            break
        pose = orthonormalised(exp_se3(delta) @ pose)
        if np.linalg.norm(delta) < 1e-6:
            break
    hessian, _, _, associated = dense_normal_equations(pose, term)
    eigenvalues = np.linalg.eigvalsh(hessian)
    conditioning = float(eigenvalues[0] / eigenvalues[-1]) if eigenvalues[-1] > 0 else 0.0
    return DepthAlignment(pose, associated / max(1, len(term.samples_camera_m)), max(0.0, conditioning))


def _checked_cells(cells: np.ndarray, term: DenseTerm, read: bool) -> np.ndarray:
    """``cells`` if the kernel may write (and, ``read``, index) it for ``term``: one int64 per sample, each cell -1 or
    on the reference's grid; the kernel itself does not check, and out of bounds it would touch other memory."""
    height, width = term.reference.normals.shape[:2]
    if cells.dtype != np.int64 or cells.shape != (len(term.samples_camera_m),) or not cells.flags.c_contiguous:
        raise ValueError(f"cells must be a contiguous int64 array of {len(term.samples_camera_m)} samples, got "
                         f"{cells.dtype} {cells.shape}")
    if read and len(cells) and not (-1 <= cells.min() and cells.max() < height * width):
        raise ValueError(f"cells must lie in [-1, {height * width}) for a {width}x{height} reference grid")
    return cells


def dense_pair_normal_equations(camera_from_world: np.ndarray, reference_from_world: np.ndarray, term: DenseTerm,
                                cells: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float, int]:
    """``(H (12, 12), g (12,), robust cost, associated samples)`` of the term with the reference's pose
    ``reference_from_world`` variable too (``term.reference_from_world`` is not used), over
    ``[delta_camera, delta_reference]``, associations made at these poses; ``cells`` (M,) int64, where given,
    receives them (each sample's flat reference cell index, -1 for none) for :func:`dense_pair_cost`."""
    return _dense_system(np.ascontiguousarray(camera_from_world, np.float64),
                         np.ascontiguousarray(reference_from_world, np.float64), *kernel_arguments(term)[1:], True,
                         True, np.empty(0, np.int64) if cells is None else _checked_cells(cells, term, False), False)


def dense_pair_cost(camera_from_world: np.ndarray, reference_from_world: np.ndarray, term: DenseTerm,
                    cells: np.ndarray | None = None) -> float:
    """The term's robust cost at these two poses (``term.reference_from_world`` is not used), as
    :func:`dense_pair_normal_equations` gives it, without building the system; with ``cells`` (M,), the
    associations that function wrote, the samples keep them instead of being associated at these poses."""
    return _dense_system(np.ascontiguousarray(camera_from_world, np.float64),
                         np.ascontiguousarray(reference_from_world, np.float64), *kernel_arguments(term)[1:], False,
                         False, np.empty(0, np.int64) if cells is None else _checked_cells(cells, term, True),
                         cells is not None)[2]


def dense_residuals_reference(camera_from_world: np.ndarray, term: DenseTerm,
                              cells: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Slow twin's association, with numpy: ``(residual (M,), sigma^2 (M,), associated (M,) bool, normals (M, 3),
    cells (M,))`` per sample (residual 0, sigma^2 1 and normal 0 where a sample has no association; ``cells`` the
    flat reference cell index, -1 for none). Given ``cells``, the samples keep those associations, ungated."""
    reference = term.reference
    points_reference = transform_points(term.reference_from_world @ inverse(camera_from_world), term.samples_camera_m)
    z = points_reference[:, 2]
    in_front = z > MIN_DEPTH_M
    safe_z = np.where(in_front, z, 1.0)
    K = term.K
    u, v = pinhole(points_reference[:, 0], points_reference[:, 1], safe_z, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    column = np.floor(u / reference.stride + 0.5).astype(np.int64)
    row = np.floor(v / reference.stride + 0.5).astype(np.int64)
    height, width = reference.normals.shape[:2]
    inside = in_front & (column >= 0) & (row >= 0) & (column < width) & (row < height)
    if cells is not None:
        inside = cells >= 0
        row, column = np.divmod(cells, width)
    row, column = np.where(inside, row, 0), np.where(inside, column, 0)
    normals = reference.normals[row, column]
    vertices = reference.points_camera_m[row, column]
    residual = np.einsum("ij,ij->i", normals, vertices - points_reference)
    associated = inside & np.any(normals != 0, axis=1)
    if cells is None:
        associated &= np.abs(residual) <= term.max_distance_m
    sigma2 = term.depth_noise_per_m**2 * (vertices[:, 2] ** 4 + term.samples_camera_m[:, 2] ** 4)
    return (np.where(associated, residual, 0.0), np.where(associated, sigma2, 1.0), associated,
            np.where(associated[:, None], normals, 0.0), np.where(associated, row * width + column, -1))


def dense_jacobian_reference(camera_from_world: np.ndarray, term: DenseTerm,
                             cells: np.ndarray | None = None) -> np.ndarray:
    """(M, 6) d(residual)/d(delta) per sample, zero where a sample has no association.

    r = n . (q - p_ref) with q, n held at their association and p_ref(delta) = A exp(-delta) p (A =
    reference_from_camera; the left update of camera_from_world is exp(-delta) on the right of
    world_from_camera), so dr/d(delta) = n^T R_A [I, -hat(p)].
    """
    normals = dense_residuals_reference(camera_from_world, term, cells)[3]
    rotation = (term.reference_from_world @ inverse(camera_from_world))[:3, :3]
    points = term.samples_camera_m
    point_by_delta = np.zeros((len(points), 3, 6))
    point_by_delta[:, 0, 0] = point_by_delta[:, 1, 1] = point_by_delta[:, 2, 2] = 1.0
    x, y, z = points.T
    point_by_delta[:, 0, 4], point_by_delta[:, 0, 5] = z, -y
    point_by_delta[:, 1, 3], point_by_delta[:, 1, 5] = -z, x
    point_by_delta[:, 2, 3], point_by_delta[:, 2, 4] = y, -x
    return np.einsum("ni,ij,njk->nk", normals, rotation, point_by_delta)


def dense_normal_equations_reference(camera_from_world: np.ndarray, term: DenseTerm) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Slow twin of :func:`dense_normal_equations`, on whole arrays with :func:`dense_jacobian_reference`."""
    return _robust_system(camera_from_world, term, dense_jacobian_reference(camera_from_world, term))


def _robust_system(camera_from_world: np.ndarray, term: DenseTerm, jacobian: np.ndarray,
                   cells: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float, int]:
    """The twins' Huber-weighted Gauss-Newton system of the term's residuals at ``camera_from_world`` with
    ``jacobian`` (M, n): ``(H (n, n), g (n,), robust cost, associated samples)``; ``cells`` as in
    :func:`dense_residuals_reference`."""
    residual, sigma2, associated = dense_residuals_reference(camera_from_world, term, cells)[:3]
    whitened2 = residual**2 / sigma2
    huber, huber2 = term.huber_sigmas, term.huber_sigmas**2
    kernel = np.where(whitened2 <= huber2, 1.0, huber / np.sqrt(np.maximum(whitened2, 1e-300)))
    cost = np.where(whitened2 <= huber2, whitened2, 2.0 * huber * np.sqrt(whitened2) - huber2)
    weight = np.where(associated, kernel * term.sample_weight / sigma2, 0.0)
    hessian = np.einsum("n,ni,nj->ij", weight, jacobian, jacobian)
    gradient = np.einsum("n,ni,n->i", weight, jacobian, residual)
    return hessian, gradient, float(term.sample_weight * cost[associated].sum()), int(associated.sum())


def dense_pair_jacobian_reference(camera_from_world: np.ndarray, term: DenseTerm,
                                  cells: np.ndarray | None = None) -> np.ndarray:
    """(M, 12) d(residual)/d([delta_camera, delta_reference]) per sample, zero where a sample has no association:
    the camera's block is :func:`dense_jacobian_reference`; moving the reference by ``exp(delta)`` moves
    ``p_ref`` by ``rho + phi x p_ref`` with q, n held, so its block is ``-[n, p_ref x n]``."""
    normals = dense_residuals_reference(camera_from_world, term, cells)[3]
    points_reference = transform_points(term.reference_from_world @ inverse(camera_from_world), term.samples_camera_m)
    reference_block = -np.concatenate([normals, np.cross(points_reference, normals)], axis=1)
    return np.concatenate([dense_jacobian_reference(camera_from_world, term, cells), reference_block], axis=1)


def dense_pair_normal_equations_reference(camera_from_world: np.ndarray, reference_from_world: np.ndarray,
                                          term: DenseTerm, cells: np.ndarray | None = None,
                                          ) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Slow twin of :func:`dense_pair_normal_equations` and, with ``cells`` (associations held), of
    :func:`dense_pair_cost`; on whole arrays with :func:`dense_pair_jacobian_reference`."""
    term = dataclasses.replace(term, reference_from_world=reference_from_world)
    return _robust_system(camera_from_world, term, dense_pair_jacobian_reference(camera_from_world, term, cells), cells)
