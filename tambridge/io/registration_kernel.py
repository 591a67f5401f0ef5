"""Numba kernel of :meth:`tambridge.io.registration.ColourToDepth.colour_in_depth_camera` (imported on first use)."""

from __future__ import annotations

import numba
import numpy as np

from tambridge.camera import pinhole_numba


@numba.njit(cache=True, nogil=True, fastmath=True, error_model="numpy")
def resample_colour(
    colour: np.ndarray,
    lookup_depth_m: np.ndarray,
    rotated_rays: np.ndarray,
    translation_m: np.ndarray,
    intrinsics: np.ndarray,
    distortion: np.ndarray,
    out: np.ndarray,
) -> None:
    """Fill ``out`` (H, W, 3) uint8 with ``colour`` (Hc, Wc, 3) uint8 sampled where each depth pixel's point lands.

    ``lookup_depth_m`` (H, W) > 0; ``rotated_rays`` (H, W, 3): depth-camera rays in the colour frame; the point is
    ``ray * z + translation_m``; ``intrinsics`` = (fx, fy, cx, cy) and ``distortion`` = (k1, k2, p1, p2, k3) of the
    colour camera. The arithmetic of ``colour_maps`` + ``bilinear_or_black`` (float32, round half up), compiled with
    fastmath (for speed) and with the bilinear weights taken once per pixel: reordered float operations may move a
    channel by one grey level (tests/test_registration.py).
    """
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    tx, ty, tz = translation_m[0], translation_m[1], translation_m[2]
    k1, k2, p1, p2, k3 = distortion[0], distortion[1], distortion[2], distortion[3], distortion[4]
    distorted = k1 != 0 or k2 != 0 or p1 != 0 or p2 != 0 or k3 != 0
    colour_height, colour_width = colour.shape[0], colour.shape[1]
    u_max, v_max = np.float32(colour_width - 1), np.float32(colour_height - 1)
    for row in range(out.shape[0]):
        for column in range(out.shape[1]):
            z = lookup_depth_m[row, column]
            inverse_pz = np.float32(1.0) / (rotated_rays[row, column, 2] * z + tz)
            x = (rotated_rays[row, column, 0] * z + tx) * inverse_pz
            y = (rotated_rays[row, column, 1] * z + ty) * inverse_pz
            if distorted:
                r2 = x * x + y * y
                radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
                x, y = (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                        y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)
            u, v = pinhole_numba(x, y, np.float32(1.0), fx, fy, cx, cy)  # (x, y) is a point at z = 1
            u, v = np.float32(u), np.float32(v)
            if not (u >= 0 and u <= u_max and v >= 0 and v <= v_max):
                out[row, column, 0] = 0
                out[row, column, 1] = 0
                out[row, column, 2] = 0
                continue
            x0 = int(u)  # u, v >= 0 here: truncation is floor
            y0 = int(v)
            x1 = x0 + 1 if x0 + 1 < colour_width else colour_width - 1
            y1 = y0 + 1 if y0 + 1 < colour_height else colour_height - 1
            ax = u - np.float32(x0)
            ay = v - np.float32(y0)
            # The four bilinear weights once per pixel, not per channel: a third of the work.
            w00, w01 = (1 - ax) * (1 - ay), ax * (1 - ay)
            w10, w11 = (1 - ax) * ay, ax * ay
            for channel in range(3):
                value = (w00 * np.float32(colour[y0, x0, channel]) + w01 * np.float32(colour[y0, x1, channel])
                         + w10 * np.float32(colour[y1, x0, channel]) + w11 * np.float32(colour[y1, x1, channel]))
                out[row, column, channel] = np.uint8(np.int32(value + np.float32(0.5)))
