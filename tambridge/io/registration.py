"""Colour resampled into the depth camera, for sensors whose colour and depth images are not registered.

A Kinect v1 (7-Scenes) records colour and depth with two cameras a few centimetres apart and of different focal
lengths (525 and 585 px): taken pixel for pixel, a colour feature is lifted with the depth of another surface, up to
30 px away at the image border. Here every depth pixel's 3D point is projected into the colour camera and the colour
image is sampled there, so the frame is the depth camera's: its trajectory is the one the depth sensor's ground
truth (KinectFusion's, on 7-Scenes) describes, and depth needs no resampling (no surfaces invented at edges).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from tambridge.camera import Camera

# Where depth is missing, colour is looked up with the farthest valid depth in a block of this many pixels: missing
# Kinect depth is mostly the shadow a foreground edge casts on the background, so the background's depth is the
# better guess there; the parallax it can get wrong is fx_colour * baseline * |1/z - 1/z_guess| pixels.
FILL_BLOCK_PX = 16
# Depths between which valid_region's pixels sample inside the colour image (closer points shift further).
VALID_REGION_DEPTHS_M = (0.4, 1e6)


@dataclasses.dataclass(frozen=True)
class ColourToDepth:
    """How to resample colour into the depth camera.

    ``depth_camera``: intrinsics of the depth images (the frames' camera, no distortion). ``colour_camera``: of
    the colour images, with their distortion. ``colour_from_depth``: (4, 4) float64 rigid transform of points
    from the depth camera's frame into the colour camera's (OpenCV frames, metres).
    """

    depth_camera: Camera
    colour_camera: Camera
    colour_from_depth: np.ndarray

    def __post_init__(self) -> None:
        # Each depth pixel's ray rotated into the colour frame, computed once: per frame only z scales it.
        camera = self.depth_camera
        rows, cols = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
        rays = camera.backproject(np.stack([cols, rows], -1), 1.0)
        object.__setattr__(self, "_rotated_rays", (rays @ self.colour_from_depth[:3, :3].T).astype(np.float32))

    def colour_maps(self, lookup_depth_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) float32 colour-image x and y, in pixels, seen by each depth pixel at ``lookup_depth_m`` (> 0)."""
        points = self._rotated_rays * lookup_depth_m[..., None] + self.colour_from_depth[:3, 3].astype(np.float32)
        x = points[..., 0] / points[..., 2]
        y = points[..., 1] / points[..., 2]
        camera = self.colour_camera
        if camera.has_distortion:
            x, y = distort_normalised(x, y, camera.distortion)
        # The distorted normalised coordinates are a point at z = 1, which the pinhole projection takes to pixels.
        pixels = camera.project(np.stack([x, y, np.ones_like(x)], -1)).astype(np.float32)
        return pixels[..., 0], pixels[..., 1]

    def colour_in_depth_camera(self, colour: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 ``colour`` (colour camera) resampled onto the depth camera's pixels by ``depth_m`` (H, W).

        Bilinear; pixels whose ray leaves the colour image are black (``valid_region`` excludes them). One numba
        pass without the GIL, as it runs in the frame prefetcher's thread beside tracking;
        :meth:`colour_in_depth_camera_reference` is its slow twin.
        """
        from tambridge.io.registration_kernel import resample_colour

        camera = self.colour_camera
        distortion = np.array((list(camera.distortion) + [0.0] * 5)[:5], np.float32)
        out = np.empty((self.depth_camera.height, self.depth_camera.width, 3), np.uint8)
        resample_colour(
            np.ascontiguousarray(colour), fill_missing_depth(depth_m), self._rotated_rays,
            self.colour_from_depth[:3, 3].astype(np.float32),
            np.array([camera.fx, camera.fy, camera.cx, camera.cy], np.float32), distortion, out,
        )
        return out

    def colour_in_depth_camera_reference(self, colour: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
        """The slow, plain-numpy twin of :meth:`colour_in_depth_camera` (tests compare the two)."""
        map_x, map_y = self.colour_maps(fill_missing_depth(depth_m))
        return bilinear_or_black(colour, map_x, map_y)

    def inside_colour_image(self) -> np.ndarray:
        """(H, W) bool: depth pixels that sample inside the colour image at every depth of VALID_REGION_DEPTHS_M."""
        camera = self.colour_camera
        inside = np.ones((self.depth_camera.height, self.depth_camera.width), bool)
        for depth in VALID_REGION_DEPTHS_M:
            inside &= camera.in_image(np.stack(self.colour_maps(np.full(inside.shape, depth, np.float32)), -1))
        return inside


def bilinear_or_black(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """(H, W, C) uint8 samples of (Hi, Wi, C) uint8 ``image`` at float pixel coordinates (H, W), rounded to nearest;
    0 where a coordinate lies outside [0, Wi - 1] x [0, Hi - 1]."""
    height, width = image.shape[:2]
    inside = (map_x >= 0) & (map_x <= width - 1) & (map_y >= 0) & (map_y <= height - 1)
    x = np.where(inside, map_x, 0).astype(np.float32)
    y = np.where(inside, map_y, 0).astype(np.float32)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    x1 = np.minimum(x0 + 1, width - 1)
    y1 = np.minimum(y0 + 1, height - 1)
    ax = (x - x0)[..., None]
    ay = (y - y0)[..., None]
    values = image.astype(np.float32)
    top = values[y0, x0] * (1 - ax) + values[y0, x1] * ax
    bottom = values[y1, x0] * (1 - ax) + values[y1, x1] * ax
    sampled = top * (1 - ay) + bottom * ay
    return np.where(inside[..., None], np.floor(sampled + 0.5), 0).astype(np.uint8)


def distort_normalised(x: np.ndarray, y: np.ndarray, distortion: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's (k1 k2 p1 p2 k3) distortion of normalised image coordinates (as ``cv2.projectPoints``)."""
    k1, k2, p1, p2, k3 = (list(distortion) + [0.0] * 5)[:5]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def fill_missing_depth(depth_m: np.ndarray, block_px: int = FILL_BLOCK_PX) -> np.ndarray:
    """(H, W) float32 ``depth_m`` with each 0 replaced by the largest valid depth of its block; blocks without
    valid depth take the median of the other blocks' largest depths."""
    valid = depth_m > 0
    if valid.all():
        return depth_m
    if not valid.any():
        return np.full_like(depth_m, 2.0)  # nothing to go by: a typical indoor distance
    height, width = depth_m.shape
    blocks_y, blocks_x = -(-height // block_px), -(-width // block_px)
    padded = np.zeros((blocks_y * block_px, blocks_x * block_px), np.float32)
    padded[:height, :width] = depth_m
    block_max = padded.reshape(blocks_y, block_px, -1).max(axis=1).reshape(blocks_y, blocks_x, block_px).max(axis=2)
    empty = block_max == 0
    if empty.any():
        # Over the blocks, not the pixels: a median over every pixel cost more than all the rest.
        block_max[empty] = np.median(block_max[~empty])
    guess = cv2.resize(block_max, padded.shape[::-1], interpolation=cv2.INTER_NEAREST)[:height, :width]
    filled = depth_m.astype(np.float32, copy=True)
    np.copyto(filled, guess, where=~valid)
    return filled

