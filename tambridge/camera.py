"""Pinhole camera intrinsics, the projection they define, TUM presets and camera files (YAML or ``key value`` text).

Pixel convention (OpenCV's): pixel ``(column, row)``'s centre sits at integer coordinates ``u = column, v = row``;
the image spans ``[-0.5, width - 0.5] x [-0.5, height - 0.5]``. Camera frame: x right, y down, z forward, metres.
The projection is written once, in :func:`pinhole` (and its inverse :func:`pinhole_ray`), as plain arithmetic
that numpy arrays, torch tensors and numba scalars all run; ``Camera`` wraps it for arrays, ``pinhole_numba``
and ``pinhole_inverse_depth_numba`` are its compiled forms for numba kernels.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import dataclasses
import re
from pathlib import Path

import numba
import numpy as np
import yaml

from tambridge.errors import CameraConfigError
from tambridge.files import config_file_names, find_config_file, load_yaml, read_text_file, yaml_error_line

if TYPE_CHECKING:
    import torch


def pinhole(x, y, z, fx, fy, cx, cy):
    """Pixel ``(u, v)`` of camera-frame coordinates ``x, y, z`` (metres, z > 0): ``u = fx * x / z + cx``.

    Elementwise over numpy arrays, torch tensors or scalars; the result has the dtype arithmetic on the inputs
    gives. Keep this operation order: the numba kernels and the torch projection must agree bit for bit.
    """
    return fx * x / z + cx, fy * y / z + cy


def pinhole_inverse_depth(x, y, inverse_z, fx, fy, cx, cy):
    """:func:`pinhole` with ``1 / z`` given: ``u = fx * x * inverse_z + cx`` (may differ from it in the last bit).

    For the RGB-D residual ``(u, v, 1/z)``, which needs ``1 / z`` anyway.
    """
    return fx * x * inverse_z + cx, fy * y * inverse_z + cy


def pinhole_ray(u, v, fx, fy, cx, cy):
    """Camera-frame ``(x, y)`` at depth z = 1 of pixel ``(u, v)``: the inverse of :func:`pinhole`."""
    return (u - cx) / fx, (v - cy) / fy


# The same arithmetic compiled for numba kernels, where a Camera method cannot be called (inlined at numba's IR
# level, so a kernel computes exactly what it did with the expression written out).
pinhole_numba = numba.njit(cache=True, inline="always")(pinhole)
pinhole_inverse_depth_numba = numba.njit(cache=True, inline="always")(pinhole_inverse_depth)
pinhole_ray_numba = numba.njit(cache=True, inline="always")(pinhole_ray)


def exposure_offsets_s(count: int, exposure_s: float) -> np.ndarray:
    """(count,) times, seconds from a frame's timestamp, that sample its exposure ``[t - e/2, t + e/2]``: the
    midpoints of ``count`` equal slices (0 among them for an odd count)."""
    return (np.arange(count) + 0.5) / count * exposure_s - exposure_s / 2.0


def rolling_shutter_row_times_s(rows_px: np.ndarray, height: int, readout_s: float) -> np.ndarray:
    """Times (N,), seconds from a frame's timestamp, at which a rolling shutter that reads ``height`` rows over
    ``readout_s`` takes the rows ``rows_px`` (N,): row ``v`` at ``(v / height - 1/2) readout_s``, the middle row at
    the timestamp."""
    return (np.asarray(rows_px, np.float64) / height - 0.5) * readout_s


@dataclasses.dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics of the colour camera, in pixels; ``distortion`` is OpenCV's (k1 k2 p1 p2 k3).
    ``rolling_shutter_s``: the colour image's rows are read top to bottom over this long, seconds
    (:func:`rolling_shutter_row_times_s`); 0 for a global shutter."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    rolling_shutter_s: float = 0.0

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix, float64."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def mean_focal_px(self) -> float:
        """``(fx + fy) / 2``, pixels: the one focal length where one number is wanted (a new Gaussian's radius of one
        pixel, ``r = z / f``; the mapper's pruning size ``f r / z``)."""
        return 0.5 * (self.fx + self.fy)

    def project(self, points_camera_m: np.ndarray, depth_m: np.ndarray | None = None) -> np.ndarray:
        """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)`` (metres, z > 0): ``u = fx x / z + cx``.

        ``depth_m`` (...,) is divided by instead of the points' z: a finite stand-in a caller puts in for points
        behind the camera, which it then masks out. Distortion is ignored (frames are undistorted by the reader).
        """
        z = points_camera_m[..., 2] if depth_m is None else depth_m
        u, v = pinhole(points_camera_m[..., 0], points_camera_m[..., 1], z, self.fx, self.fy, self.cx, self.cy)
        return np.stack([u, v], axis=-1)

    def project_torch(self, points_camera_m: "torch.Tensor", depth_m: "torch.Tensor | None" = None) -> "torch.Tensor":
        """Differentiable twin of :meth:`project` for tensors: ``(..., 3)`` -> ``(..., 2)``, same dtype and device."""
        import torch

        z = points_camera_m[..., 2] if depth_m is None else depth_m
        u, v = pinhole(points_camera_m[..., 0], points_camera_m[..., 1], z, self.fx, self.fy, self.cx, self.cy)
        return torch.stack([u, v], dim=-1)

    def backproject(self, pixels_px: np.ndarray, depth_m: np.ndarray | float) -> np.ndarray:
        """Camera-frame points ``(..., 3)`` (metres) of pixels ``(..., 2)`` at z-depths ``depth_m`` (...,) or one
        number: ``x = (u - cx) / fx * z``; at depth 1 these are the pixels' rays. Inverse of :meth:`project`."""
        x, y = pinhole_ray(pixels_px[..., 0], pixels_px[..., 1], self.fx, self.fy, self.cx, self.cy)
        return np.stack(np.broadcast_arrays(x * depth_m, y * depth_m, depth_m), axis=-1)

    def backproject_torch(self, pixels_px: "torch.Tensor", depth_m: "torch.Tensor") -> "torch.Tensor":
        """Differentiable twin of :meth:`backproject` for tensors: pixels ``(..., 2)`` and ``depth_m`` (...,) ->
        ``(..., 3)``, in their dtype and device."""
        import torch

        x, y = pinhole_ray(pixels_px[..., 0], pixels_px[..., 1], self.fx, self.fy, self.cx, self.cy)
        return torch.stack([x * depth_m, y * depth_m, depth_m], dim=-1)

    def depth_points(self, depth_m: np.ndarray, stride: int) -> np.ndarray:
        """Camera-frame points (M, 3), metres, of the valid (> 0) z-depths of ``depth_m`` (H, W) on every
        ``stride``-th pixel of its rows and columns."""
        rows, columns = np.mgrid[0 : self.height : stride, 0 : self.width : stride]
        depth = np.asarray(depth_m, np.float64)[rows, columns]
        valid = depth > 0
        return self.backproject(np.stack([columns, rows], axis=-1)[valid].astype(np.float64), depth[valid])

    def image_motion_px(self, points_camera_m: np.ndarray, a_from_camera: np.ndarray, b_from_camera: np.ndarray) -> float:
        """Largest distance, pixels, between the images of ``points_camera_m`` (N, 3, this camera's frame) seen by
        this camera at pose a and at pose b (4x4 ``a_from_camera``, ``b_from_camera``); 0 without points. Points
        behind either pose are projected at 1 mm depth."""
        ends = []
        for other_from_camera in (a_from_camera, b_from_camera):
            points = points_camera_m @ other_from_camera[:3, :3].T + other_from_camera[:3, 3]
            ends.append(self.project(points, np.maximum(points[:, 2], 1e-3)))
        return float(np.max(np.linalg.norm(ends[1] - ends[0], axis=1), initial=0.0))

    def in_image(self, pixels_px):
        """Bool mask ``(...,)`` of pixels ``(..., 2)`` (numpy or torch) within the outermost pixel centres,
        ``0 <= u <= width - 1`` and ``0 <= v <= height - 1`` (NaN is outside)."""
        u, v = pixels_px[..., 0], pixels_px[..., 1]
        return (u >= 0) & (u <= self.width - 1) & (v >= 0) & (v <= self.height - 1)

    @property
    def has_distortion(self) -> bool:
        return any(abs(c) > 0 for c in self.distortion)

    def undistorted(self) -> "Camera":
        """The same intrinsics with no distortion (what frames are after undistortion)."""
        return dataclasses.replace(self, distortion=(0.0, 0.0, 0.0, 0.0, 0.0))

    def cropped(self, top: int, bottom: int, left: int, right: int) -> "Camera":
        """The camera of the image's rows ``top:bottom`` and columns ``left:right`` (ends exclusive): a crop, same rays."""
        return dataclasses.replace(self, width=right - left, height=bottom - top, cx=self.cx - left, cy=self.cy - top)

    def scaled(self, factor: float) -> "Camera":
        """Intrinsics of the image resized by ``factor`` (pixel-centre convention of cv2.resize)."""
        return Camera(
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            distortion=self.distortion,
            rolling_shutter_s=self.rolling_shutter_s,
        )


@dataclasses.dataclass(frozen=True)
class RgbdSensor:
    """A camera plus how its depth PNGs encode metres: ``depth_m = raw / depth_scale``; ``raw == depth_invalid`` -> 0.

    ``camera`` is the camera of the frames. With colour registered to depth (TUM, most drivers) it is the colour
    camera. A sensor whose colour is not registered gives ``colour_camera`` and ``colour_from_depth`` ((4, 4),
    depth-camera points into the colour camera's frame, metres): ``camera`` is then the depth camera, and colour is
    resampled into it (:mod:`tambridge.io.registration`). ``exposure_s``: the colour frames' exposure time, seconds,
    where the camera file gives it (``tambridge synth`` writes it for its motion blur), else None (unknown).
    """

    camera: Camera
    depth_scale: float = 5000.0
    depth_invalid: int | None = None
    colour_camera: Camera | None = None
    colour_from_depth: np.ndarray | None = None
    exposure_s: float | None = None


# The Kinect v1's colour camera reads its rows over about this long: the readout at which tracking fr1/xyz fits
# the motion capture best (docs/benchmarks.md, "A rolling shutter"). Its own 7-Scenes camera file gives it too.
KINECT_V1_ROLLING_SHUTTER_S = 0.015

# TUM RGB-D calibration (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats), 640x480.
TUM_PRESETS: dict[str, RgbdSensor] = {
    "fr1": RgbdSensor(Camera(640, 480, 517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
                             KINECT_V1_ROLLING_SHUTTER_S)),
    "fr2": RgbdSensor(Camera(640, 480, 520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
                             KINECT_V1_ROLLING_SHUTTER_S)),
    "fr3": RgbdSensor(Camera(640, 480, 535.4, 539.2, 320.1, 247.6)),
}

_CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy")
_COLOUR_KEYS = ("colour_fx", "colour_fy", "colour_cx", "colour_cy", "colour_from_depth")
_KNOWN_KEYS = frozenset((*_CAMERA_KEYS, "depth_scale", "depth_invalid", "distortion", *(f"d{i}" for i in range(5)),
                         "exposure_s", "rolling_shutter_s", *_COLOUR_KEYS, "colour_width", "colour_height", "colour_distortion"))


def tum_preset_for_folder(folder: Path) -> RgbdSensor | None:
    """The TUM preset named by a folder such as ``rgbd_dataset_freiburg1_xyz`` or ``tum_fr2_desk``, else None."""
    name = Path(folder).resolve().name.lower()
    # A word of its own (fr1 in tum_fr1_desk, not in fr10_garden or afr1x): a name that only contains the letters
    # must not give another camera TUM's calibration.
    match = re.search(r"(?<![a-z0-9])(?:freiburg|fr)([123])(?![0-9])", name)
    return None if match is None else TUM_PRESETS[f"fr{match.group(1)}"]


MAX_ROLLING_SHUTTER_S = 0.1
"""Longest rolling-shutter readout a camera file may give (s): a frame's rows cannot take longer than a 10 Hz frame."""

DISTORTION_LENGTHS = (4, 5, 8, 12, 14)
"""Coefficient counts OpenCV's distortion model accepts (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]])."""


def sensor_from_mapping(values: dict, source: Path) -> RgbdSensor:
    """Build a sensor from a parsed camera file; ``source`` names the file in errors.

    ``depth_scale`` is required: only the TUM presets may assume TUM's 5000, since a wrong scale still gives a
    plausible-looking trajectory of the wrong size."""
    # A misspelt optional key (exposure_sec, depth_invalide) would otherwise fall back to its default unseen.
    unknown = sorted(str(key) for key in values if key not in _KNOWN_KEYS)
    if unknown:
        raise CameraConfigError(f"{source}: unknown key {', '.join(unknown)}; a camera file takes "
                                f"{', '.join(sorted(_KNOWN_KEYS))}")
    missing = [key for key in (*_CAMERA_KEYS, "depth_scale") if key not in values]
    if missing:
        raise CameraConfigError(f"{source}: missing {', '.join(missing)}; a camera file needs "
                                f"{', '.join(_CAMERA_KEYS)} and depth_scale (raw depth units per metre: TUM 5000, "
                                "millimetres 1000)")
    _check_numbers(values, source)
    d_keys = [f"d{i}" for i in range(5) if values.get(f"d{i}") is not None]
    if d_keys and values.get("distortion") is not None:
        raise CameraConfigError(f"{source}: gives distortion and {', '.join(d_keys)}; give the coefficients one way")
    invalid = values.get("depth_invalid")
    if invalid is not None and not (float(invalid).is_integer() and 0 <= float(invalid) <= 65535):
        raise CameraConfigError(f"{source}: depth_invalid is {invalid!r}; expected the raw 16-bit value (an integer "
                                "0-65535) that marks a pixel without depth")
    try:
        distortion = values.get("distortion") or [values.get(f"d{i}", 0.0) for i in range(5)]
        camera = _camera_from_values(values, "")
        camera = dataclasses.replace(camera, distortion=tuple(float(c) for c in distortion),
                                     rolling_shutter_s=float(values.get("rolling_shutter_s") or 0.0))
        colour_camera, colour_from_depth = _colour_camera_from_values(values, camera, source)
        sensor = RgbdSensor(
            camera=camera,
            depth_scale=float(values["depth_scale"]),
            depth_invalid=None if invalid is None else int(float(invalid)),
            colour_camera=colour_camera,
            colour_from_depth=colour_from_depth,
            exposure_s=None if values.get("exposure_s") is None else float(values["exposure_s"]),
        )
    except (TypeError, ValueError) as error:
        raise CameraConfigError(f"{source}: {error}; values must be numbers") from error
    for prefix, checked in (("", camera), ("colour_", colour_camera)):
        if checked is None:
            continue
        if checked.width <= 0 or checked.height <= 0 or checked.fx <= 0 or checked.fy <= 0:
            raise CameraConfigError(f"{source}: width, height, fx and fy (and their colour_ forms) must be positive")
        if not (0 <= checked.cx <= checked.width and 0 <= checked.cy <= checked.height):
            raise CameraConfigError(f"{source}: principal point {prefix}cx={checked.cx:g}, {prefix}cy={checked.cy:g} "
                                    f"lies outside the {checked.width}x{checked.height} image; check the intrinsics")
        if len(checked.distortion) not in DISTORTION_LENGTHS:
            raise CameraConfigError(f"{source}: {prefix}distortion has {len(checked.distortion)} coefficients; OpenCV's "
                                    f"model takes {', '.join(map(str, DISTORTION_LENGTHS))}")
    if sensor.depth_scale <= 0:
        raise CameraConfigError(f"{source}: depth_scale must be positive")
    if sensor.exposure_s is not None and sensor.exposure_s < 0:
        raise CameraConfigError(f"{source}: exposure_s must be >= 0 (seconds)")
    if not 0 <= camera.rolling_shutter_s <= MAX_ROLLING_SHUTTER_S:
        raise CameraConfigError(f"{source}: rolling_shutter_s {camera.rolling_shutter_s:g} must be in [0, "
                                f"{MAX_ROLLING_SHUTTER_S:g}] (seconds from the first row to the last; 0: global shutter)")
    return sensor


_LIST_KEYS = frozenset(("distortion", "colour_distortion", "colour_from_depth"))
"""Camera keys that take a list of numbers (colour_from_depth: rows of them); every other key takes one number."""
_PIXEL_COUNT_KEYS = frozenset(("width", "height", "colour_width", "colour_height"))
"""Camera keys that take a whole number (of pixels)."""


def _check_numbers(values: dict, source: Path) -> None:
    """Refuse a camera key that is not a finite number (for :data:`_LIST_KEYS`, numbers; for
    :data:`_PIXEL_COUNT_KEYS`, a whole one), naming the key; null is a key left unset, an empty list is refused."""
    for key, value in values.items():
        if value is None:
            continue
        expected = "a list of numbers" if key in _LIST_KEYS else "a number"
        if key in _LIST_KEYS and not isinstance(value, (list, tuple)):
            raise CameraConfigError(f"{source}: {key} is {value!r}; expected a list of numbers")
        if key in _LIST_KEYS and len(value) == 0:
            raise CameraConfigError(f"{source}: {key} is an empty list; give its numbers, or leave the key out")
        numbers = np.ravel(np.asarray(value, dtype=object)) if key in _LIST_KEYS else [value]
        for number in numbers:
            # YAML reads yes, no, true and false as booleans, which float() would take as 1 and 0.
            if isinstance(number, bool):
                raise CameraConfigError(f"{source}: {key} is {value!r} (YAML reads {str(number).lower()} as a "
                                        f"boolean); expected {expected}")
            try:
                as_float = float(number)
            except (TypeError, ValueError):
                raise CameraConfigError(f"{source}: {key} is {value!r}; expected {expected}") from None
            if not np.isfinite(as_float):
                raise CameraConfigError(f"{source}: {key} is {number!r}; camera values must be finite numbers")
            if key in _PIXEL_COUNT_KEYS and not as_float.is_integer():
                raise CameraConfigError(f"{source}: {key} is {value!r}; expected a whole number of pixels")


def _camera_from_values(values: dict, prefix: str) -> Camera:
    """The pinhole camera of keys ``{prefix}fx`` ...; a colour camera's size defaults to the depth camera's."""
    return Camera(
        width=int(values.get(f"{prefix}width", values["width"])),
        height=int(values.get(f"{prefix}height", values["height"])),
        fx=float(values[f"{prefix}fx"]),
        fy=float(values[f"{prefix}fy"]),
        cx=float(values[f"{prefix}cx"]),
        cy=float(values[f"{prefix}cy"]),
        distortion=tuple(float(c) for c in values.get(f"{prefix}distortion") or (0.0,) * 5),
    )


def _colour_camera_from_values(values: dict, depth_camera: Camera, source: Path) -> tuple[Camera | None, np.ndarray | None]:
    """``(colour_camera, colour_from_depth)`` of an unregistered sensor's file, or ``(None, None)``."""
    # Any colour_ key says the colour camera is another one: the optional ones alone would be dropped unseen.
    given = [key for key, value in values.items() if str(key).startswith("colour_") and value is not None]
    if not given:
        return None, None
    missing = [key for key in _COLOUR_KEYS if key not in values]
    if missing:
        raise CameraConfigError(
            f"{source}: has {', '.join(given)} but not {', '.join(missing)}; an unregistered colour camera needs "
            f"{', '.join(_COLOUR_KEYS)} (width/height and fx.. then describe the depth camera)"
        )
    if depth_camera.has_distortion:
        raise CameraConfigError(
            f"{source}: distortion describes the depth camera when colour_fx.. are given, and depth undistortion is "
            "not supported; put the colour camera's coefficients in colour_distortion"
        )
    matrix = np.array(values["colour_from_depth"], dtype=float).ravel()
    if matrix.size == 12:
        matrix = np.concatenate([matrix, [0.0, 0.0, 0.0, 1.0]])
    if matrix.size != 16:
        raise CameraConfigError(
            f"{source}: colour_from_depth has {matrix.size} numbers; give the 4x4 (or top 3x4) matrix row by row"
        )
    colour_from_depth = matrix.reshape(4, 4)
    rotation = colour_from_depth[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4) or np.linalg.det(rotation) < 0:
        raise CameraConfigError(f"{source}: colour_from_depth's top-left 3x3 is not a rotation")
    return _camera_from_values(values, "colour_"), colour_from_depth


def load_sensor_file(path: Path) -> RgbdSensor:
    """Read a camera file: YAML (``.yaml``/``.yml``) or text lines of ``key value`` with ``#`` comments."""
    path = Path(path)
    if path.is_dir():
        raise CameraConfigError(f"{path}: is a folder; pass --camera the camera file (camera.yaml) itself")
    if not path.is_file():
        raise CameraConfigError(f"{path}: camera file not found; pass --camera with a YAML file of "
                                f"{', '.join(_CAMERA_KEYS)}, or a camera's name ({config_file_names('cameras')})")
    text = read_text_file(path, CameraConfigError)
    if path.suffix.lower() in (".yaml", ".yml"):
        try:
            values = load_yaml(text) or {}
        except yaml.YAMLError as error:
            raise CameraConfigError(f"{path}: not valid YAML ({yaml_error_line(error)})") from error
        if not isinstance(values, dict):
            raise CameraConfigError(f"{path}: expected a mapping of camera keys")
        return sensor_from_mapping(values, path)
    values: dict = {}
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) < 2:
            raise CameraConfigError(f"{path} line {number}: expected 'key value', got {line!r}")
        if parts[0] in values:
            raise CameraConfigError(f"{path} line {number}: {parts[0]} is given twice; keep one of its lines")
        values[parts[0]] = parts[1] if len(parts) == 2 else parts[1:]
    return sensor_from_mapping(values, path)


def find_sensor(folder: Path, camera_file: Path | None = None) -> RgbdSensor:
    """The sensor of a sequence: an explicit file, else camera.yaml/camera.txt in the folder, else a TUM preset."""
    folder = Path(folder)
    if camera_file is not None:
        return load_sensor_file(find_config_file(camera_file, "cameras"))
    for name in ("camera.yaml", "camera.yml", "camera.txt"):
        if (folder / name).is_file():
            return load_sensor_file(folder / name)
    preset = tum_preset_for_folder(folder)
    if preset is None:
        raise CameraConfigError(
            f"{folder}: no camera.yaml or camera.txt and the folder name names no TUM camera (freiburg1/2/3); "
            "pass --camera camera.yaml with width, height, fx, fy, cx, cy, depth_scale"
        )
    return preset
