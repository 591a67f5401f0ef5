"""Synthetic RGB-D sequences with exact ground truth: a textured room with boxes, ray-cast in numpy.

The scene is a set of textured rectangles (room walls, floor, ceiling, box faces). Each face carries its
own non-repeating texture (multi-scale noise plus random shapes), so ORB finds corners everywhere. The
camera follows a smooth closed path that ends where it started, for loop-closure tests, optionally with
bursts of fast rotation; colour frames can integrate over an exposure along that true path (motion blur),
with the sharp frames kept in ``gt_rgb/``. Sequences are written in the TUM layout (``rgb.txt``,
``depth.txt``, ``groundtruth.txt``, ``camera.yaml``), so they go through the same reader as real data.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable, Iterable

import cv2
import numpy as np
import yaml

from tambridge.camera import Camera, exposure_offsets_s, rolling_shutter_row_times_s
from tambridge.errors import ConfigError
from tambridge.files import atomic_path, atomic_write_text
from tambridge.geometry import inverse, look_at
from tambridge.io.tum import GT_RGB_FOLDER, MAX_ASSOCIATION_DIFFERENCE_S, read_file_list
from tambridge.trajectory import Trajectory, format_tum_trajectory

SYNTHETIC_DEPTH_SCALE = 5000.0
TEXTURE_PIXELS_PER_M = 160.0


@dataclasses.dataclass(frozen=True)
class Face:
    """A textured rectangle: centre (3,), unit axes ``axis_u``/``axis_v`` (3,), half sizes in metres."""

    centre_m: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    half_u_m: float
    half_v_m: float
    texture: np.ndarray  # (Ht, Wt, 3) float32 in [0, 1], Wt along axis_u

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.axis_u, self.axis_v)


@dataclasses.dataclass(frozen=True)
class SyntheticScene:
    """The faces of the room and its boxes, in the world frame (z up, floor at z = 0)."""

    faces: tuple[Face, ...]

    def sample_surface_m(self, spacing_m: float) -> np.ndarray:
        """Points on every face on a grid of ``spacing_m``, (N, 3): the true surface for mesh checks."""
        points = []
        for face in self.faces:
            us = np.arange(-face.half_u_m, face.half_u_m + 1e-9, spacing_m)
            vs = np.arange(-face.half_v_m, face.half_v_m + 1e-9, spacing_m)
            grid_u, grid_v = np.meshgrid(us, vs)
            points.append(face.centre_m + grid_u.reshape(-1, 1) * face.axis_u + grid_v.reshape(-1, 1) * face.axis_v)
        return np.concatenate(points)


def _texture(rng: np.random.Generator, width_m: float, height_m: float) -> np.ndarray:
    """Non-repeating texture: smooth multi-scale colour noise with random rectangles, discs and lines."""
    width = max(8, int(round(width_m * TEXTURE_PIXELS_PER_M)))
    height = max(8, int(round(height_m * TEXTURE_PIXELS_PER_M)))
    base = rng.uniform(0.25, 0.75, size=3).astype(np.float32)
    image = np.tile(base, (height, width, 1))
    for cell, amplitude in ((64, 0.10), (16, 0.06), (4, 0.02)):
        coarse = rng.normal(0.0, amplitude, size=(max(2, height // cell), max(2, width // cell), 3)).astype(np.float32)
        image += cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    shape_count = int(width * height / 900)
    for _ in range(shape_count):
        colour = tuple(float(c) for c in rng.uniform(0.0, 1.0, size=3))
        kind = rng.integers(3)
        x, y = int(rng.integers(width)), int(rng.integers(height))
        size = int(rng.integers(3, 14))
        if kind == 0:
            cv2.rectangle(image, (x, y), (x + size, y + int(rng.integers(3, 14))), colour, -1)
        elif kind == 1:
            cv2.circle(image, (x, y), size // 2 + 1, colour, -1)
        else:
            cv2.line(image, (x, y), (x + int(rng.integers(-20, 20)), y + int(rng.integers(-20, 20))), colour, 2)
    return np.clip(image, 0.0, 1.0)


def _box_faces(rng: np.random.Generator, minimum: np.ndarray, maximum: np.ndarray, inward: bool) -> list[Face]:
    """The six faces of an axis-aligned box; ``inward`` orients normals into the box (a room)."""
    centre = (minimum + maximum) / 2.0
    half = (maximum - minimum) / 2.0
    faces = []
    for axis in range(3):
        other_u, other_v = [a for a in range(3) if a != axis]
        for sign in (-1.0, 1.0):
            face_centre = centre.copy()
            face_centre[axis] += sign * half[axis]
            axis_u = np.eye(3)[other_u]
            axis_v = np.eye(3)[other_v]
            # Orient so that u x v points out of the box (or into it for a room): makes normals meaningful.
            outward = np.eye(3)[axis] * sign
            if np.dot(np.cross(axis_u, axis_v), outward) * (-1.0 if inward else 1.0) < 0:
                axis_v = -axis_v
            faces.append(
                Face(
                    centre_m=face_centre,
                    axis_u=axis_u,
                    axis_v=axis_v,
                    half_u_m=float(half[other_u]),
                    half_v_m=float(half[other_v]),
                    texture=_texture(rng, 2 * half[other_u], 2 * half[other_v]),
                )
            )
    return faces


def make_room_scene(seed: int = 0) -> SyntheticScene:
    """A 6 x 5 x 2.8 m room with four boxes on the floor, every face with its own texture."""
    rng = np.random.default_rng(seed)
    faces = _box_faces(rng, np.array([-3.0, -2.5, 0.0]), np.array([3.0, 2.5, 2.8]), inward=True)
    boxes = [
        ((1.4, -1.2, 0.0), (2.2, -0.4, 0.9)),
        ((1.6, 0.6, 0.0), (2.3, 1.5, 1.4)),
        ((0.6, -0.2, 0.0), (1.0, 0.3, 0.5)),
        ((-2.4, 1.2, 0.0), (-1.6, 2.0, 1.1)),
    ]
    for minimum, maximum in boxes:
        faces += _box_faces(rng, np.array(minimum), np.array(maximum), inward=False)
    return SyntheticScene(tuple(faces))


def default_camera(width: int, height: int) -> Camera:
    """A Kinect-like pinhole camera (about 60 degrees horizontal field of view) for a ``width x height`` image."""
    focal = 0.82 * width
    return Camera(width, height, focal, focal, (width - 1) / 2.0, (height - 1) / 2.0)


def loop_path(frame_count: int) -> np.ndarray:
    """``world_from_camera`` (N, 4, 4) along a smooth closed loop; the last frame is one step before the first.

    The camera circles an ellipse of 0.4 x 0.25 m at 1.4 m height, looking across the room towards +x
    with a yaw swing of +-25 degrees, so consecutive frames overlap and the end revisits the start.
    """
    return _loop_poses(np.arange(frame_count), frame_count)


def _loop_poses(frame_positions: np.ndarray, frame_count: int) -> np.ndarray:
    """The loop's poses (N, 4, 4) at fractional frame positions (N,) of a ``frame_count``-frame loop."""
    poses = []
    for phase in np.asarray(frame_positions, np.float64) / frame_count * 2.0 * np.pi:
        eye = np.array([-0.8 + 0.4 * np.cos(phase), 0.25 * np.sin(phase), 1.4 + 0.05 * np.sin(2 * phase)])
        yaw = np.deg2rad(25.0) * np.sin(phase)
        target = eye + np.array([np.cos(yaw), np.sin(yaw), -0.25 + 0.1 * np.cos(phase)])
        poses.append(look_at(eye, target))
    return np.stack(poses)


