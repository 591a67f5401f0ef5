"""Checkpoints of a ``reconstruct`` run, so that ``--resume`` continues a killed run from its last one.

A checkpoint is one pickle, ``<output>/checkpoint/checkpoint.pkl``, written atomically (temp file + rename), so a
run killed while writing one leaves the previous checkpoint whole. It holds the state dicts of the stateful
classes (the frontend's sparse map, keyframe database, motion model and frame records; the mapping stage's
Gaussian map with its Adam state, views and random generator), the index of the next frame to track, the run's
counters and timings, and what it was made from: the resolved config and a fingerprint of the sequence, which a
resumed run must match. Threads, locks and what a constructor rebuilds from the config (ORB extractor,
vocabulary) are not saved; every object in one checkpoint is pickled in a single pass, so objects shared between
them (a keyframe and the frontend's reference to it) stay shared after loading.

Pickle runs code when it loads: resume only from checkpoints your own runs wrote.
"""

from __future__ import annotations

import copyreg
import dataclasses
import hashlib
import logging
import pickle
from pathlib import Path
from typing import Callable

import numpy as np

from tambridge.errors import CheckpointError
from tambridge.state import dotted_items
from tambridge.files import atomic_path
from tambridge.settings import NON_NEGATIVE, setting

logger = logging.getLogger("tambridge.checkpoint")

CHECKPOINT_VERSION = 1
"""Bumped whenever what a checkpoint holds changes; a checkpoint of another version is refused."""
CHECKPOINT_FOLDER = "checkpoint"
CHECKPOINT_NAME = "checkpoint.pkl"
IGNORED_CONFIG_SECTIONS = ("checkpoint",)
"""Config sections a resumed run may change: how often it checkpoints does not change its results."""


@dataclasses.dataclass
class CheckpointConfig:
    """Checkpoints for ``reconstruct --resume``: every ``every_keyframes`` keyframes (0: never) the frontend and
    mapping state are written atomically to ``<output>/checkpoint/``; a finished run removes them."""

    every_keyframes: int = setting(0, "write a checkpoint for --resume every n keyframes (0: never)", NON_NEGATIVE)


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


# ---- the sequence ---------------------------------------------------------------------------------------------


def sequence_fingerprint(folder: Path, timestamps_s: np.ndarray, sensor: object) -> dict:
    """What identifies the frames a run reads: folder, frame count, a hash of the timestamps, the sensor (camera,
    depth encoding and, for unregistered colour, the colour camera: a resumed run must resample colour alike)."""
    timestamps = np.ascontiguousarray(np.asarray(timestamps_s, np.float64))
    return {
        "folder": str(Path(folder).resolve()),
        "frames": int(len(timestamps)),
        "timestamps_sha1": hashlib.sha1(timestamps.tobytes()).hexdigest(),
        "camera": repr(sensor),
    }


# ---- files ----------------------------------------------------------------------------------------------------


def _reduce_open3d(kind: str, arrays: dict[str, np.ndarray]):
    return _rebuild_open3d, (kind, arrays)


def _rebuild_open3d(kind: str, arrays: dict[str, np.ndarray]):
    import open3d as o3d

    if kind == "PointCloud":
        cloud = o3d.geometry.PointCloud()
        for name, values in arrays.items():
            setattr(cloud, name, o3d.utility.Vector3dVector(values))
        return cloud
    if kind == "Image":
        return o3d.geometry.Image(arrays["data"])
    rgbd = o3d.geometry.RGBDImage()
    rgbd.color, rgbd.depth = o3d.geometry.Image(arrays["color"]), o3d.geometry.Image(arrays["depth"])
    return rgbd


def _open3d_reducers() -> dict[type, Callable]:
    """Pickle support for the Open3D objects the Open3D frontends keep (their pybind types have none)."""
    try:
        import open3d as o3d
    except ImportError:
        return {}
    geometry = o3d.geometry

    def cloud(value):
        return _reduce_open3d("PointCloud", {name: np.asarray(getattr(value, name)).copy()
                                             for name in ("points", "colors", "normals") if len(getattr(value, name))})

    return {
        geometry.PointCloud: cloud,
        geometry.Image: lambda value: _reduce_open3d("Image", {"data": np.asarray(value).copy()}),
        geometry.RGBDImage: lambda value: _reduce_open3d(
            "RGBDImage", {"color": np.asarray(value.color).copy(), "depth": np.asarray(value.depth).copy()}),
    }


