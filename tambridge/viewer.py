"""Live view of a run in rerun (the optional ``viewer`` extra: ``pip install -e ".[viewer]"``, or
``pip install rerun-sdk``).

``--viewer rerun`` spawns a rerun viewer and streams to it; ``--viewer rerun:run.rrd`` saves a recording that
``rerun run.rrd`` opens later. Entities (the world frame is the frontend's: the first camera, OpenCV axes):

- ``world/camera`` the current camera (pose, pinhole), with ``image`` (JPEG) and ``depth`` (millimetres);
- ``world/trajectory`` the camera path so far (one line strip, re-logged each frame so it grows);
- ``world/keyframes`` keyframe positions; ``world/map_points`` the frontend's sparse map;
- ``world/gaussians`` Gaussian centres with their colours and radii; ``render`` the map rendered at a view.

Every entity is logged on the ``frame`` timeline (the frame index) and the ``time`` timeline (seconds).
"""

from __future__ import annotations

import importlib.util
import logging
from pathlib import Path

import numpy as np

from tambridge.camera import Camera
from tambridge.errors import TambridgeError
from tambridge.files import check_output_file
from tambridge.frontend.contract import FrontendResult
from tambridge.images import rgb_uint8
from tambridge.io.tum import RgbdSequence
from tambridge.mapping.stage import MappingStage

logger = logging.getLogger("tambridge.viewer")

JPEG_QUALITY = 85


class ViewerError(TambridgeError):
    """The viewer spec is malformed or rerun-sdk is not installed."""


def parse_viewer_spec(spec: str) -> Path | None:
    """``"rerun"`` -> None (spawn a viewer), ``"rerun:PATH.rrd"`` -> the recording path; anything else raises."""
    if spec == "rerun":
        return None
    if spec.startswith("rerun:") and len(spec) > len("rerun:"):
        return Path(spec[len("rerun:"):])
    raise ViewerError(f"--viewer {spec!r}: expected 'rerun' (live viewer) or 'rerun:FILE.rrd' (save a recording)")


def check_viewer_spec(spec: str) -> Path | None:
    """:func:`parse_viewer_spec`, and a :class:`ViewerError` where rerun-sdk is not installed: what a run checks
    before it touches its output folder."""
    recording_path = parse_viewer_spec(spec)
    if recording_path is not None:
        check_output_file(recording_path, "--viewer")
    if importlib.util.find_spec("rerun") is None:
        raise ViewerError(f"--viewer {spec}: rerun-sdk is not installed; pip install rerun-sdk (or pip install -e "
                          "'.[viewer]' in the checkout)")
    return recording_path


