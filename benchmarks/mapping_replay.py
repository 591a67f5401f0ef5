"""Mapping diagnostics: track once, then replay the same keyframe events into the mapping stage with other settings.

    python benchmarks/mapping_replay.py record                                  # ORB, 7-Scenes first 150 frames
    python benchmarks/mapping_replay.py replay --set bridge.enabled=false --per-frame
    python benchmarks/mapping_replay.py replay --set mapper.exposure_compensation=false --track 5,25,45
    python benchmarks/mapping_replay.py replay --ground-truth-poses --set bridge.enabled=false

``record`` runs the frontend over the sequence and stores every keyframe event with the frontend's keyframe poses
at that moment, and the final trajectory and keyframe poses (an ``.npz`` of plain arrays and one JSON document, read
with ``allow_pickle=False``, under benchmarks/results/runs/). ``replay`` feeds those events to
:class:`MappingStage` exactly as ``reconstruct`` does, so that mapper and bridge settings are compared on the same
keyframes and poses (a live run's keyframes depend on timing: the ORB frontend's keyframes wait while mapping is
busy; and the keyframes the mapper asks for where its map lacks coverage, ``mapper.coverage_unexplained``, are
not recorded: record runs the frontend alone). It prints one JSON line: novel-view and mapping-view PSNR/SSIM at
full resolution (as metrics.json), the mapping views' position error against ground truth (after an SE(3) alignment of the whole trajectory), seconds
per stage; ``--per-frame`` adds every novel view's PSNR, ``--track`` the PSNR of some frames after each view
(forgetting shows there), ``--results NAME`` also stores the row under NAME in
benchmarks/results/mapping_replay.json, ``--ground-truth-poses`` maps at the ground-truth poses (the bridge's map points are
moved by the same alignment, so pair it with bridge.enabled=false unless the frontend is accurate). On 7-Scenes the ground truth is KinectFusion's depth-camera trajectory and colour is
not registered to depth: mapping at those poses renders worse than at the ORB poses.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import datetime
import io
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe_machine  # noqa: E402
from tambridge.evaluation.mapping import evaluation_frames, score_views  # noqa: E402
from tambridge.mapping.stage import MappingStage  # noqa: E402
from tambridge.config import load_config  # noqa: E402
from tambridge.files import atomic_write_bytes, atomic_write_text  # noqa: E402
from tambridge.frontend.contract import KeyframeEvent  # noqa: E402
from tambridge.frontend.factory import make_frontend  # noqa: E402
from tambridge.geometry import nearest_rotation, transform_points  # noqa: E402
from tambridge.io.tum import RgbdSequence, open_sequence  # noqa: E402
from tambridge.runlog import RunLog  # noqa: E402
from tambridge.trajectory import Trajectory  # noqa: E402

RUNS = ROOT / "benchmarks" / "results" / "runs"
RESULTS = ROOT / "benchmarks" / "results" / "mapping_replay.json"


def umeyama_se3(source_m: np.ndarray, target_m: np.ndarray) -> np.ndarray:
    """4x4 rigid ``target_from_source`` minimising the squared distances of (N, 3) point pairs (Umeyama 1991, no scale)."""
    source_mean, target_mean = source_m.mean(0), target_m.mean(0)
    covariance = (target_m - target_mean).T @ (source_m - source_mean) / len(source_m)
    target_from_source = np.eye(4)
    target_from_source[:3, :3] = nearest_rotation(covariance)
    target_from_source[:3, 3] = target_mean - target_from_source[:3, :3] @ source_mean
    return target_from_source


def ground_truth_per_frame(sequence: RgbdSequence) -> np.ndarray:
    """(N, 4, 4) ground-truth ``world_from_camera`` of every frame (nearest timestamp)."""
    return sequence.ground_truth.nearest(sequence.timestamps_s).world_from_camera


def record(sequence_dir: Path, max_frames: int, cache: Path, overrides: list[str]) -> None:
    config = load_config(None, overrides)
    sequence = open_sequence(sequence_dir, max_frames=max_frames or None)
    frontend = make_frontend(config.frontend, sequence.camera)
    events = []
    started = time.perf_counter()
    for frame in sequence:
        result = frontend.track(frame)
        if result.keyframe is not None:
            events.append((result.keyframe, {key: pose.copy() for key, pose in frontend.keyframe_poses().items()}))
    final = frontend.finish()
    print(f"tracked {len(sequence)} frames in {time.perf_counter() - started:.1f} s, {len(events)} keyframes")
    write_events(cache, {"sequence_dir": str(sequence_dir), "max_frames": max_frames}, events, final)


ARRAY_FIELDS = [field.name for field in dataclasses.fields(KeyframeEvent) if field.type in ("np.ndarray", np.ndarray)]


def write_events(cache: Path, document: dict, events: list, final) -> None:
    """``cache`` (.npz): each event's arrays and keyframe poses, the final trajectory and keyframe poses, and
    ``document`` with the events' scalar fields as JSON; plain arrays only."""
    arrays = {"trajectory_timestamps_s": final.trajectory.timestamps_s,
              "trajectory_world_from_camera": final.trajectory.world_from_camera,
              "final_keyframe_ids": np.array(sorted(final.keyframe_poses), np.int64),
              "final_keyframe_poses": np.array([final.keyframe_poses[key] for key in sorted(final.keyframe_poses)])}
    scalars = []
    for number, (event, keyframe_poses) in enumerate(events):
        fields = dataclasses.asdict(event)
        arrays.update({f"event{number}_{name}": np.asarray(fields.pop(name)) for name in ARRAY_FIELDS})
        arrays[f"event{number}_keyframe_ids"] = np.array(sorted(keyframe_poses), np.int64)
        arrays[f"event{number}_keyframe_poses"] = np.array([keyframe_poses[key] for key in sorted(keyframe_poses)])
        scalars.append(fields)
    document = {**document, "events": scalars,
                "keyframe_frame_indices": {str(key): index for key, index in final.keyframe_frame_indices.items()}}
    arrays["document"] = np.frombuffer(json.dumps(document).encode(), np.uint8)
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    cache.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(cache, buffer.getvalue())


