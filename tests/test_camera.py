"""The pinhole model of tambridge.camera: its numpy, torch and numba forms against each other and OpenCV."""

import cv2
import numba
import numpy as np
import pytest
import torch

from tambridge.camera import Camera, pinhole_inverse_depth_numba, pinhole_numba

CAMERA = Camera(640, 480, 517.3, 516.5, 318.6, 255.3)


def _points(count: int, seed: int = 0) -> np.ndarray:
    """(count, 3) camera-frame points in front of the camera, metres."""
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-2.0, 2.0, count), rng.uniform(-1.5, 1.5, count), rng.uniform(0.3, 6.0, count)])


@numba.njit(cache=True)
def _project_numba(points, fx, fy, cx, cy, inverse_depth):
    out = np.empty((points.shape[0], 2))
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if inverse_depth:
            out[i, 0], out[i, 1] = pinhole_inverse_depth_numba(x, y, 1.0 / z, fx, fy, cx, cy)
        else:
            out[i, 0], out[i, 1] = pinhole_numba(x, y, z, fx, fy, cx, cy)
    return out


def test_project_matches_opencv():
    points = _points(500)
    expected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), CAMERA.K, np.zeros(5))
    np.testing.assert_allclose(CAMERA.project(points), expected[:, 0], rtol=0, atol=1e-9)


def test_pixel_centres_sit_at_integer_coordinates():
    # The optical axis hits the principal point; pixel centres of an image resized by 2 keep the scene points.
    np.testing.assert_array_equal(CAMERA.project(np.array([0.0, 0.0, 2.0])), [CAMERA.cx, CAMERA.cy])
    points = _points(20, seed=1)
    halved = CAMERA.scaled(0.5)
    np.testing.assert_allclose(halved.project(points), (CAMERA.project(points) + 0.5) * 0.5 - 0.5, atol=1e-9)


def test_backproject_inverts_project():
    points = _points(500, seed=2)
    np.testing.assert_allclose(CAMERA.backproject(CAMERA.project(points), points[:, 2]), points, rtol=0, atol=1e-12)
    pixels = np.array([[0.0, 0.0], [639.0, 479.0], [CAMERA.cx, CAMERA.cy]])
    np.testing.assert_allclose(CAMERA.project(CAMERA.backproject(pixels, 3.0)), pixels, rtol=0, atol=1e-9)
    rays = CAMERA.backproject(pixels, 1.0)  # one depth for all: the rays, z = 1
    np.testing.assert_array_equal(rays[:, 2], [1.0, 1.0, 1.0])
    np.testing.assert_allclose(rays[2], [0.0, 0.0, 1.0], atol=1e-15)


def test_numpy_and_torch_twins_agree_bit_for_bit():
    points = _points(300, seed=3)
    depth = np.where(points[:, 2] > 1.0, points[:, 2], 1.0)
    np.testing.assert_array_equal(CAMERA.project_torch(torch.from_numpy(points)).numpy(), CAMERA.project(points))
    np.testing.assert_array_equal(CAMERA.project_torch(torch.from_numpy(points), torch.from_numpy(depth)).numpy(),
                                  CAMERA.project(points, depth))
    pixels = CAMERA.project(points)
    np.testing.assert_array_equal(
        CAMERA.backproject_torch(torch.from_numpy(pixels), torch.from_numpy(points[:, 2])).numpy(),
        CAMERA.backproject(pixels, points[:, 2]),
    )


def test_twins_keep_dtype_and_shape():
    points = _points(12, seed=4).reshape(3, 4, 3)
    assert CAMERA.project(points.astype(np.float32)).dtype == np.float32
    assert CAMERA.project(points).shape == (3, 4, 2)
    projected = CAMERA.project_torch(torch.from_numpy(points).float())
    assert projected.dtype == torch.float32 and projected.shape == (3, 4, 2)
    lifted = CAMERA.backproject_torch(projected, torch.from_numpy(points[..., 2]).float())
    assert lifted.dtype == torch.float32 and lifted.shape == (3, 4, 3)
    torch.testing.assert_close(lifted, torch.from_numpy(points).float(), rtol=1e-5, atol=1e-5)


def test_torch_twins_gradients_match_finite_differences():
    points = torch.from_numpy(_points(6, seed=5)).requires_grad_(True)
    assert torch.autograd.gradcheck(CAMERA.project_torch, (points,))
    pixels = torch.from_numpy(CAMERA.project(_points(6, seed=6))).requires_grad_(True)
    depth = torch.linspace(0.5, 4.0, 6, dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(CAMERA.backproject_torch, (pixels, depth))


@pytest.mark.parametrize("inverse_depth", [False, True])
def test_numba_projection_matches_camera_project(inverse_depth):
    points = _points(400, seed=7)
    projected = _project_numba(points, CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy, inverse_depth)
    if inverse_depth:  # multiplies by 1/z instead of dividing by z: equal up to rounding
        np.testing.assert_allclose(projected, CAMERA.project(points), rtol=0, atol=1e-9)
    else:
        np.testing.assert_array_equal(projected, CAMERA.project(points))


def test_in_image_is_bounded_by_the_outermost_pixel_centres():
    pixels = np.array([[0.0, 0.0], [639.0, 479.0], [-1e-9, 10.0], [10.0, 479.000001], [np.nan, 5.0], [320.0, 240.0]])
    expected = [True, True, False, False, False, True]
    np.testing.assert_array_equal(CAMERA.in_image(pixels), expected)
    np.testing.assert_array_equal(CAMERA.in_image(torch.from_numpy(pixels)).numpy(), expected)


def test_mean_focal_length():
    assert CAMERA.mean_focal_px == pytest.approx(516.9, abs=1e-12)
    assert CAMERA.scaled(0.5).mean_focal_px == pytest.approx(258.45, abs=1e-12)
