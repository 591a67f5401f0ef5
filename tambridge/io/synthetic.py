"""Synthetic RGB-D sequences with exact ground truth: a textured room with boxes, ray-cast in numpy.

The scene is a set of textured rectangles (room walls, floor, ceiling, box faces). Each face carries its
own non-repeating texture (multi-scale noise plus random shapes), so ORB finds corners everywhere. The
camera follows a smooth closed path that ends where it started, for loop-closure tests. Sequences are
written in the TUM layout (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``, ``camera.yaml``), so they go
through the same reader as real data.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Iterable

import cv2
import numpy as np
import yaml

from tambridge.camera import Camera
from tambridge.files import atomic_path, atomic_write_text
from tambridge.geometry import interpolate_pose, look_at
from tambridge.io.tum import read_file_list
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
    poses = []
    for phase in np.arange(frame_count) / frame_count * 2.0 * np.pi:
        eye = np.array([-0.8 + 0.4 * np.cos(phase), 0.25 * np.sin(phase), 1.4 + 0.05 * np.sin(2 * phase)])
        yaw = np.deg2rad(25.0) * np.sin(phase)
        target = eye + np.array([np.cos(yaw), np.sin(yaw), -0.25 + 0.1 * np.cos(phase)])
        poses.append(look_at(eye, target))
    return np.stack(poses)


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


@dataclasses.dataclass(frozen=True)
class SynthOptions:
    """Sensor effects of a synthetic sequence. Depth noise is Gaussian with sigma ``depth_noise_m * z^2``."""

    frame_count: int = 30
    width: int = 160
    height: int = 120
    fps: float = 30.0
    depth_noise_m: float = 0.0
    colour_noise: float = 0.0
    motion_blur_samples: int = 1
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

    Depth stamps lag colour stamps by 5 ms, as real Kinect streams do, so association is exercised.
    """
    folder = Path(folder)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(options.seed + 1)
    scene = make_room_scene(options.seed)
    camera = default_camera(options.width, options.height)
    world_from_camera = loop_path(options.frame_count)
    if options.roll_deg:
        angle = np.radians(options.roll_deg)
        # The camera's x and y axes turn by the angle about its z: the image turns the other way.
        world_from_camera[:, :3, :2] = world_from_camera[:, :3, :2] @ np.array([[np.cos(angle), np.sin(angle)],
                                                                                [-np.sin(angle), np.cos(angle)]])
    timestamps = np.arange(options.frame_count) / options.fps
    rgb_lines, depth_lines = ["# timestamp filename"], ["# timestamp filename"]
    colour_camera = options.colour_camera(camera)
    depth_from_colour = np.linalg.inv(options.colour_from_depth())
    for index, pose in enumerate(world_from_camera):
        colour, depth_m = render(scene, camera, pose, options.supersampling)
        if not options.registered:
            colour = render(scene, colour_camera, pose @ depth_from_colour, options.supersampling)[0]
        if options.motion_blur_samples > 1:
            previous = world_from_camera[index - 1]
            blurred = [render(scene, colour_camera, interpolate_pose(previous, pose, f) @ depth_from_colour,
                              options.supersampling)[0]
                       for f in np.linspace(0.5, 1.0, options.motion_blur_samples)[:-1]]
            colour = (colour + sum(blurred)) / options.motion_blur_samples
        if options.colour_noise > 0:
            colour = colour + rng.normal(0.0, options.colour_noise, colour.shape).astype(np.float32)
        if options.depth_noise_m > 0:
            depth_m = depth_m + (rng.normal(0.0, 1.0, depth_m.shape) * options.depth_noise_m * depth_m**2).astype(np.float32)
        rgb_name = f"rgb/{timestamps[index]:.6f}.png"
        depth_stamp = timestamps[index] + 0.005
        depth_name = f"depth/{depth_stamp:.6f}.png"
        rgb8 = (np.clip(colour, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        depth16 = np.clip(depth_m * SYNTHETIC_DEPTH_SCALE + 0.5, 0, 65535).astype(np.uint16)
        _write_png(folder / rgb_name, cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR))
        _write_png(folder / depth_name, depth16)
        rgb_lines.append(f"{timestamps[index]:.6f} {rgb_name}")
        depth_lines.append(f"{depth_stamp:.6f} {depth_name}")
    trajectory = Trajectory(timestamps, world_from_camera)
    atomic_write_text(folder / "rgb.txt", "\n".join(rgb_lines) + "\n")
    atomic_write_text(folder / "depth.txt", "\n".join(depth_lines) + "\n")
    atomic_write_text(folder / "groundtruth.txt", format_tum_trajectory(trajectory))
    camera_values = {field: getattr(camera, field) for field in ("width", "height", "fx", "fy", "cx", "cy")}
    camera_values.update(depth_scale=SYNTHETIC_DEPTH_SCALE, distortion=[0.0] * 5)
    if not options.registered:
        camera_values.update({f"colour_{field}": getattr(colour_camera, field) for field in ("fx", "fy", "cx", "cy")})
        camera_values["colour_from_depth"] = options.colour_from_depth().tolist()
    atomic_write_text(folder / "camera.yaml", yaml.safe_dump(camera_values, sort_keys=False))
    return trajectory


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