def read_events(cache: Path) -> tuple[dict, list, Trajectory, dict[int, np.ndarray]]:
    """``(document, [(event, keyframe poses)], final trajectory, final keyframe poses)`` of :func:`write_events`."""
    with np.load(cache, allow_pickle=False) as data:
        document = json.loads(data["document"].tobytes().decode())
        events = []
        for number, fields in enumerate(document["events"]):
            event = KeyframeEvent(**fields, **{name: data[f"event{number}_{name}"] for name in ARRAY_FIELDS})
            events.append((event, dict(zip(data[f"event{number}_keyframe_ids"].tolist(), data[f"event{number}_keyframe_poses"]))))
        trajectory = Trajectory(data["trajectory_timestamps_s"], data["trajectory_world_from_camera"])
        final_poses = dict(zip(data["final_keyframe_ids"].tolist(), data["final_keyframe_poses"]))
    return document, events, trajectory, final_poses


def replay(cache: Path, overrides: list[str], preset: Path | None, ground_truth_poses: bool, per_frame: bool,
           tracked_frames: list[int]) -> tuple[dict, dict]:
    """Replay ``cache``'s keyframe events into a mapping stage built from ``preset`` and ``overrides``; prints and
    returns the row, with the cache's document (its recorded sequence)."""
    document, events, estimated, final_keyframe_poses = read_events(cache)
    config = load_config(preset, overrides)
    sequence = open_sequence(Path(document["sequence_dir"]), max_frames=document["max_frames"] or None)
    truth = ground_truth_per_frame(sequence)
    estimate = estimated.world_from_camera
    truth_from_estimate = umeyama_se3(estimate[:, :3, 3], truth[:, :3, 3])
    keyframe_frames = {int(key): index for key, index in document["keyframe_frame_indices"].items()}
    frame_poses = truth if ground_truth_poses else estimate
    trajectory = Trajectory(estimated.timestamps_s, frame_poses)
    run_log = RunLog(cache.with_suffix(".replay.log"))
    stage = MappingStage(sequence, config.mapper, config.bridge, run_log, seed=config.seed)
    tracked = []
    started = time.perf_counter()
    for event, keyframe_poses in events:
        if ground_truth_poses:
            event = copy.copy(event)
            event.world_from_camera = truth[event.frame_index]
            event.points_world_m = transform_points(truth_from_estimate, np.asarray(event.points_world_m).reshape(-1, 3))
            keyframe_poses = {key: truth[keyframe_frames[key]] for key in keyframe_poses}
        stage.on_keyframe(event, sequence[event.frame_index], keyframe_poses)
        if tracked_frames:
            scores = score_views(stage, stage.rendering_poses(trajectory), tracked_frames)
            tracked.append((event.frame_index, [round(value, 2) for value in scores.psnr_db]))
    final_poses = {key: truth[keyframe_frames[key]] if ground_truth_poses else pose for key, pose in final_keyframe_poses.items()}
    stage.finish(final_poses)
    mapping_s = time.perf_counter() - started
    run_log.close()
    poses = stage.rendering_poses(trajectory)
    view_frames = sorted(view.frame_index for view in stage.views)
    novel_frames = evaluation_frames(len(sequence), config.evaluation.novel_view_every, set(view_frames))
    novel, views = score_views(stage, poses, novel_frames), score_views(stage, poses, view_frames)
    aligned = poses if ground_truth_poses else truth_from_estimate @ poses
    view_errors_m = [np.linalg.norm(aligned[index][:3, 3] - truth[index][:3, 3]) for index in view_frames]
    row = {"overrides": overrides, "ground_truth_poses": ground_truth_poses,
           "novel_psnr_db": float(np.mean(novel.psnr_db)), "novel_ssim": float(np.mean(novel.ssim)),
           "views_psnr_db": float(np.mean(views.psnr_db)), "views": len(view_frames), "gaussians": len(stage.map),
           "views_position_rmse_cm": float(np.sqrt(np.mean(np.square(view_errors_m))) * 100),
           "mapping_seconds": mapping_s, "seconds_per_stage": dict(run_log.stage_seconds)}
    if per_frame:
        row["novel_psnr_per_frame"] = [[index, round(value, 2)] for index, value in zip(novel.frame_indices, novel.psnr_db)]
    if tracked:
        row["tracked_psnr_after_each_view"] = tracked
    print(json.dumps(row))
    return document, row


