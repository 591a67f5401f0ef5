"""``tambridge export``: a finished run's poses, images and points as a COLMAP model or as nerfstudio data.

The run folder gives the poses (``trajectory.txt``), the settings the sequence was read with (``config.yaml``),
the keyframes, map points and their observations, and the sequence's folder (``sparse_map.npz``); the sequence
gives the images. Everything is written into a hidden folder beside the target, renamed to it at the end: an
export that fails leaves nothing behind.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from tambridge.camera import Camera
from tambridge.checkpoint import sequence_differences, sequence_fingerprint
from tambridge.config import load_config
from tambridge.errors import ExportError
from tambridge.evaluation.metrics import read_metrics
from tambridge.export.colmap_model import ModelImage, build_model, write_model
from tambridge.export.images import ImageMode, image_camera, image_name, pixels_in_images, write_frames
from tambridge.export.mesh import read_mesh
from tambridge.export.nerfstudio import transforms, write_point_cloud, write_transforms
from tambridge.export.sparse_map import SparseMap, points_seen, read_sparse_map
from tambridge.files import check_new_or_empty_folder, staged_folder
from tambridge.io.tum import RgbdSequence, open_sequence
from tambridge.settings import Choice
from tambridge.trajectory import Trajectory, read_tum_trajectory

logger = logging.getLogger("tambridge.pipelines.export")

TIMESTAMP_TOLERANCE_S = 1e-5
"""trajectory.txt's timestamps (written to the microsecond) against the sequence's."""


class ExportFormat(Choice):
    colmap = "colmap"
    nerfstudio = "nerfstudio"


@dataclasses.dataclass
class RunRecord:
    """What a finished run says for an export: its folder, per-frame poses, sequence (read as the run read it) and
    sparse map."""

    run_dir: Path
    trajectory: Trajectory
    sequence: RgbdSequence
    sparse_map: SparseMap


@dataclasses.dataclass
class Points:
    """The exported points: (P, 3) world metres, (P, 3) uint8 RGB, and where they come from (for the user)."""

    world_m: np.ndarray
    colours: np.ndarray
    source: str
    tracked: bool


@dataclasses.dataclass
class ExportResult:
    """The folder written, its image and point counts, where the points came from, and (COLMAP with points that
    have tracks, else None) the point observations the model's tracks hold."""

    output_dir: Path
    images: int
    points: int
    points_source: str
    observations: int | None


def export_run(run_dir: Path, output_dir: Path | None = None, format: str = "colmap", frames: str = "keyframes",
               images: str = "copy", text: bool = False) -> ExportResult:
    """Export the run in ``run_dir`` as ``format`` into ``output_dir`` (default ``run_dir/export_FORMAT``; it must
    not exist or be empty). ``frames``: ``keyframes``, ``all`` or ``every:N``; ``images``: :class:`ImageMode`;
    ``text``: COLMAP's text files beside its binary ones."""
    export_format = _choice(ExportFormat, format, "--format")
    mode = _choice(ImageMode, images, "--images")
    run_dir = Path(run_dir)
    output_dir = Path(output_dir) if output_dir is not None else run_dir / f"export_{export_format}"
    check_new_or_empty_folder(output_dir, "-o", error=ExportError)
    record = read_run(run_dir)
    frame_indices = select_frames(frames, record)
    camera = image_camera(record.sequence, mode)
    points = export_points(record)
    with staged_folder(output_dir) as staging:
        if export_format == ExportFormat.colmap:
            observations = write_colmap(staging, record, frame_indices, camera, mode, points, text)
        else:
            write_nerfstudio(staging, record, frame_indices, camera, mode, points)
            observations = None
    logger.info("exported %d images and %d points (%s) to %s", len(frame_indices), len(points.world_m), points.source,
                output_dir)
    return ExportResult(output_dir, len(frame_indices), len(points.world_m), points.source,
                        observations if points.tracked else None)


