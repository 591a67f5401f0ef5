"""Checkpoints of a ``reconstruct`` run, so that ``--resume`` continues a killed run from its last one.

A checkpoint is one numpy archive, ``<output>/checkpoint/checkpoint.npz``, written atomically (temp file + rename),
so a run killed while writing one leaves the previous checkpoint whole. It holds the state dicts of the stateful
classes (the frontend's sparse map, keyframe database, motion model and frame records; the mapping stage's
Gaussian map with its Adam state, views and random generator), the index of the next frame to track, the run's
counters and timings, and what it was made from: the resolved config and a fingerprint of the sequence, which a
resumed run must match. Threads, locks and what a constructor rebuilds from the config (ORB extractor,
vocabulary) are not saved.

The archive holds only plain arrays (loaded with ``allow_pickle=False``) and one JSON document, ``document``, with
the format name, :data:`CHECKPOINT_VERSION` and the state as a tree (:func:`tambridge.state.encode_state`) that
names the arrays. Loading builds objects only of the types in :func:`state_types`, so no checkpoint, crafted or
not, runs code when it loads. Everything is encoded in one pass, so objects shared between the states (a keyframe
and the frontend's reference to it) stay shared after loading.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np

from tambridge.errors import CheckpointError
from tambridge.files import atomic_path
from tambridge.io.tum import RgbdSequence
from tambridge.settings import FRACTION, NON_NEGATIVE, setting
from tambridge.state import StateCodec, StateTypes, decode_state, dotted_items, encode_state

logger = logging.getLogger("tambridge.checkpoint")

CHECKPOINT_VERSION = 4
"""Bumped whenever what a checkpoint holds changes; a checkpoint of another version is refused."""
CHECKPOINT_FORMAT = "tambridge checkpoint"
CHECKPOINT_FOLDER = "checkpoint"
CHECKPOINT_NAME = "checkpoint.npz"
PICKLE_CHECKPOINT_NAME = "checkpoint.pkl"
"""Where tambridge before checkpoint version 2 wrote its (pickled) checkpoints; never read, only named in errors."""
DOCUMENT_ARRAY = "document"
"""The archive member holding the JSON document (UTF-8 bytes as a uint8 array)."""
IGNORED_CONFIG_SECTIONS = ("checkpoint",)
"""Config sections a resumed run may change: how often it checkpoints does not change its results."""
ORB_KEYS = "frontend.orb."
"""Where the config keeps the ORB settings, which a run records as adapted to the image size (config.yaml)."""
SEQUENCE_INDEX_FILES = ("rgb.txt", "depth.txt", "groundtruth.txt")
"""The files of a sequence folder that say which frames it has (:func:`tambridge.io.tum.open_sequence` reads them)."""


@dataclasses.dataclass
class CheckpointConfig:
    """Checkpoints for ``reconstruct --resume``: after a keyframe, once ``every_keyframes`` keyframes (0: never) and
    ``min_interval_s`` seconds have passed since the last one, the frontend and mapping state are written atomically
    to ``<output>/checkpoint/``; a run stopped by a signal writes one too; a finished run removes them."""

    every_keyframes: int = setting(10, "write a checkpoint for --resume every n keyframes (0: never)", NON_NEGATIVE)
    # Keeps the cost of checkpoints a small share of the run where keyframes come fast.
    min_interval_s: float = setting(20.0, "seconds of wall time at least between two checkpoints", NON_NEGATIVE)
    # The state, and so a checkpoint's time, grows with the session: at fixed intervals their total would grow with
    # its square.
    max_time_share: float = setting(0.02, "after a checkpoint that took t seconds, the next waits at least "
                                          "t / max_time_share seconds (checkpoints take at most this share of the run)",
                                    FRACTION)
    # Keyframes stop coming where a camera stays on ground its map covers (keyframe_revisit_distance_m), and with
    # them the checkpoints of every_keyframes.
    max_interval_s: float = setting(600.0, "seconds of wall time after which a checkpoint is written after the next "
                                           "frame, however few keyframes came (0: only every_keyframes)", NON_NEGATIVE)


@dataclasses.dataclass
class Checkpoint:
    """What ``--resume`` needs. ``next_frame``: frames ``[0, next_frame)`` are tracked and mapped.

    ``config`` is the resolved config as a dict (:func:`~tambridge.config.to_dict`); ``sequence`` is
    :func:`sequence_fingerprint`; ``frontend`` and ``mapping`` (None with the mapper off) are the stages' state
    dicts; ``run`` holds the pipeline's own counters (stage seconds, warnings, elapsed seconds, ...).
    """

    next_frame: int
    config: dict
    sequence: dict
    frontend: dict
    mapping: dict | None
    run: dict
    version: int = CHECKPOINT_VERSION


def checkpoint_path(output_dir: Path) -> Path:
    """Where a run into ``output_dir`` keeps its checkpoint."""
    return Path(output_dir) / CHECKPOINT_FOLDER / CHECKPOINT_NAME


def remove_checkpoint(output_dir: Path) -> None:
    """Remove the checkpoint of a run into ``output_dir`` (the run is whole), and its folder unless something else
    lies in it."""
    path = checkpoint_path(output_dir)
    path.unlink(missing_ok=True)
    if path.parent.is_dir() and not any(path.parent.iterdir()):
        path.parent.rmdir()


START_OVER = "pass --overwrite instead of --resume to start over (or give another -o)"
"""How to go on from a checkpoint that cannot be resumed: a plain start refuses a folder that holds one."""


# ---- the sequence ---------------------------------------------------------------------------------------------


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def sequence_fingerprint(sequence: RgbdSequence) -> dict:
    """What identifies the frames a run reads: the resolved folder, frame count, a hash of the timestamps, the
    sensor (camera, depth encoding and, for unregistered colour, the colour camera: a resumed run must resample
    colour alike), and SHA-256 of the folder's index files (:data:`SEQUENCE_INDEX_FILES`, those it has) and of the
    colour and depth images of the first, middle and last frame (``files_sha256``, by path in the folder)."""
    folder = Path(sequence.folder).resolve()
    timestamps = np.ascontiguousarray(np.asarray(sequence.timestamps_s, np.float64))
    files = [folder / name for name in SEQUENCE_INDEX_FILES if (folder / name).is_file()]
    sampled = sorted({0, len(sequence) // 2, len(sequence) - 1}) if len(sequence) else []
    names = {str(path.relative_to(folder)): path for path in files}
    for paths in (sequence.rgb_paths, sequence.depth_paths):
        for index in sampled:
            path = Path(paths[index])
            # By its path in the folder; an image that rgb.txt names by an absolute path elsewhere, by that.
            inside = Path(sequence.folder) in path.parents
            names[str(path.relative_to(sequence.folder)) if inside else str(path.resolve())] = path
    # Every image's size and modification time: an edited frame between those hashed changes them (a stat each).
    # Sizes alone too, for the export, which a copy that sets new times must not stop.
    stats, sizes = hashlib.sha1(), hashlib.sha1()
    for path in (*sequence.rgb_paths, *sequence.depth_paths):
        status = Path(path).stat()
        stats.update(f"{Path(path).name} {status.st_size} {status.st_mtime_ns}\n".encode())
        sizes.update(f"{Path(path).name} {status.st_size}\n".encode())
    return {
        "folder": str(folder),
        "frames": int(len(timestamps)),
        "timestamps_sha1": hashlib.sha1(timestamps.tobytes()).hexdigest(),
        "camera": repr(sequence.sensor),
        "files_sha256": {name: _sha256(path) if path.is_file() else "missing" for name, path in names.items()},
        "images_stat_sha1": stats.hexdigest(),
        "images_size_sha1": sizes.hexdigest(),
    }


def sequence_differences(saved: dict, current: dict, images_only: bool = False) -> list[str]:
    """What differs between two :func:`sequence_fingerprint`, in words. ``images_only``: what an export reads, the
    frames' images: groundtruth.txt and the images' modification times (a copy without -p sets new ones) are left
    out, their sizes compared instead."""
    differences = []
    if saved.get("folder") != current["folder"]:
        differences.append(f"folder {saved.get('folder')}, now {current['folder']}")
    if saved.get("frames") != current["frames"]:
        differences.append(f"{saved.get('frames')} frames, now {current['frames']}")
    elif saved.get("timestamps_sha1") != current["timestamps_sha1"]:
        differences.append("other frame timestamps")
    if saved.get("camera") != current["camera"]:
        differences.append(f"camera {saved.get('camera')}, now {current['camera']}")
    saved_files = saved.get("files_sha256")
    saved_files = saved_files if type(saved_files) is dict else {}
    changed = sorted(name for name in saved_files.keys() | current["files_sha256"].keys()
                     if saved_files.get(name) != current["files_sha256"].get(name)
                     and not (images_only and name == "groundtruth.txt"))
    if changed:
        differences.append(f"other {', '.join(changed[:4])}{', ...' if len(changed) > 4 else ''}")
    if differences:
        return differences
    # Fingerprints written before the sizes had their own digest compare sizes and times together.
    if images_only and "images_size_sha1" in saved:
        if saved["images_size_sha1"] != current["images_size_sha1"]:
            differences.append("images changed since (their sizes)")
    elif saved.get("images_stat_sha1") != current["images_stat_sha1"]:
        differences.append("images changed since (their sizes or modification times)")
    return differences


# ---- what a checkpoint may hold -------------------------------------------------------------------------------


def _generator_parts(generator: np.random.Generator) -> dict:
    return {"bit_generator": generator.bit_generator.state}


def _generator(parts: dict) -> np.random.Generator:
    state = parts["bit_generator"]
    if type(state) is not dict or state.get("bit_generator") != "PCG64":
        raise ValueError("a random generator that is not numpy's default PCG64")
    generator = np.random.Generator(np.random.PCG64())
    generator.bit_generator.state = state
    return generator


def _image_array(value: object) -> np.ndarray:
    """``value`` checked to be an image Open3D can hold, as a contiguous array."""
    if type(value) is not np.ndarray or value.dtype not in (np.uint8, np.uint16, np.float32) \
            or value.ndim not in (2, 3) or not value.size:
        raise ValueError("an Open3D image that is not a non-empty (H, W) or (H, W, C) uint8, uint16 or float32 array")
    return np.ascontiguousarray(value)


@functools.cache
def state_types() -> StateTypes:
    """Every type a checkpoint may hold beyond the built-in ones, and so the only types loading one creates."""
    # Imported here: the stages import the config, which imports this module.
    import open3d as o3d

    from tambridge.bridge.blur import ExposurePath
    from tambridge.bridge.refinement import RefinementResult
    from tambridge.bridge.view import MappingView
    from tambridge.bridge.view_selection import Candidate, Selection
    from tambridge.frontend.open3d.frontend import _Keyframe as Open3dKeyframe
    from tambridge.frontend.orb.dense_depth import DenseReference
    from tambridge.frontend.orb.features import FrameFeatures
    from tambridge.frontend.orb.frontend import _FrameRecord
    from tambridge.frontend.orb.loop_closing import LoopConsistency
    from tambridge.frontend.orb.matching import KeypointGrid
    from tambridge.frontend.orb.slam_map import Keyframe, MapPoints, SlamMap
    from tambridge.frontend.orb.vocabulary import KeyframeDatabase
    from tambridge.frontend.pose_graph import PoseEdge
    from tambridge.gaussians.mapper import ViewExposure, ViewImages

    cloud_parts = ("points", "colors", "normals")

    def cloud(parts: dict) -> o3d.geometry.PointCloud:
        value = o3d.geometry.PointCloud()
        for name, points in parts.items():
            if name not in cloud_parts or type(points) is not np.ndarray or points.dtype != np.float64 \
                    or points.ndim != 2 or points.shape[1] != 3:
                raise ValueError(f"an Open3D point cloud with {name} that are not (N, 3) float64")
            setattr(value, name, o3d.utility.Vector3dVector(points))
        return value

    def rgbd(parts: dict) -> o3d.geometry.RGBDImage:
        value = o3d.geometry.RGBDImage()
        value.color, value.depth = (o3d.geometry.Image(_image_array(parts[name])) for name in ("color", "depth"))
        return value

    return StateTypes(
        records=(Keyframe, KeypointGrid, FrameFeatures, MapPoints, SlamMap, KeyframeDatabase, LoopConsistency,
                 _FrameRecord, DenseReference, Open3dKeyframe, PoseEdge, MappingView, RefinementResult, ViewImages,
                 Candidate, ExposurePath),
        enums=(Selection,),
        codecs=(
            StateCodec(ViewExposure, ViewExposure.state_dict, ViewExposure.from_state_dict),
            StateCodec(np.random.Generator, _generator_parts, _generator),
            StateCodec(o3d.geometry.PointCloud, lambda value: {name: np.asarray(getattr(value, name)) for name in
                                                               cloud_parts if len(getattr(value, name))}, cloud),
            StateCodec(o3d.geometry.RGBDImage, lambda value: {"color": np.asarray(value.color),
                                                              "depth": np.asarray(value.depth)}, rgbd),
        ),
    )


# ---- files ----------------------------------------------------------------------------------------------------

_FIELD_TYPES = {"next_frame": (int,), "config": (dict,), "sequence": (dict,), "frontend": (dict,),
                "mapping": (dict, type(None)), "run": (dict,)}
"""The :class:`Checkpoint` fields stored as the state, with the types a loaded one must have."""


def save_checkpoint(path: Path, checkpoint: Checkpoint) -> int:
    """Write ``checkpoint`` to ``path`` atomically; returns its size in bytes. The state's arrays are written as
    they are, so writing one needs no second copy of the state in memory."""
    fields = {name: getattr(checkpoint, name) for name in _FIELD_TYPES}
    fields["next_frame"] = int(checkpoint.next_frame)
    tree, arrays = encode_state(fields, state_types())
    document = json.dumps({"format": CHECKPOINT_FORMAT, "version": checkpoint.version, "checkpoint": tree},
                          separators=(",", ":")).encode()
    with atomic_path(path) as temp_path, open(temp_path, "wb") as handle:
        np.savez(handle, allow_pickle=False, **{DOCUMENT_ARRAY: np.frombuffer(document, np.uint8)}, **arrays)
        return handle.tell()


def _read_checkpoint(path: Path) -> Checkpoint:
    with open(path, "rb") as handle:
        # Checked here, not left to np.load: anything but a zip archive is refused before numpy looks at it.
        if handle.read(4) != b"PK\x03\x04":
            raise ValueError("not a numpy .npz archive")
    with np.load(path, allow_pickle=False) as archive:
        raw = archive[DOCUMENT_ARRAY]
        if raw.dtype != np.uint8 or raw.ndim != 1:
            raise ValueError(f"its {DOCUMENT_ARRAY} is not a byte string")
        document = json.loads(raw.tobytes())
        if type(document) is not dict or document.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"no {CHECKPOINT_FORMAT!r} document")
        version = document.get("version")
        if version != CHECKPOINT_VERSION:
            raise CheckpointError(f"{path}: checkpoint version {version}, this tambridge reads version "
                                  f"{CHECKPOINT_VERSION}; {START_OVER}")
        fields = decode_state(document["checkpoint"], archive, state_types())
    if type(fields) is not dict or set(fields) != set(_FIELD_TYPES) \
            or any(type(fields[name]) not in kinds for name, kinds in _FIELD_TYPES.items()):
        raise ValueError("its state is not that of a run")
    return Checkpoint(**fields, version=version)


def find_checkpoint(path: Path) -> Checkpoint | None:
    """The checkpoint at ``path`` (:func:`load_checkpoint`), or None where a run left none (it was killed before its
    first one); a pickle of an older tambridge is refused, never read."""
    path = Path(path)
    if not path.is_file() and not path.with_name(PICKLE_CHECKPOINT_NAME).is_file():
        return None
    return load_checkpoint(path)


def load_checkpoint(path: Path) -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint`; a one-line :class:`CheckpointError` naming the file
    and how to start over when it is missing, truncated, of another version or not a tambridge checkpoint."""
    path = Path(path)
    if not path.is_file():
        pickled = path.with_name(PICKLE_CHECKPOINT_NAME)
        if pickled.is_file():
            raise CheckpointError(f"{pickled}: a checkpoint of an older tambridge, a pickle, which this one never "
                                  f"loads (loading a pickle can run any code); {START_OVER}")
        raise CheckpointError(f"{path}: no checkpoint to resume from (the run finished, was stopped before its first "
                              f"checkpoint, or ran with checkpoint.every_keyframes=0); run without --resume")
    try:
        return _read_checkpoint(path)
    except CheckpointError:
        raise
    except Exception as error:  # noqa: BLE001 - whatever is wrong with the file, the user can only start over
        reason = " ".join(f"{type(error).__name__}: {error}".split())
        raise CheckpointError(f"{path}: not a readable tambridge checkpoint ({reason[:300]}); "
                              f"{START_OVER}") from error


