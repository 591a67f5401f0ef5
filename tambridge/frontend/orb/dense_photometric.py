"""Dense photometric term of the motion-only refinement (direct alignment against a keyframe's intensities).

The reference keyframe contributes pixels of high intensity gradient on a grid, back-projected with its depth into
its camera frame, ``points_reference_m`` (M, 3), with their smoothed grey intensities ``intensities`` (M,) in
[0, 1] (:func:`photometric_reference`). For the pose ``camera_from_world`` of the current frame, a point goes to the
current camera, ``p = camera_from_world @ world_from_reference @ X``, is projected there, and the current frame's
smoothed grey image is sampled bilinearly: ``r = g I(pi(p)) - I_ref``. The gain ``g`` (the change of auto exposure
between the two images) is re-fitted at every evaluation, ``g = sum I_ref / sum I(pi(p))`` over the points that
land inside the image, and held fixed in the derivative. Residuals are whitened by ``sigma`` (intensity units),
weighted by ``weight / M`` (as the depth term: the whole term weighs as ``weight`` whitened residuals) and
down-weighted by Huber's kernel at ``huber_sigmas``. With the left update ``camera_from_world <- exp(delta) @
camera_from_world``, ``p <- p + rho + phi x p``, so ``dr/d(delta) = [a, p x a]`` with ``a = g grad I . d pi / d p``.
"""

from __future__ import annotations

import dataclasses

import cv2
import numba
import numpy as np

from tambridge.camera import pinhole_numba, pinhole_ray
from tambridge.frontend.orb.reprojection import MIN_DEPTH_M

# Gaussian smoothing of both images before sampling (px): widens the basin of the intensity's gradient.
SMOOTHING_SIGMA_PX = 1.0
# Neighbouring depths differing by more than this fraction of the depth are a depth edge: no point there
# (its intensity belongs to two surfaces).
EDGE_RATIO = 0.05


@dataclasses.dataclass
class PhotometricReference:
    """A keyframe's high-gradient pixels as ``points_camera_m`` (M, 3) in its camera frame and their smoothed
    grey ``intensities`` (M,) in [0, 1]."""

    keyframe_id: int
    points_camera_m: np.ndarray
    intensities: np.ndarray


@dataclasses.dataclass
class PhotometricImage:
    """The current frame's smoothed grey ``intensity`` (H, W) in [0, 1] and its per-pixel derivatives
    ``gradient_x``, ``gradient_y`` (H, W), all float64."""

    intensity: np.ndarray
    gradient_x: np.ndarray
    gradient_y: np.ndarray


@dataclasses.dataclass
class PhotometricTerm:
    """Everything the refinement needs for the photometric term of one frame (see the module docstring):
    ``world_from_reference`` (4, 4) the reference keyframe's pose, ``K`` (3, 3) the intrinsics of both images."""

    reference: PhotometricReference
    world_from_reference: np.ndarray
    image: PhotometricImage
    K: np.ndarray
    weight: float
    sigma: float
    huber_sigmas: float

    @property
    def sample_weight(self) -> float:
        """The factor on each point's whitened squared residual: ``weight / M``."""
        return self.weight / max(1, len(self.reference.intensities))


def smoothed_grey(rgb: np.ndarray) -> np.ndarray:
    """(H, W) float64 grey in [0, 1] of an RGB uint8 image (H, W, 3), Gaussian-smoothed by SMOOTHING_SIGMA_PX."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float64) / 255.0
    return cv2.GaussianBlur(grey, (0, 0), SMOOTHING_SIGMA_PX)


def photometric_image(rgb: np.ndarray) -> PhotometricImage:
    """The current frame's side of the term: smoothed grey and its central-difference derivatives (per pixel)."""
    intensity = smoothed_grey(rgb)
    gradient_x = cv2.Sobel(intensity, cv2.CV_64F, 1, 0, ksize=1, scale=0.5)
    gradient_y = cv2.Sobel(intensity, cv2.CV_64F, 0, 1, ksize=1, scale=0.5)
    return PhotometricImage(intensity, gradient_x, gradient_y)