def store_result(name: str, row: dict, document: dict) -> None:
    """Merge ``row`` into :data:`RESULTS` under ``name``, with the date, machine, command and the recorded sequence
    of ``document`` (the cache's, :func:`read_events`)."""
    results = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
    results[name] = {"date": datetime.datetime.now().isoformat(timespec="seconds"),
                     "machine": describe_machine(),
                     "command": "python benchmarks/mapping_replay.py " + " ".join(sys.argv[1:]),
                     "sequence": document["sequence_dir"], "max_frames": document["max_frames"], **row}
    atomic_write_text(RESULTS, json.dumps(results, indent=1) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("command", choices=("record", "replay"))
    parser.add_argument("--sequence", type=Path, default=ROOT.parent / "shared" / "data" / "7scenes_redkitchen_0-699")
    parser.add_argument("--max-frames", type=int, default=150)
    parser.add_argument("--cache", type=Path, default=RUNS / "mapping_replay_events.npz")
    parser.add_argument("--config", type=Path, help="a preset YAML for replay (default: the dataclass defaults)")
    parser.add_argument("--set", action="append", default=[], help="section.key=value, as reconstruct's --set")
    parser.add_argument("--ground-truth-poses", action="store_true")
    parser.add_argument("--per-frame", action="store_true")
    parser.add_argument("--track", default="", help="comma-separated frames scored after every view")
    parser.add_argument("--results", metavar="NAME", help="replay: store the row under NAME in " + str(RESULTS.relative_to(ROOT)))
    arguments = parser.parse_args()
    if arguments.command == "record":
        record(arguments.sequence, arguments.max_frames, arguments.cache, arguments.set)
    else:
        tracked = [int(value) for value in arguments.track.split(",") if value]
        document, row = replay(arguments.cache, arguments.set, arguments.config, arguments.ground_truth_poses,
                               arguments.per_frame, tracked)
        if arguments.results:
            store_result(arguments.results, row, document)


if __name__ == "__main__":
    main()