def check_resumable(path: Path, checkpoint: Checkpoint, config: dict, sequence: dict) -> None:
    """Raise :class:`CheckpointError` (naming ``path`` and what differs) unless ``checkpoint`` was written by a run
    of the same config (sections in :data:`IGNORED_CONFIG_SECTIONS` aside) over the same sequence.

    ``config`` is the resumed run's resolved config as a dict, ``sequence`` its :func:`sequence_fingerprint`.
    """
    saved = dotted_items({k: v for k, v in checkpoint.config.items() if k not in IGNORED_CONFIG_SECTIONS})
    current = dotted_items({k: v for k, v in config.items() if k not in IGNORED_CONFIG_SECTIONS})
    differing = sorted(key for key in saved.keys() | current.keys() if saved.get(key, "<absent>") != current.get(key, "<absent>"))
    if differing:
        shown = ", ".join(f"{key}: {saved.get(key, '<absent>')!r} in the checkpoint, {current.get(key, '<absent>')!r} now"
                          for key in differing[:5])
        # Both sides are the run's config.yaml values: ORB's counts and pixel sizes there are adapted to the image.
        adapted = any(key.startswith(ORB_KEYS) for key in differing[:5]) * "; ORB values as adapted to the image size"
        raise CheckpointError(f"{path}: the checkpoint was written with another config ({shown}"
                              f"{', ...' if len(differing) > 5 else ''}{adapted}); resume with the same options "
                              f"(see config.yaml beside it) or {START_OVER}")
    differences = sequence_differences(checkpoint.sequence, sequence)
    if differences:
        raise CheckpointError(f"{path}: the checkpoint is of another sequence ({'; '.join(differences)}); resume with "
                              f"the same sequence or {START_OVER}")
    if checkpoint.next_frame > sequence["frames"]:
        raise CheckpointError(f"{path}: the checkpoint is at frame {checkpoint.next_frame} of a "
                              f"{sequence['frames']}-frame sequence; {START_OVER}")