def photometric_reference(keyframe_id: int, rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray, stride: int,
                          min_gradient: float, max_points: int, min_depth_m: float, max_depth_m: float) -> PhotometricReference:
    """The keyframe's pixels on every ``stride``-th pixel whose smoothed intensity gradient is at least
    ``min_gradient`` (per pixel, intensity in [0, 1]) with a valid depth away from depth edges; at most
    ``max_points``, spread evenly over the candidates in raster order."""
    image = photometric_image(rgb)
    z = depth_m[::stride, ::stride].astype(np.float64)
    valid = np.isfinite(z) & (z >= min_depth_m) & (z <= max_depth_m)
    z = np.where(valid, z, 0.0)
    smooth = np.zeros_like(valid)
    centre = z[1:-1, 1:-1]
    neighbours = np.stack([z[1:-1, 2:], z[1:-1, :-2], z[2:, 1:-1], z[:-2, 1:-1]])
    smooth[1:-1, 1:-1] = (centre > 0) & np.all(np.abs(neighbours - centre) <= EDGE_RATIO * centre, axis=0)
    gradient = np.hypot(image.gradient_x[::stride, ::stride], image.gradient_y[::stride, ::stride])
    rows, columns = np.nonzero(smooth & (gradient >= min_gradient))
    if len(rows) > max_points:
        keep = np.linspace(0, len(rows) - 1, max_points).round().astype(np.int64)
        rows, columns = rows[keep], columns[keep]
    depth = z[rows, columns]
    x, y = pinhole_ray((columns * stride).astype(np.float64), (rows * stride).astype(np.float64),
                       K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    points = np.stack([x * depth, y * depth, depth], axis=-1)
    intensities = image.intensity[rows * stride, columns * stride]
    return PhotometricReference(keyframe_id, np.ascontiguousarray(points), np.ascontiguousarray(intensities))


@numba.njit(cache=True, inline="always")
def _bilinear(image, u, v):
    column, row = int(np.floor(u)), int(np.floor(v))
    a, b = u - column, v - row
    return ((1.0 - a) * (1.0 - b) * image[row, column] + a * (1.0 - b) * image[row, column + 1]
            + (1.0 - a) * b * image[row + 1, column] + a * b * image[row + 1, column + 1])


@numba.njit(cache=True, nogil=True)
def photometric_normal_equations_numba(camera_from_world, world_from_reference, points, intensities, image,
                                       gradient_x, gradient_y, fx, fy, cx, cy, sample_weight, sigma, huber):
    """Photometric Gauss-Newton system ``(H (6, 6), g (6,), cost, count of points in the image)``; see the
    module docstring."""
    hessian = np.zeros((6, 6))
    gradient = np.zeros(6)
    n = points.shape[0]
    if n == 0:
        return hessian, gradient, 0.0, 0
    transform = camera_from_world @ world_from_reference
    height, width = image.shape[0], image.shape[1]
    projected = np.zeros((n, 5))  # x, y, z, u, v
    inside = np.zeros(n, np.bool_)
    sum_reference, sum_current = 0.0, 0.0
    for i in range(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        x = transform[0, 0] * px + transform[0, 1] * py + transform[0, 2] * pz + transform[0, 3]
        y = transform[1, 0] * px + transform[1, 1] * py + transform[1, 2] * pz + transform[1, 3]
        z = transform[2, 0] * px + transform[2, 1] * py + transform[2, 2] * pz + transform[2, 3]
        if z <= MIN_DEPTH_M:
            continue
        u, v = pinhole_numba(x, y, z, fx, fy, cx, cy)
        if u < 0.0 or v < 0.0 or u >= width - 1.0 or v >= height - 1.0:
            continue
        inside[i] = True
        projected[i, 0], projected[i, 1], projected[i, 2], projected[i, 3], projected[i, 4] = x, y, z, u, v
        sum_reference += intensities[i]
        sum_current += _bilinear(image, u, v)
    if sum_current <= 0.0:
        return hessian, gradient, 0.0, 0
    gain = sum_reference / sum_current
    cost = 0.0
    count = 0
    inv_sigma2 = 1.0 / (sigma * sigma)
    jacobian = np.zeros(6)
    for i in range(n):
        if not inside[i]:
            continue
        x, y, z, u, v = projected[i, 0], projected[i, 1], projected[i, 2], projected[i, 3], projected[i, 4]
        residual = gain * _bilinear(image, u, v) - intensities[i]
        whitened2 = residual * residual * inv_sigma2
        kernel = 1.0
        if whitened2 > huber * huber:
            kernel = huber / np.sqrt(whitened2)
            cost += sample_weight * (2.0 * huber * np.sqrt(whitened2) - huber * huber)
        else:
            cost += sample_weight * whitened2
        count += 1
        du, dv = gain * _bilinear(gradient_x, u, v), gain * _bilinear(gradient_y, u, v)
        inv_z = 1.0 / z
        ax, ay = du * fx * inv_z, dv * fy * inv_z
        az = -(ax * x + ay * y) * inv_z
        jacobian[0], jacobian[1], jacobian[2] = ax, ay, az
        jacobian[3], jacobian[4], jacobian[5] = y * az - z * ay, z * ax - x * az, x * ay - y * ax
        w = kernel * sample_weight * inv_sigma2
        for j in range(6):
            gradient[j] += w * jacobian[j] * residual
            for k in range(j, 6):
                hessian[j, k] += w * jacobian[j] * jacobian[k]
    for j in range(6):
        for k in range(j):
            hessian[j, k] = hessian[k, j]
    return hessian, gradient, cost, count


def photometric_kernel_arguments(term: PhotometricTerm | None) -> tuple:
    """The photometric term as the refinement kernel's positional arguments (an empty term if None)."""
    if term is None:
        empty = np.zeros((2, 2))
        return (np.eye(4), np.zeros((0, 3)), np.zeros(0), empty, empty, empty, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0)
    K, image = term.K, term.image
    return (np.ascontiguousarray(term.world_from_reference, np.float64), term.reference.points_camera_m,
            term.reference.intensities, image.intensity, image.gradient_x, image.gradient_y,
            float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), term.sample_weight, term.sigma,
            term.huber_sigmas)


def photometric_normal_equations(camera_from_world: np.ndarray, term: PhotometricTerm) -> tuple[np.ndarray, np.ndarray, float, int]:
    """``(H (6, 6), g (6,), robust cost, points in the image)`` of the term at ``camera_from_world``; the update
    is ``delta = -H^-1 g`` (with any other term's system added)."""
    return photometric_normal_equations_numba(np.ascontiguousarray(camera_from_world, np.float64),
                                              *photometric_kernel_arguments(term))