def read_run(run_dir: Path) -> RunRecord:
    """Read a finished run's folder and open its sequence as the run did; one-line errors for what is missing and
    for a sequence that no longer holds the frames the run read (metrics.json's ``sequence_fingerprint``)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ExportError(f"{run_dir}: not a folder; pass the -o folder of a 'tambridge reconstruct' run")
    trajectory_path = run_dir / "trajectory.txt"
    if not trajectory_path.is_file():
        raise ExportError(f"{trajectory_path}: not found; pass the -o folder of a finished 'tambridge reconstruct' run")
    # metrics.json is written last: its presence says the run finished.
    metrics = read_metrics(run_dir / "metrics.json")
    folder = Path(metrics.sequence)
    sparse_map = read_sparse_map(run_dir / "sparse_map.npz")
    if not folder.is_dir():
        raise ExportError(f"{folder}: the run's sequence folder is gone (moved or deleted); the export needs its "
                          f"images: put it back there")
    if not (run_dir / "config.yaml").is_file():
        raise ExportError(f"{run_dir / 'config.yaml'}: not found; the run folder is incomplete (it says how the sequence "
                          "was read): run reconstruct again")
    config = load_config(run_dir / "config.yaml")
    camera_file = config.input.camera_file
    if camera_file is not None and not Path(camera_file).is_absolute() and not Path(camera_file).is_file():
        raise ExportError(f"{run_dir / 'config.yaml'}: input.camera_file {camera_file} is a relative path not found from "
                          f"here; run the export from the folder the run was started in")
    sequence = open_sequence(folder, camera_file=None if camera_file is None else Path(camera_file),
                             stride=config.input.stride, max_frames=config.input.max_frames)
    trajectory = read_tum_trajectory(trajectory_path)
    if len(trajectory) != len(sequence) or np.abs(trajectory.timestamps_s - sequence.timestamps_s).max() > TIMESTAMP_TOLERANCE_S:
        raise ExportError(f"{trajectory_path}: {len(trajectory)} poses do not match the {len(sequence)} frames of {folder} "
                          "read with config.yaml's input settings; the sequence changed since the run")
    if metrics.sequence_fingerprint is not None:
        # The folder is metrics.json's "sequence"; what matters here is that it still holds the frames the run read.
        current = sequence_fingerprint(sequence)
        differences = sequence_differences({**metrics.sequence_fingerprint, "folder": current["folder"]}, current,
                                           images_only=True)
        if differences:
            raise ExportError(f"{folder}: not the frames the run read ({'; '.join(differences)}); the export would pair "
                              "the run's poses with other images: run reconstruct again on the folder as it is now")
    return RunRecord(run_dir, trajectory, sequence, sparse_map)


def select_frames(spec: str, record: RunRecord) -> list[int]:
    """Frame indices of ``spec``: ``keyframes`` (the run's keyframes, culled ones included), ``all``, or ``every:N``
    (frames 0, N, 2N, ...)."""
    spec = str(spec).strip().lower()
    if spec == "keyframes":
        return sorted(set(record.sparse_map.keyframe_frame_indices.values()))
    if spec == "all":
        return list(range(len(record.sequence)))
    if spec.startswith("every:"):
        try:
            step = int(spec.split(":", 1)[1])
        except ValueError:
            step = 0
        if step >= 1:
            return list(range(0, len(record.sequence), step))
    raise ExportError(f"--frames {spec!r}: expected keyframes, all or every:N with N >= 1")


def export_points(record: RunRecord) -> Points:
    """The ORB frontend's map points (with tracks); for a frontend without a sparse map the vertices of the run's
    TSDF mesh (mesh.ply); else none."""
    sparse_map = record.sparse_map
    if len(sparse_map.points_world_m):
        return Points(sparse_map.points_world_m, sparse_map.point_colours, "the ORB frontend's map points", True)
    mesh_path = record.run_dir / "mesh.ply"
    if mesh_path.is_file():
        mesh = read_mesh(mesh_path)
        colours = getattr(mesh.visual, "vertex_colors", None)
        colours = np.full((len(mesh.vertices), 3), 128, np.uint8) if colours is None else np.asarray(colours)[:, :3]
        return Points(np.asarray(mesh.vertices, np.float64), colours.astype(np.uint8),
                      "the vertices of mesh.ply (this frontend keeps no sparse map; the points have no tracks)", False)
    return Points(np.zeros((0, 3)), np.zeros((0, 3), np.uint8),
                  "none (this frontend keeps no sparse map and the run wrote no mesh.ply)", False)


def write_colmap(folder: Path, record: RunRecord, frame_indices: list[int], camera: Camera, mode: ImageMode,
                 points: Points, text: bool) -> int:
    """``folder/images/`` and ``folder/sparse/0/``; returns the number of point observations in the model.

    A keyframe's image holds its recorded keypoints; any other frame's the map points it sees by its pose and depth
    (:func:`points_seen`), so that every image has points (gsplat's depth loss looks each image's up)."""
    names = [image_name(index, mode, record.sequence) for index in frame_indices]
    write_frames(record.sequence, frame_indices, names, mode, folder / "images")
    keyframe_of_frame = {frame: keyframe for keyframe, frame in record.sparse_map.keyframe_frame_indices.items()}
    observations = record.sparse_map.observations
    images = []
    for index, name in zip(frame_indices, names):
        world_from_camera = record.trajectory.world_from_camera[index]
        if not points.tracked:
            rows, pixels_px = np.zeros(0, np.int64), np.zeros((0, 2))
        elif index in keyframe_of_frame:
            seen = observations.keyframe_ids == keyframe_of_frame[index]
            rows, pixels_px = observations.point_rows[seen], observations.keypoints_px[seen]
        else:
            rows, pixels_px = points_seen(points.world_m, world_from_camera, record.sequence.camera,
                                          record.sequence.frame_depth_m(index))
        pixels_px = pixels_in_images(pixels_px, record.sequence, mode)
        inside = camera.in_image(pixels_px)
        images.append(ModelImage(name, world_from_camera, rows[inside], pixels_px[inside]))
    pointless = [image.name for image in images if len(image.point_rows) == 0]
    if points.tracked and pointless:
        # gsplat's depth loss, for one, stops at an image that sees no point.
        logger.warning("%d exported images see no map point (no depth measures one where it projects), e.g. %s",
                       len(pointless), pointless[0])
    model = build_model(camera, images, points.world_m, points.colours)
    write_model(model, folder / "sparse" / "0", text)
    return int(model.compute_num_observations())


def write_nerfstudio(folder: Path, record: RunRecord, frame_indices: list[int], camera: Camera, mode: ImageMode,
                     points: Points) -> None:
    """``folder/transforms.json`` with ``images/``, ``depth/`` and ``points3D.ply`` (without points: none)."""
    names = [image_name(index, mode, record.sequence) for index in frame_indices]
    write_frames(record.sequence, frame_indices, names, mode, folder / "images", folder / "depth")
    ply_path = None
    if len(points.world_m):
        ply_path = "points3D.ply"
        write_point_cloud(folder / ply_path, points.world_m, points.colours)
    contents = transforms(camera, [f"images/{name}" for name in names],
                          record.trajectory.world_from_camera[frame_indices],
                          [f"depth/{Path(name).with_suffix('.png').name}" for name in names], ply_path)
    write_transforms(folder / "transforms.json", contents)


def _choice(kind: type[Choice], value: str, option: str) -> Choice:
    parsed = kind.parse(value)
    if parsed is None:
        raise ExportError(f"{option} {value!r}: expected {' or '.join(member.value for member in kind)}")
    return parsed