BURST_RAMP_S = 0.1
"""Seconds over which a rotation burst's speed ramps up, reverses through zero, and ramps down."""


@dataclasses.dataclass(frozen=True)
class RotationBursts:
    """Fast swings of the camera about its own x axis (a tilt), added to the loop: ``count`` bursts of
    ``duration_s`` each, evenly spaced with equal stretches of the plain loop before, between and after them.

    In a burst the camera tilts out at ``speed_deg_s`` and back to the loop at the same speed, so the loop
    still closes; the speed ramps with a half cosine over :data:`BURST_RAMP_S` at the start, the turn and
    the end. The loop turns mostly about the vertical, nearly orthogonal to the tilt, so outside those ramps
    the camera's angular speed stays near ``speed_deg_s`` (the loop's own turn adds or takes a little).
    Bursts alternate up and down.
    """

    count: int = 0
    speed_deg_s: float = 90.0
    duration_s: float = 1.5

    def windows_s(self, sequence_s: float) -> list[tuple[float, float]]:
        """(start, end) seconds of each burst in a sequence ``sequence_s`` long."""
        gap_s = (sequence_s - self.count * self.duration_s) / (self.count + 1)
        return [(gap_s * (i + 1) + self.duration_s * i, (gap_s + self.duration_s) * (i + 1)) for i in range(self.count)]

    def tilt_rad(self, times_s: np.ndarray, sequence_s: float) -> np.ndarray:
        """The tilt angle (N,) in radians at ``times_s`` (N,): the integral of the ramped speed profile."""
        times_s = np.asarray(times_s, np.float64)
        angle = np.zeros_like(times_s)
        speed = np.deg2rad(self.speed_deg_s)
        ramp, duration = BURST_RAMP_S, self.duration_s
        for index, (start_s, _) in enumerate(self.windows_s(sequence_s)):
            tau = times_s - start_s
            # The speed is +1, -1, 0 (times ``speed``) joined by smooth steps: up at 0, down through 0 at the
            # middle, up to 0 at the end; the angle is the sum of the steps' integrals.
            swing = _step_integral(tau, ramp) - 2.0 * _step_integral(tau - (duration - ramp) / 2.0, ramp) \
                + _step_integral(tau - (duration - ramp), ramp)
            angle += (1.0 if index % 2 == 0 else -1.0) * speed * swing
        return angle