def save_checkpoint(path: Path, checkpoint: Checkpoint) -> int:
    """Write ``checkpoint`` to ``path`` atomically; returns its size in bytes. Pickled straight into the file, so
    writing one needs no second copy of the state in memory."""
    with atomic_path(path) as temp_path, open(temp_path, "wb") as handle:
        pickler = pickle.Pickler(handle, protocol=pickle.HIGHEST_PROTOCOL)
        pickler.dispatch_table = {**copyreg.dispatch_table, **_open3d_reducers()}
        pickler.dump(checkpoint)
        return handle.tell()


def load_checkpoint(path: Path) -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint`; a :class:`CheckpointError` naming the file otherwise."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint to resume from; run without --resume, with "
                              f"--set checkpoint.every_keyframes=N (N > 0) so that the run writes checkpoints")
    try:
        with open(path, "rb") as handle:
            checkpoint = pickle.load(handle)
    except Exception as error:  # noqa: BLE001 - any unpickling failure means the same thing to the user
        raise CheckpointError(f"{path}: not a readable tambridge checkpoint ({type(error).__name__}: {error}); "
                              f"delete it and run without --resume") from error
    if not isinstance(checkpoint, Checkpoint):
        raise CheckpointError(f"{path}: not a tambridge checkpoint; delete it and run without --resume")
    if checkpoint.version != CHECKPOINT_VERSION:
        raise CheckpointError(f"{path}: checkpoint version {checkpoint.version}, this tambridge reads version "
                              f"{CHECKPOINT_VERSION}; run again without --resume")
    return checkpoint


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
        raise CheckpointError(f"{path}: the checkpoint was written with another config ({shown}"
                              f"{', ...' if len(differing) > 5 else ''}); resume with the same options "
                              f"(see config.yaml beside it) or run without --resume")
    saved_sequence = checkpoint.sequence
    if saved_sequence["frames"] != sequence["frames"] or saved_sequence["timestamps_sha1"] != sequence["timestamps_sha1"] \
            or saved_sequence["camera"] != sequence["camera"]:
        raise CheckpointError(f"{path}: the checkpoint is of another sequence ({saved_sequence['folder']}, "
                              f"{saved_sequence['frames']} frames), not of {sequence['folder']} ({sequence['frames']} "
                              f"frames); resume with the same sequence or run without --resume")
    if checkpoint.next_frame > sequence["frames"]:
        raise CheckpointError(f"{path}: the checkpoint is at frame {checkpoint.next_frame} of a "
                              f"{sequence['frames']}-frame sequence; run without --resume")


class KeyframeCheckpoints:
    """Writes a checkpoint after every ``every_keyframes``-th keyframe of a run (never when it is 0).

    ``snapshot(next_frame)`` builds the :class:`Checkpoint` when one is due.
    """

    def __init__(self, path: Path, every_keyframes: int, snapshot: Callable[[int], Checkpoint],
                 keyframes_so_far: int = 0) -> None:
        if every_keyframes < 0:
            raise CheckpointError(f"checkpoint.every_keyframes={every_keyframes}: expected 0 (off) or a positive count")
        self.path = Path(path)
        self.every_keyframes = every_keyframes
        self.snapshot = snapshot
        self.keyframes = keyframes_so_far
        self.written = 0

    def after_keyframe(self, next_frame: int) -> None:
        """Call after each keyframe is tracked and mapped; ``next_frame`` is the index of the frame that comes next."""
        self.keyframes += 1
        if self.every_keyframes and self.keyframes % self.every_keyframes == 0:
            size = save_checkpoint(self.path, self.snapshot(next_frame))
            self.written += 1
            logger.info("checkpoint at frame %d (%d keyframes): %s, %.1f MB", next_frame, self.keyframes, self.path,
                        size / 1e6)
