"""Image helpers: sharpness falls with blur and is measured on a thumbnail."""

import cv2
import numpy as np

from tambridge.images import SHARPNESS_THUMBNAIL_PX, rgb_uint8, sharpness


def _checkerboard(height: int, width: int, square: int) -> np.ndarray:
    rows, columns = np.indices((height, width))
    grey = (((rows // square) + (columns // square)) % 2 * 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2)


def test_sharpness_falls_monotonically_with_blur():
    image = _checkerboard(480, 640, 16)
    scores = [sharpness(cv2.GaussianBlur(image, (0, 0), sigma)) if sigma else sharpness(image) for sigma in (0, 2, 4, 8)]
    assert all(a > 2.0 * b for a, b in zip(scores, scores[1:])), scores


def test_sharpness_is_the_laplacian_variance_of_the_thumbnail():
    image = _checkerboard(480, 640, 16)
    thumbnail = cv2.resize(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), (SHARPNESS_THUMBNAIL_PX, 120), interpolation=cv2.INTER_AREA)
    laplacian = cv2.filter2D(thumbnail.astype(np.float64), -1, np.array([[0, 1, 0], [1, -4, 1], [0, 1, 0]], np.float64),
                             borderType=cv2.BORDER_REFLECT_101)
    assert np.isclose(sharpness(image), laplacian.var(), rtol=1e-4)
    assert sharpness(np.full((60, 80, 3), 128, np.uint8)) == 0.0


def test_rgb_uint8_rounds_and_clips():
    assert rgb_uint8(np.array([[-0.1, 0.5, 1.2]])).tolist() == [[0, 128, 255]]