def _step_integral(tau_s: np.ndarray, ramp_s: float) -> np.ndarray:
    """Integral from -inf to ``tau_s`` of a smooth unit step: 0 before 0, a half cosine up to 1 over ``ramp_s``."""
    inside = np.clip(tau_s, 0.0, ramp_s)
    return inside / 2.0 - ramp_s / (2.0 * np.pi) * np.sin(np.pi * inside / ramp_s) + np.maximum(tau_s - ramp_s, 0.0)


@dataclasses.dataclass(frozen=True)
class CameraPath:
    """The true camera motion of a synthetic sequence, continuous in time: the loop plus rotation bursts.

    Frame ``i`` is at ``i / fps`` seconds; the loop takes ``frame_count / fps`` seconds.
    """

    frame_count: int
    fps: float
    bursts: RotationBursts = RotationBursts()
    roll_deg: float = 0.0
    """Every camera turned about its optical axis by this (degrees), as a handheld camera held askew."""

    @property
    def duration_s(self) -> float:
        return self.frame_count / self.fps

    def poses(self, frame_positions: np.ndarray) -> np.ndarray:
        """``world_from_camera`` (N, 4, 4) at fractional frame positions (N,) (seconds times fps)."""
        frame_positions = np.asarray(frame_positions, np.float64)
        poses = _loop_poses(frame_positions, self.frame_count)
        if self.roll_deg:
            cos, sin = np.cos(np.radians(self.roll_deg)), np.sin(np.radians(self.roll_deg))
            # The camera's x and y axes turn by the angle about its z: the image turns the other way.
            camera_from_rolled = np.eye(4)
            camera_from_rolled[:2, :2] = [[cos, sin], [-sin, cos]]
            poses = poses @ camera_from_rolled
        if self.bursts.count == 0:
            return poses
        tilt = self.bursts.tilt_rad(frame_positions / self.fps, self.duration_s)
        cos, sin = np.cos(tilt), np.sin(tilt)
        camera_from_tilted = np.tile(np.eye(4), (len(tilt), 1, 1))
        camera_from_tilted[:, 1, 1], camera_from_tilted[:, 1, 2] = cos, -sin
        camera_from_tilted[:, 2, 1], camera_from_tilted[:, 2, 2] = sin, cos
        return poses @ camera_from_tilted


