"""COLMAP (pycolmap) structure-from-motion on the colour images of a sequence: the monocular baseline trajectory.

SIFT features, sequential matching and incremental mapping, as ``colmap feature_extractor``,
``sequential_matcher`` and ``mapper`` do, with the sequence's own pinhole intrinsics held fixed (the images
are already undistorted by the reader). COLMAP sees no depth, so its trajectory has an arbitrary scale and
is compared to ground truth after a Sim(3) alignment.
"""

from __future__ import annotations

import dataclasses
import logging
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Sequence

import cv2
import numpy as np

from tambridge.camera import Camera
from tambridge.errors import TambridgeError
from tambridge.geometry import inverse
from tambridge.files import atomic_write_text
from tambridge.trajectory import Trajectory, format_tum_trajectory

if TYPE_CHECKING:
    import pycolmap

logger = logging.getLogger("tambridge.evaluation.colmap")

MONOCULAR_MARKER = "# tambridge: monocular"
"""First comment line of a TUM file whose scale is unknown (COLMAP): ``compare`` aligns it with Sim(3)."""


class ColmapError(TambridgeError):
    """COLMAP could not reconstruct the images (too few features, matches or registered images)."""


@dataclasses.dataclass(frozen=True)
class ColmapOptions:
    """Settings of the COLMAP run.

    ``sequential_overlap``: each image is matched with this many following images. ``init_min_tri_angle_deg``:
    COLMAP's default (16 degrees) suits photo collections; hand-held RGB-D sequences move a few centimetres
    between frames, so a smaller angle lets the mapper start. ``max_features``: SIFT features per image.
    ``num_threads``: -1 uses every core.
    """

    sequential_overlap: int = 10
    init_min_tri_angle_deg: float = 4.0
    max_features: int = 4096
    num_threads: int = -1
    seed: int = 0


@dataclasses.dataclass
class ColmapResult:
    """Registered images of the largest model: their timestamps and ``world_from_camera`` in COLMAP's frame.

    ``trajectory`` holds only registered images (N <= images given), sorted by time; ``image_count`` is the
    number of images given to COLMAP and ``points_world`` (P, 3) the model's sparse points (COLMAP's frame
    and scale).
    """

    trajectory: Trajectory
    image_count: int
    points_world: np.ndarray

    @property
    def registered_count(self) -> int:
        return len(self.trajectory)


MIN_COLMAP_IMAGES = 3
"""The fewest images handed to COLMAP's incremental mapper: fewer cannot make a model worth scoring."""