class RerunViewer:
    """Streams a run to rerun. Call the ``log_*`` methods as the run goes, then :meth:`close` once."""

    def __init__(self, spec: str, camera: Camera, application_id: str = "tambridge") -> None:
        recording_path = check_viewer_spec(spec)
        import rerun as rr

        self._rr = rr
        self.camera = camera
        self.recording = rr.RecordingStream(application_id)
        if recording_path is None:
            self.recording.spawn()
        else:
            recording_path.parent.mkdir(parents=True, exist_ok=True)
            self.recording.save(recording_path)
        self.recording_path = recording_path
        self._positions: list[np.ndarray] = []
        self._keyframe_positions: list[np.ndarray] = []
        self.recording.log("world", rr.ViewCoordinates.RDF, static=True)
        self.recording.log(
            "world/camera",
            rr.Pinhole(image_from_camera=camera.K, width=camera.width, height=camera.height, camera_xyz=rr.ViewCoordinates.RDF),
            static=True,
        )

    def _set_time(self, frame_index: int, timestamp_s: float) -> None:
        self.recording.set_time("frame", sequence=int(frame_index))
        self.recording.set_time("time", duration=float(timestamp_s))

    def log_frame(
        self,
        frame_index: int,
        timestamp_s: float,
        world_from_camera: np.ndarray,
        rgb: np.ndarray | None = None,
        depth_m: np.ndarray | None = None,
        is_keyframe: bool = False,
    ) -> None:
        """One tracked frame: camera pose (4, 4), images ((H, W, 3) uint8, (H, W) metres), the path so far."""
        rr = self._rr
        self._set_time(frame_index, timestamp_s)
        world_from_camera = np.asarray(world_from_camera, np.float64)
        self.recording.log("world/camera", rr.Transform3D(translation=world_from_camera[:3, 3], mat3x3=world_from_camera[:3, :3]))
        if rgb is not None:
            self.recording.log("world/camera/image", rr.Image(rgb).compress(jpeg_quality=JPEG_QUALITY))
        if depth_m is not None:
            depth_mm = np.clip(np.asarray(depth_m) * 1000.0 + 0.5, 0, 65535).astype(np.uint16)
            self.recording.log("world/camera/depth", rr.DepthImage(depth_mm, meter=1000.0))
        self._positions.append(world_from_camera[:3, 3].copy())
        self.recording.log("world/trajectory", rr.LineStrips3D([np.array(self._positions)], colors=[[40, 120, 255]]))
        if is_keyframe:
            self._keyframe_positions.append(world_from_camera[:3, 3].copy())
            self.recording.log("world/keyframes", rr.Points3D(np.array(self._keyframe_positions), colors=[[255, 140, 0]], radii=0.01))

    def log_keyframes(self, frame_index: int, timestamp_s: float, keyframe_world_from_camera: np.ndarray) -> None:
        """Replace the keyframe positions with corrected ones ((K, 4, 4), e.g. after loop closure)."""
        self._set_time(frame_index, timestamp_s)
        self._keyframe_positions = [pose[:3, 3].copy() for pose in np.asarray(keyframe_world_from_camera)]
        if self._keyframe_positions:
            self.recording.log("world/keyframes", self._rr.Points3D(np.array(self._keyframe_positions),
                                                                    colors=[[255, 140, 0]], radii=0.01))

    def log_sparse_map(self, frame_index: int, timestamp_s: float, points_world_m: np.ndarray, colours: np.ndarray | None = None) -> None:
        """The frontend's map points, (P, 3) metres, with (P, 3) uint8 colours when known."""
        self._set_time(frame_index, timestamp_s)
        self.recording.log("world/map_points", self._rr.Points3D(np.asarray(points_world_m), colors=colours, radii=0.005))

    def log_gaussians(
        self, frame_index: int, timestamp_s: float, means_m: np.ndarray, rgb: np.ndarray, radii_m: np.ndarray
    ) -> None:
        """Gaussian centres (N, 3) metres, colours (N, 3) in [0, 1], radii (N,) metres."""
        self._set_time(frame_index, timestamp_s)
        colours = np.clip(np.asarray(rgb) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        self.recording.log("world/gaussians", self._rr.Points3D(np.asarray(means_m), colors=colours, radii=np.asarray(radii_m)))

    def log_render(self, frame_index: int, timestamp_s: float, rendered_rgb: np.ndarray) -> None:
        """The map rendered at a view, (H, W, 3) uint8."""
        self._set_time(frame_index, timestamp_s)
        self.recording.log("render", self._rr.Image(rendered_rgb).compress(jpeg_quality=JPEG_QUALITY))

    def close(self) -> None:
        """Flush everything to the viewer or the file and end the stream."""
        self.recording.flush()
        self.recording.disconnect()
        if self.recording_path is not None:
            logger.info("rerun recording: %s (open with: rerun %s)", self.recording_path, self.recording_path)


def log_final_state(live_view: RerunViewer, sequence: RgbdSequence, tracking: FrontendResult,
                    mapping: MappingStage | None) -> None:
    """After the frontend: corrected keyframes, the sparse map, the Gaussian centres and a render of the last view."""
    last = len(sequence) - 1
    stamp = float(sequence.timestamps_s[last])
    live_view.log_keyframes(last, stamp, tracking.keyframe_trajectory.world_from_camera)
    if len(tracking.map_points_world_m):
        live_view.log_sparse_map(last, stamp, tracking.map_points_world_m, tracking.map_point_colours)
    if mapping is not None and len(mapping.map):
        gaussians = mapping.map.world_gaussians()
        live_view.log_gaussians(last, stamp, gaussians.means_m.detach().cpu().numpy(), gaussians.rgb.detach().cpu().numpy(),
                                gaussians.log_radii_m.detach().exp().cpu().numpy())
        pose = mapping.rendering_poses(tracking.trajectory)[last]
        live_view.log_render(last, stamp, rgb_uint8(mapping.map.render(mapping.camera, pose).rgb.detach().cpu().numpy()))