def render(
    scene: SyntheticScene, camera: Camera, world_from_camera: np.ndarray, supersampling: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast the scene: colour (H, W, 3) float32 in [0, 1] and z-depth (H, W) float32 metres (0 = no hit).

    ``supersampling`` k (odd) casts k x k rays per pixel and averages their colour, as a real sensor integrates
    light over the pixel's area; the depth is the centre ray's, as a depth camera does not blend surfaces.
    With one ray per pixel, texture detail finer than a pixel aliases differently in every frame, which no
    3D model can reproduce: it caps novel-view PSNR.
    """
    if supersampling != 1:
        if supersampling < 1 or supersampling % 2 == 0:
            raise ValueError(f"supersampling must be an odd positive integer, got {supersampling}")
        colour, depth_m = render(scene, camera.scaled(supersampling), world_from_camera)
        k, height, width = supersampling, camera.height, camera.width
        colour = colour.reshape(height, k, width, k, 3).mean(axis=(1, 3))
        return colour.astype(np.float32), np.ascontiguousarray(depth_m[k // 2 :: k, k // 2 :: k])
    columns, rows = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
    rays_camera = camera.backproject(np.stack([columns, rows], axis=-1), 1.0).reshape(-1, 3)
    rays_world = rays_camera @ world_from_camera[:3, :3].T  # z-component 1 in the camera: t is z-depth
    origin = world_from_camera[:3, 3]
    best_t = np.full(len(rays_world), np.inf)
    best_face = np.full(len(rays_world), -1)
    for index, face in enumerate(scene.faces):
        denominator = rays_world @ face.normal
        # Rays parallel to a face meet it at infinity: their (nan) hits fail the tests below.
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.dot(face.centre_m - origin, face.normal) / denominator
            hits = origin + t[:, None] * rays_world - face.centre_m
        inside = (
            (t > 1e-6)
            & (np.abs(hits @ face.axis_u) <= face.half_u_m)
            & (np.abs(hits @ face.axis_v) <= face.half_v_m)
            & (t < best_t)
        )
        best_t[inside] = t[inside]
        best_face[inside] = index
    colour = np.zeros((len(rays_world), 3), np.float32)
    for index, face in enumerate(scene.faces):
        selected = np.flatnonzero(best_face == index)
        if selected.size == 0:
            continue
        local = origin + best_t[selected, None] * rays_world[selected] - face.centre_m
        map_x = (local @ face.axis_u + face.half_u_m) * TEXTURE_PIXELS_PER_M
        map_y = (local @ face.axis_v + face.half_v_m) * TEXTURE_PIXELS_PER_M
        colour[selected] = _sample_texture(face.texture, map_x, map_y)
    depth_m = np.where(np.isfinite(best_t), best_t, 0.0).astype(np.float32)
    return colour.reshape(camera.height, camera.width, 3), depth_m.reshape(camera.height, camera.width)


def _sample_texture(texture: np.ndarray, x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
    """Bilinear samples (N, 3) of ``texture`` at texel coordinates ``x_px``, ``y_px`` (N,).

    The coordinates are laid out in rows of 1024 because cv2.remap limits each side of its maps to 32767
    (a single (N, 1) column fails for faces covering more pixels than that, e.g. at 320x240).
    """
    columns = 1024
    count = len(x_px)
    padded = -(-count // columns) * columns
    map_x = np.zeros(padded, np.float32)
    map_y = np.zeros(padded, np.float32)
    map_x[:count] = x_px
    map_y[:count] = y_px
    samples = cv2.remap(texture, map_x.reshape(-1, columns), map_y.reshape(-1, columns), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
    return samples.reshape(-1, 3)[:count]


MIN_SHARP_BEFORE_BURST_S = 0.2
"""Seconds of the plain loop before, between and after rotation bursts (the tracker starts on sharp frames)."""

BLUR_STEP_PX = 0.5
"""Largest image motion, pixels, between consecutive sub-frames of a blurred frame: finer looks like a smooth smear."""

MAX_BLUR_SUBFRAMES = 128


def subframe_positions(frame_index: float, fps: float, exposure_s: float, count: int) -> np.ndarray:
    """Fractional frame positions (count,) of the sub-frames of frame ``frame_index``: the midpoints of ``count``
    equal slices of the exposure ``[t - exposure_s / 2, t + exposure_s / 2]`` around its timestamp ``t``."""
    return frame_index + exposure_offsets_s(count, exposure_s) * fps


def blur_subframe_count(camera: Camera, depth_m: np.ndarray, world_from_camera: np.ndarray,
                        world_from_start: np.ndarray, world_from_end: np.ndarray) -> int:
    """Sub-frames enough that the scene seen at ``world_from_camera`` (z-depth (H, W) metres) moves at most
    :data:`BLUR_STEP_PX` between consecutive ones, from pose ``world_from_start`` to ``world_from_end`` (4x4);
    at least 2, at most :data:`MAX_BLUR_SUBFRAMES`. The exposure is short: its motion is taken as linear."""
    points_camera = camera.depth_points(depth_m, 4)
    motion_px = camera.image_motion_px(points_camera, inverse(world_from_start) @ world_from_camera,
                                       inverse(world_from_end) @ world_from_camera)
    return int(np.clip(np.ceil(motion_px / BLUR_STEP_PX), 2, MAX_BLUR_SUBFRAMES))


def render_exposure(scene: SyntheticScene, camera: Camera, world_from_subframes: np.ndarray,
                    supersampling: int = 1) -> np.ndarray:
    """Colour (H, W, 3) float32 of an exposure: the mean of sharp renders at the sub-frame poses (K, 4, 4),
    as a sensor sums the light arriving while the camera moves (motion blur along the true path)."""
    total = np.zeros((camera.height, camera.width, 3), np.float64)
    for pose in world_from_subframes:
        total += render(scene, camera, pose, supersampling)[0]
    return (total / len(world_from_subframes)).astype(np.float32)


ROLLING_SHUTTER_BANDS = 32
"""Bands of rows a rolling-shutter frame is rendered in, each band at its middle row's time."""


def render_rolling_shutter(colour_taken: Callable[[float, Camera], np.ndarray], camera: Camera,
                           readout_s: float) -> np.ndarray:
    """Colour (H, W, 3) of a rolling-shutter frame of ``camera``: each of :data:`ROLLING_SHUTTER_BANDS` equal bands
    of rows is ``colour_taken(dt, band_camera)``, the band's image (:meth:`Camera.rows`) taken ``dt`` seconds after
    the frame's stamp, ``dt`` the band's middle row's time (:func:`~tambridge.camera.rolling_shutter_row_times_s`)."""
    edges = np.linspace(0, camera.height, min(camera.height, ROLLING_SHUTTER_BANDS) + 1).round().astype(int)
    bands = []
    for start, stop in zip(edges[:-1], edges[1:]):
        middle_row = (start + stop - 1) / 2.0
        offset_s = float(rolling_shutter_row_times_s(np.array([middle_row]), camera.height, readout_s)[0])
        bands.append(colour_taken(offset_s, camera.cropped(int(start), int(stop), 0, camera.width)))
    return np.concatenate(bands, axis=0)


@dataclasses.dataclass(frozen=True)
class SynthOptions:
    """Sensor effects of a synthetic sequence. Depth noise is Gaussian with sigma ``depth_noise_m * z^2``."""

    frame_count: int = 30
    width: int = 160
    height: int = 120
    fps: float = 30.0
    depth_noise_m: float = 0.0
    colour_noise: float = 0.0
    # Motion blur: each colour frame integrates light over ``exposure_s`` seconds centred on its timestamp (see
    # :func:`render_exposure`); ``blur_subframes`` fixes the number of sub-frame renders (None: from the motion).
    exposure_s: float = 0.0
    blur_subframes: int | None = None
    bursts: RotationBursts = RotationBursts()
    # Rays per pixel along each side (odd); see :func:`render`. 1 keeps the tests' sequences fast to write.
    supersampling: int = 1
    seed: int = 0
    # An unregistered sensor (as a Kinect v1 without depth registration): colour comes from a second camera,
    # ``colour_baseline_m`` to the right of the depth camera, with its focal length scaled by ``colour_focal_scale``.
    # The ground truth is the depth camera's; camera.yaml gets the colour_* keys. 0 and 1: one registered camera.
    colour_baseline_m: float = 0.0
    colour_focal_scale: float = 1.0
    # Every camera turned about its optical axis by this (degrees), as a handheld camera held askew.
    roll_deg: float = 0.0
    # The depth image taken this long after the colour image (seconds; negative: before), as a Kinect's two streams
    # are: depth.txt gets that stamp and the depth is rendered at the pose of that time.
    depth_delay_s: float = 0.0
    # A rolling shutter: the colour image's rows taken one after another over this readout time (seconds), the
    # middle row at the stamp (see :func:`render_rolling_shutter`); 0: a global shutter. Depth stays global.
    rolling_shutter_s: float = 0.0

    def __post_init__(self) -> None:
        problems = []
        if not 0.0 <= self.rolling_shutter_s <= 1.0 / self.fps:
            problems.append(f"rolling shutter readout {self.rolling_shutter_s} s: must be in [0, 1/fps = "
                            f"{1.0 / self.fps:.4g}] s")
        if not 0.0 <= self.exposure_s <= 1.0 / self.fps:
            problems.append(f"motion blur exposure {self.exposure_s} s: must be in [0, 1/fps = {1.0 / self.fps:.4g}] s")
        if not abs(self.depth_delay_s) < MAX_ASSOCIATION_DIFFERENCE_S:
            problems.append(f"depth delay {self.depth_delay_s} s: must lie within {MAX_ASSOCIATION_DIFFERENCE_S} s of "
                            "the colour stamp (the reader pairs colour and depth images no further apart)")
        if self.blur_subframes is not None and self.blur_subframes < 1:
            problems.append(f"blur sub-frames {self.blur_subframes}: must be at least 1")
        bursts = self.bursts
        if bursts.count < 0 or bursts.speed_deg_s <= 0 or bursts.duration_s <= 4 * BURST_RAMP_S:
            problems.append(f"rotation bursts {bursts}: need count >= 0, speed > 0 and duration > {4 * BURST_RAMP_S} s")
        elif bursts.count and bursts.windows_s(self.frame_count / self.fps)[0][0] < MIN_SHARP_BEFORE_BURST_S:
            problems.append(f"{bursts.count} rotation bursts of {bursts.duration_s} s do not fit in {self.frame_count} "
                            f"frames at {self.fps} fps with {MIN_SHARP_BEFORE_BURST_S} s of steady motion around each: "
                            "use more frames or fewer or shorter bursts")
        if problems:
            raise ConfigError("synthetic sequence: " + "; ".join(problems))

    @property
    def path(self) -> CameraPath:
        return CameraPath(self.frame_count, self.fps, self.bursts, self.roll_deg)

    @property
    def blurred(self) -> bool:
        return self.exposure_s > 0.0

    @property
    def registered(self) -> bool:
        return self.colour_baseline_m == 0.0 and self.colour_focal_scale == 1.0

    def colour_camera(self, depth_camera: Camera) -> Camera:
        """The colour camera's intrinsics: the depth camera's, focal length scaled."""
        return dataclasses.replace(
            depth_camera, fx=depth_camera.fx * self.colour_focal_scale, fy=depth_camera.fy * self.colour_focal_scale
        )

    def colour_from_depth(self) -> np.ndarray:
        """(4, 4): depth-camera points into the colour camera's frame (the colour camera sits at +baseline x)."""
        transform = np.eye(4)
        transform[0, 3] = -self.colour_baseline_m
        return transform


def write_synthetic_sequence(folder: Path, options: SynthOptions = SynthOptions()) -> Trajectory:
    """Render a sequence into ``folder`` in the TUM layout; returns its ground-truth trajectory.

    Depth is always sharp: the pose at its own stamp (the colour stamp plus ``depth_delay_s``), as a depth camera's
    short structured-light exposure is; the ground truth is the pose at the colour stamps.
    With motion blur or colour noise, ``gt_rgb/`` (same file names as ``rgb/``) holds every frame's sharp,
    noise-free colour image at its ground-truth pose, for evaluation.
    """
    folder = Path(folder)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    write_sharp = options.blurred or options.colour_noise > 0
    if write_sharp:
        (folder / GT_RGB_FOLDER).mkdir(exist_ok=True)
    rng = np.random.default_rng(options.seed + 1)
    scene = make_room_scene(options.seed)
    camera = default_camera(options.width, options.height)
    path = options.path
    world_from_camera = path.poses(np.arange(options.frame_count))
    timestamps = np.arange(options.frame_count) / options.fps
    rgb_lines, depth_lines = ["# timestamp filename"], ["# timestamp filename"]
    colour_camera = options.colour_camera(camera)
    depth_from_colour = np.linalg.inv(options.colour_from_depth())
    for index, pose in enumerate(world_from_camera):
        colour, depth_m = render(scene, camera, pose, options.supersampling)
        if options.depth_delay_s != 0.0:
            depth_pose = path.poses(np.array([index + options.depth_delay_s * options.fps]))[0]
            depth_m = render(scene, camera, depth_pose, options.supersampling)[1]
        if not options.registered:
            colour = render(scene, colour_camera, pose @ depth_from_colour, options.supersampling)[0]
        sharp = colour

        def colour_taken(offset_s: float, rows_camera: Camera, index=index, pose=pose, depth_m=depth_m) -> np.ndarray:
            """The colour image of ``rows_camera`` (the colour camera or some of its rows), blurred over the
            exposure, taken ``offset_s`` after the frame's stamp."""
            position = index + offset_s * options.fps
            if options.blurred:
                exposure_frames = options.exposure_s * options.fps
                count = options.blur_subframes or blur_subframe_count(
                    camera, depth_m, pose, *path.poses(position + np.array([-0.5, 0.5]) * exposure_frames))
                subframes = path.poses(subframe_positions(position, options.fps, options.exposure_s, count))
                return render_exposure(scene, rows_camera, subframes @ depth_from_colour, options.supersampling)
            return render(scene, rows_camera, path.poses(np.array([position]))[0] @ depth_from_colour,
                          options.supersampling)[0]

        if options.rolling_shutter_s > 0.0:
            colour = render_rolling_shutter(colour_taken, colour_camera, options.rolling_shutter_s)
        elif options.blurred:
            colour = colour_taken(0.0, colour_camera)
        if options.colour_noise > 0:
            colour = colour + rng.normal(0.0, options.colour_noise, colour.shape).astype(np.float32)
        if options.depth_noise_m > 0:
            depth_m = depth_m + (rng.normal(0.0, 1.0, depth_m.shape) * options.depth_noise_m * depth_m**2).astype(np.float32)
        rgb_name = f"rgb/{timestamps[index]:.6f}.png"
        depth_stamp = timestamps[index] + options.depth_delay_s
        depth_name = f"depth/{depth_stamp:.6f}.png"
        depth16 = np.clip(depth_m * SYNTHETIC_DEPTH_SCALE + 0.5, 0, 65535).astype(np.uint16)
        _write_png(folder / rgb_name, cv2.cvtColor(to_rgb8(colour), cv2.COLOR_RGB2BGR))
        _write_png(folder / depth_name, depth16)
        if write_sharp:
            _write_png(folder / GT_RGB_FOLDER / Path(rgb_name).name, cv2.cvtColor(to_rgb8(sharp), cv2.COLOR_RGB2BGR))
        rgb_lines.append(f"{timestamps[index]:.6f} {rgb_name}")
        depth_lines.append(f"{depth_stamp:.6f} {depth_name}")
    trajectory = Trajectory(timestamps, world_from_camera)
    atomic_write_text(folder / "rgb.txt", "\n".join(rgb_lines) + "\n")
    atomic_write_text(folder / "depth.txt", "\n".join(depth_lines) + "\n")
    atomic_write_text(folder / "groundtruth.txt", format_tum_trajectory(trajectory))
    camera_values = {field: getattr(camera, field) for field in ("width", "height", "fx", "fy", "cx", "cy")}
    camera_values.update(depth_scale=SYNTHETIC_DEPTH_SCALE, distortion=[0.0] * 5)
    if options.blurred:
        camera_values["exposure_s"] = options.exposure_s
    if options.rolling_shutter_s > 0.0:
        camera_values["rolling_shutter_s"] = options.rolling_shutter_s
    if not options.registered:
        camera_values.update({f"colour_{field}": getattr(colour_camera, field) for field in ("fx", "fy", "cx", "cy")})
        camera_values["colour_from_depth"] = options.colour_from_depth().tolist()
    atomic_write_text(folder / "camera.yaml", yaml.safe_dump(camera_values, sort_keys=False))
    return trajectory


def to_rgb8(colour: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 of a float colour image in [0, 1], rounded as the sequence's PNGs store it."""
    return (np.clip(colour, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _write_png(path: Path, image: np.ndarray) -> None:
    with atomic_path(path) as temp_path:
        ok, encoded = cv2.imencode(".png", image)
        assert ok, path
        temp_path.write_bytes(encoded.tobytes())


def blank_frames(folder: Path, depth_frames: Iterable[int] = (), colour_frames: Iterable[int] = ()) -> None:
    """Simulate sensor failures in a TUM-layout folder, in place: the depth images of ``depth_frames`` become all
    invalid (0) and the colour images of ``colour_frames`` all black (a covered lens), same size, format and name.

    Frame numbers are positions in the time-sorted ``depth.txt`` / ``rgb.txt`` lists (the sequence's frame indices
    when colour and depth are listed one to one, as in the synthetic and 7-Scenes folders).
    """
    folder = Path(folder)
    for listing, frames in (("depth.txt", depth_frames), ("rgb.txt", colour_frames)):
        names = [name for _, name in read_file_list(folder / listing)]
        for index in frames:
            path = folder / names[index]
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            with atomic_path(path) as temp_path:
                ok, encoded = cv2.imencode(path.suffix, np.zeros_like(image))
                assert ok, path
                temp_path.write_bytes(encoded.tobytes())