def run_colmap(
    images_rgb: Iterable[np.ndarray],
    timestamps_s: Sequence[float],
    camera: Camera,
    options: ColmapOptions = ColmapOptions(),
    workspace: Path | None = None,
) -> ColmapResult:
    """Reconstruct the camera path of ``images_rgb`` (each (H, W, 3) uint8, undistorted, in time order).

    ``images_rgb`` is read once (a generator keeps one image in memory); ``timestamps_s`` (N,) are their times;
    ``camera`` their pinhole intrinsics (held fixed). The database, images and model go into ``workspace`` (a
    temporary folder, removed afterwards, when None).
    Raises :class:`ColmapError` when no model of at least three images comes out.
    """
    if len(timestamps_s) < MIN_COLMAP_IMAGES:
        raise ColmapError(f"COLMAP needs at least {MIN_COLMAP_IMAGES} images, got {len(timestamps_s)}; use a smaller "
                          "--every or a larger --max-frames")
    if workspace is None:
        with tempfile.TemporaryDirectory(prefix="tambridge-colmap-") as temp:
            return run_colmap(images_rgb, timestamps_s, camera, options, Path(temp))
    workspace = Path(workspace)
    image_dir = workspace / "images"
    image_dir.mkdir(parents=True, exist_ok=True)
    names = []
    for index, rgb in enumerate(images_rgb):
        assert rgb.shape == (camera.height, camera.width, 3), rgb.shape
        name = f"{index:06d}.png"
        cv2.imwrite(str(image_dir / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        names.append(name)
    if len(names) != len(timestamps_s):
        raise ValueError(f"{len(names)} images but {len(timestamps_s)} timestamps")
    database = workspace / "database.db"
    database.unlink(missing_ok=True)
    # Imported here: pycolmap's native signal handlers would otherwise print a stack dump when any run is stopped.
    import pycolmap

    # COLMAP logs every image at INFO through glog on stderr; keep its warnings and errors only.
    log_level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = int(pycolmap.logging.WARNING)
    try:
        model = _reconstruct(database, image_dir, workspace / "sparse", names, camera, options)
    finally:
        pycolmap.logging.minloglevel = log_level
    return ColmapResult(
        trajectory=trajectory_from_reconstruction(model, dict(zip(names, np.asarray(timestamps_s, float)))),
        image_count=len(names),
        points_world=np.array([point.xyz for point in model.points3D.values()]).reshape(-1, 3),
    )


def _reconstruct(
    database: Path, image_dir: Path, model_dir: Path, names: list[str], camera: Camera, options: ColmapOptions
) -> pycolmap.Reconstruction:
    """Features, sequential matches and incremental mapping; the model with the most registered images."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = f"{camera.fx},{camera.fy},{camera.cx},{camera.cy}"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = options.num_threads
    extraction.sift.max_num_features = options.max_features
    pycolmap.extract_features(
        database, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu,
    )
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = options.sequential_overlap
    pairing.num_threads = options.num_threads
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.num_threads
    pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)

    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = options.num_threads
    mapping.random_seed = options.seed
    mapping.mapper.random_seed = options.seed
    mapping.min_model_size = 3
    mapping.mapper.init_min_tri_angle = options.init_min_tri_angle_deg
    # The intrinsics are calibrated: refining them from a short monocular sequence only adds freedom to drift.
    mapping.ba_refine_focal_length = False
    mapping.ba_refine_principal_point = False
    mapping.ba_refine_extra_params = False
    mapping.mapper.abs_pose_refine_focal_length = False
    mapping.mapper.abs_pose_refine_extra_params = False
    model_dir.mkdir(exist_ok=True)
    models = pycolmap.incremental_mapping(database, image_dir, model_dir, options=mapping)
    if not models:
        raise ColmapError(
            f"COLMAP registered no model from {len(names)} images (too little texture or parallax); "
            "try a smaller --every so consecutive images overlap more"
        )
    model = max(models.values(), key=lambda reconstruction: reconstruction.num_reg_images())
    logger.info("COLMAP: %d models, the largest registers %d of %d images with %d points",
                len(models), model.num_reg_images(), len(names), model.num_points3D())
    return model


def trajectory_from_reconstruction(model: pycolmap.Reconstruction, timestamp_by_name: dict[str, float]) -> Trajectory:
    """The registered images of ``model`` as a trajectory: COLMAP's ``cam_from_world`` inverted, ordered by time."""
    stamps, poses = [], []
    for image in model.images.values():
        if not image.has_pose or image.name not in timestamp_by_name:
            continue
        camera_from_world = np.eye(4)
        camera_from_world[:3, :] = image.cam_from_world().matrix()
        stamps.append(timestamp_by_name[image.name])
        poses.append(inverse(camera_from_world))
    if len(stamps) < 3:
        raise ColmapError(f"COLMAP registered only {len(stamps)} images; try a smaller --every")
    order = np.argsort(stamps)
    return Trajectory(np.asarray(stamps)[order], np.stack(poses)[order])


def write_monocular_trajectory(path: Path, trajectory: Trajectory, source: str = "COLMAP") -> None:
    """Write a TUM file marked as monocular (unknown scale), so ``tambridge compare`` aligns it with Sim(3)."""
    text = f"{MONOCULAR_MARKER} ({source}; scale unknown, align with Sim(3))\n" + format_tum_trajectory(trajectory)
    atomic_write_text(Path(path), text)


def is_monocular_trajectory_file(path: Path) -> bool:
    """True when the TUM file's comment header carries :data:`MONOCULAR_MARKER`."""
    with open(path, errors="replace") as handle:
        for line in handle:
            if not line.startswith("#"):
                return False
            if line.startswith(MONOCULAR_MARKER):
                return True
    return False