class KeyframeCheckpoints:
    """Writes a checkpoint after a keyframe once ``every_keyframes`` keyframes (never when it is 0) and
    ``min_interval_s`` seconds of wall time have passed since the last checkpoint (or the start), and at least the
    last checkpoint's seconds (snapshot and write) over ``max_time_share``; after any frame once ``max_interval_s``
    (0: never) and that least wait have passed.

    ``snapshot(next_frame)`` builds the :class:`Checkpoint` when one is due.
    """

    def __init__(self, path: Path, every_keyframes: int, snapshot: Callable[[int], Checkpoint],
                 keyframes_so_far: int = 0, min_interval_s: float = 0.0, max_time_share: float = 1.0,
                 max_interval_s: float = 0.0, clock: Callable[[], float] = time.perf_counter) -> None:
        if every_keyframes < 0:
            raise CheckpointError(f"checkpoint.every_keyframes={every_keyframes}: expected 0 (off) or a positive count")
        self.path = Path(path)
        self.every_keyframes = every_keyframes
        self.min_interval_s = min_interval_s
        self.max_time_share = max_time_share
        self.max_interval_s = max_interval_s
        self.snapshot = snapshot
        self.keyframes = keyframes_so_far
        self.clock = clock
        self._keyframes_at_last = keyframes_so_far
        self._time_of_last = clock()
        self._interval_s = min_interval_s
        self._next_frame_written: int | None = None

    def after_frame(self, next_frame: int, is_keyframe: bool) -> None:
        """Call after each frame is tracked and mapped; ``next_frame`` is the index of the frame that comes next."""
        self.keyframes += is_keyframe
        if not self.every_keyframes:
            return
        waited_s = self.clock() - self._time_of_last
        if waited_s < self._interval_s:
            return
        if ((is_keyframe and self.keyframes - self._keyframes_at_last >= self.every_keyframes)
                or 0 < self.max_interval_s <= waited_s):
            self.write(next_frame)

    def write(self, next_frame: int) -> None:
        """Write a checkpoint now (frames ``[0, next_frame)`` tracked and mapped); the next waits at least
        ``min_interval_s``, and at least this one's seconds over ``max_time_share``."""
        started = self.clock()
        size = save_checkpoint(self.path, self.snapshot(next_frame))
        self._keyframes_at_last, self._time_of_last = self.keyframes, self.clock()
        self._interval_s = max(self.min_interval_s, (self._time_of_last - started) / self.max_time_share)
        self._next_frame_written = next_frame
        logger.info("checkpoint at frame %d (%d keyframes): %s, %.1f MB in %.2f s; the next in %.0f s at the earliest",
                    next_frame, self.keyframes, self.path, size / 1e6, self._time_of_last - started, self._interval_s)

    def write_unless_written(self, next_frame: int) -> None:
        """:meth:`write`, unless this object's last checkpoint is already at ``next_frame`` (the same state)."""
        if self._next_frame_written != next_frame:
            self.write(next_frame)
