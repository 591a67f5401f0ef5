"""Checkpoints and ``reconstruct --resume``: a run killed with SIGKILL and resumed ends where an uninterrupted run does."""

from __future__ import annotations

import builtins
import collections
import hashlib
import json
import math
import os
import pickle
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from cli import main
from pipelines.reconstruct import reconstruct
from tambridge.bridge.view_selection import Selection
import tambridge.checkpoint as checkpoint_module
from tambridge.checkpoint import (
    CHECKPOINT_VERSION,
    START_OVER,
    Checkpoint,
    CheckpointError,
    KeyframeCheckpoints,
    check_resumable,
    checkpoint_path,
    load_checkpoint,
    save_checkpoint,
    sequence_fingerprint,
    state_types,
)
from tambridge.config import config_for_camera, load_config, to_dict
from tambridge.evaluation.metrics import read_metrics
from tambridge.evaluation.trajectory import evaluate_trajectory
from tambridge.frontend.open3d.frontend import Open3dFrontend
from tambridge.frontend.open3d.odometry import FrameToFrameOdometry
from tambridge.frontend.orb.frontend import OrbFrontend
from tambridge.frontend.orb.loop_closing import LoopConsistency
from tambridge.frontend.pose_graph import PoseEdge
from tambridge.io.tum import open_sequence
from tambridge.state import decode_state, encode_state

ROOT = Path(__file__).resolve().parents[1]
# Inline ORB mapping (deterministic), a light mapper, no mesh: the run is about the state, not the quality.
RUN_OPTIONS = ("frontend.orb.mapping_thread=false", "mesh.enabled=false", "mapper.iterations=6", "bridge.iterations=5",
               "mapper.final_iterations_per_view=1")
CHECKPOINT_EVERY = 3


def _set_options(options) -> list[str]:
    return [argument for option in options for argument in ("--set", option)]


def _kill_at_first_checkpoint(child: subprocess.Popen, checkpoint: Path, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not checkpoint.exists() and child.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    # The run logs a checkpoint just after its file appears: let the line reach run.log before the kill.
    log = checkpoint.parent.parent / "run.log"
    while "checkpoint at frame" not in log.read_text() and child.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    child.send_signal(signal.SIGKILL)
    child.wait()


@pytest.mark.slow
def test_killed_run_resumes_to_the_uninterrupted_result(synthetic_sequence_dir, tmp_path):
    killed_dir, full_dir = tmp_path / "killed", tmp_path / "full"
    command = [sys.executable, str(ROOT / "cli.py"), "reconstruct", str(synthetic_sequence_dir), "-o", str(killed_dir),
               "--quiet", *_set_options(RUN_OPTIONS + (f"checkpoint.every_keyframes={CHECKPOINT_EVERY}",
                                                        "checkpoint.min_interval_s=0"))]
    child = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                             env=dict(os.environ, PYTHONPATH=str(ROOT)))
    # The uninterrupted run (no checkpoints: writing them must not change the result) runs here meanwhile.
    killer = threading.Thread(target=_kill_at_first_checkpoint, args=(child, checkpoint_path(killed_dir), 300.0))
    killer.start()
    full = reconstruct(synthetic_sequence_dir, full_dir, load_config(None, RUN_OPTIONS + ("checkpoint.every_keyframes=0",)),
                       progress=False)
    killer.join()

    assert child.returncode == -signal.SIGKILL, "the run finished before it could be killed"
    written = load_checkpoint(checkpoint_path(killed_dir))
    sequence_length = len(open_sequence(synthetic_sequence_dir))
    assert 0 < written.next_frame < sequence_length
    # Killed while tracking: no result file exists, whole or partial, under its final name.
    for name in ("trajectory.txt", "keyframes.txt", "splats.ply", "metrics.json"):
        assert not (killed_dir / name).exists(), name
    assert (killed_dir / "run.log").is_file()

    result = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(killed_dir), "--quiet",
                                       "--resume", *_set_options(RUN_OPTIONS + ("checkpoint.every_keyframes=3",))])
    assert result.exit_code == 0, result.output
    resumed = np.loadtxt(killed_dir / "trajectory.txt")
    uninterrupted = np.loadtxt(full_dir / "trajectory.txt")
    assert resumed.shape == uninterrupted.shape == (sequence_length, 8)
    # Inline mapping is deterministic, and a checkpoint holds every state the run carries across frames.
    np.testing.assert_array_equal(resumed, uninterrupted)
    metrics = read_metrics(killed_dir / "metrics.json")
    assert metrics.keyframes == full.metrics.keyframes
    assert metrics.frames == sequence_length
    psnr = metrics.map.rendering.novel_views.psnr_db
    assert abs(psnr - full.metrics.map.rendering.novel_views.psnr_db) < 0.5
    assert (killed_dir / "splats.ply").is_file()
    # The finished run leaves nothing to resume; its log holds the killed part and the resumption.
    assert not checkpoint_path(killed_dir).parent.exists()
    log = (killed_dir / "run.log").read_text()
    assert f"checkpoint at frame {written.next_frame}" in log and f"resuming at frame {written.next_frame}" in log


def _checkpoint(config: dict, fingerprint: dict, next_frame: int = 5) -> Checkpoint:
    return Checkpoint(next_frame, config, fingerprint, frontend={}, mapping=None, run={})


def test_resume_refuses_another_config_or_sequence(synthetic_sequence_dir, tmp_path):
    sequence = open_sequence(synthetic_sequence_dir)
    fingerprint = sequence_fingerprint(sequence)
    config = to_dict(load_config(None, ["checkpoint.every_keyframes=2"]))
    path = tmp_path / "checkpoint.npz"
    # How often a run checkpoints may change; everything else must match.
    check_resumable(path, _checkpoint(config, fingerprint), to_dict(load_config(None, ["checkpoint.every_keyframes=7"])),
                    fingerprint)
    with pytest.raises(CheckpointError, match=r"checkpoint\.npz: .*another config \(mapper\.iterations: 30 in the checkpoint, 5 now"):
        check_resumable(path, _checkpoint(config, fingerprint), to_dict(load_config(None, ["mapper.iterations=5"])),
                        fingerprint)
    # ORB's values are compared as the run records them, adapted to the image: the refusal says so.
    orb = config_for_camera(load_config(None, ["frontend.orb.n_features=1000"]), sequence.camera)
    with pytest.raises(CheckpointError, match=r"frontend\.orb\.n_features: 750 in the checkpoint, 500 now; ORB values as "
                                              r"adapted to the image size\); resume with the same options"):
        check_resumable(path, _checkpoint(to_dict(config_for_camera(load_config(None, []), sequence.camera)), fingerprint),
                        to_dict(orb), fingerprint)
    shorter = open_sequence(synthetic_sequence_dir, max_frames=20)
    with pytest.raises(CheckpointError, match="another sequence"):
        check_resumable(path, _checkpoint(config, fingerprint), config,
                        sequence_fingerprint(shorter))
    with pytest.raises(CheckpointError, match="at frame 99 of a 30-frame"):
        check_resumable(path, _checkpoint(config, fingerprint, next_frame=99), config, fingerprint)


def test_resume_refuses_another_folder_or_content_with_the_same_timestamps(synthetic_sequence_dir, tmp_path):
    sequence = open_sequence(synthetic_sequence_dir)
    saved = _checkpoint({}, sequence_fingerprint(sequence))
    path = tmp_path / "out" / "checkpoint" / "checkpoint.npz"

    def refuse(folder: Path, match: str) -> None:
        other = open_sequence(folder)
        np.testing.assert_array_equal(other.timestamps_s, sequence.timestamps_s)
        with pytest.raises(CheckpointError, match=match) as refused:
            check_resumable(path, saved, {}, sequence_fingerprint(other))
        assert "\n" not in str(refused.value) and str(refused.value).endswith(START_OVER)

    copy = tmp_path / "copy"
    shutil.copytree(synthetic_sequence_dir, copy)
    # A copy is another folder: the same frames, but not the run's input.
    refuse(copy, rf"another sequence \(folder {synthetic_sequence_dir.resolve()}, now {copy.resolve()}\)")
    # The same folder with other images at the same timestamps: the last frame's colour changed.
    saved = _checkpoint({}, sequence_fingerprint(open_sequence(copy)))
    last_rgb = max((copy / "rgb").iterdir())
    shutil.copyfile(min((copy / "rgb").iterdir()), last_rgb)
    refuse(copy, rf"another sequence \(other rgb/{last_rgb.name}\)")
    # ... or, with the images as they were, its ground truth (an index file) changed.
    shutil.copy2(synthetic_sequence_dir / "rgb" / last_rgb.name, last_rgb)  # its content and time as they were
    check_resumable(path, saved, {}, sequence_fingerprint(open_sequence(copy)))
    with open(copy / "groundtruth.txt", "a") as handle:
        handle.write("# edited\n")
    refuse(copy, r"another sequence \(other groundtruth\.txt\)")
    # A frame other than those hashed, edited: its size or modification time gives it away.
    saved = _checkpoint({}, sequence_fingerprint(open_sequence(copy)))
    shutil.copyfile(min((copy / "rgb").iterdir()), sorted((copy / "rgb").iterdir())[3])
    refuse(copy, r"another sequence \(images changed since \(their sizes or modification times\)\)")


def test_images_listed_by_absolute_paths_are_fingerprinted_by_them(synthetic_sequence_dir, tmp_path):
    """rgb.txt and depth.txt may name their images anywhere: by absolute paths, inside the folder or not."""
    listing = tmp_path / "listing"
    listing.mkdir()
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "camera.yaml"):
        lines = (synthetic_sequence_dir / name).read_text().splitlines()
        if name in ("rgb.txt", "depth.txt"):
            lines = [line if line.startswith("#") else
                     f"{line.split()[0]} {(synthetic_sequence_dir / line.split()[1]).resolve()}" for line in lines]
        (listing / name).write_text("\n".join(lines) + "\n")
    fingerprint = sequence_fingerprint(open_sequence(listing))
    first_rgb = open_sequence(synthetic_sequence_dir).rgb_paths[0].resolve()
    assert fingerprint["files_sha256"][str(first_rgb)] == hashlib.sha256(first_rgb.read_bytes()).hexdigest()
    check_resumable(tmp_path / "checkpoint.npz", _checkpoint({}, fingerprint), {},
                    sequence_fingerprint(open_sequence(listing)))


def _write_archive(path: Path, document, **arrays) -> None:
    """An .npz laid out as a checkpoint, with ``document`` (JSON-able, or raw bytes) as its document."""
    raw = document if isinstance(document, bytes) else json.dumps(document).encode()
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, document=np.frombuffer(raw, np.uint8), **arrays)


def test_missing_truncated_or_foreign_checkpoints_give_clear_errors(tmp_path):
    path = checkpoint_path(tmp_path / "out")
    with pytest.raises(CheckpointError, match=r"checkpoint\.npz: no checkpoint to resume from .*every_keyframes=0\); run without --resume"):
        load_checkpoint(path)
    unreadable = rf"checkpoint\.npz: not a readable tambridge checkpoint \(.*\); pass --overwrite instead of --resume to start over " \
                 r"\(or give another -o\)$"
    path.parent.mkdir(parents=True)
    path.write_bytes(b"\x80\x05not a checkpoint")
    with pytest.raises(CheckpointError, match=unreadable):
        load_checkpoint(path)
    written = _checkpoint({"mapper": {"iterations": 30}}, {"frames": 3}, next_frame=2)
    size = save_checkpoint(path, written)
    assert size == path.stat().st_size
    whole = path.read_bytes()
    for length in (len(whole) // 2, len(whole) - 1):
        path.write_bytes(whole[:length])
        with pytest.raises(CheckpointError, match=unreadable):
            load_checkpoint(path)
    # Some other program's .npz, and a checkpoint whose document is not JSON.
    np.savez(path, weights=np.zeros(3))
    with pytest.raises(CheckpointError, match=unreadable):
        load_checkpoint(path)
    _write_archive(path, b"{not json")
    with pytest.raises(CheckpointError, match=unreadable):
        load_checkpoint(path)
    old = _checkpoint({}, {})
    old.version = 0
    save_checkpoint(path, old)
    with pytest.raises(CheckpointError, match=rf"checkpoint\.npz: checkpoint version 0, this tambridge reads version "
                                              rf"{CHECKPOINT_VERSION}; pass --overwrite instead of --resume"):
        load_checkpoint(path)
    save_checkpoint(path, written)
    assert load_checkpoint(path) == written
    assert [p.name for p in path.parent.iterdir()] == ["checkpoint.npz"]  # atomic: no temp file left


class _Payload:
    """Unpickling this creates ``marker``: what a crafted pickle could do, made visible."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return builtins.open, (str(self.marker), "w")


def test_loading_never_runs_code_from_the_file(tmp_path):
    marker = tmp_path / "payload-ran"
    payload = pickle.dumps(_Payload(marker))
    pickle.loads(payload)  # the payload works: unpickled, it makes the marker
    assert marker.is_file()
    marker.unlink()
    out = tmp_path / "out"
    path = checkpoint_path(out)
    format_ = {"format": "tambridge checkpoint", "version": CHECKPOINT_VERSION}
    state = {"$dict": "dict", "items": []}
    attacks = {
        "a pickle under the checkpoint's name": lambda: path.write_bytes(payload),
        "an object array as the document": lambda: np.savez(path, document=np.array([_Payload(marker)], object)),
        "an object array the document names": lambda: _write_archive(path, {**format_, "checkpoint": {"$array": "a0"}},
                                                                     a0=np.array([_Payload(marker)], object)),
        "a type outside the registry": lambda: _write_archive(path, {**format_, "checkpoint": {
            "$object": "system", "fields": {"command": f"touch {marker}"}}}),
        "a dict type outside the registry": lambda: _write_archive(path, {**format_, "checkpoint": {
            "$dict": "defaultdict", "items": []}}),
        "an enum member that is not one": lambda: _write_archive(path, {**format_, "checkpoint": {
            "$enum": "Selection", "name": "__class__"}}),
        "fields that the type does not have": lambda: _write_archive(path, {**format_, "checkpoint": {
            "$object": "PoseEdge", "fields": {"__reduce__": state}}}),
    }
    for attack, write in attacks.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        write()
        with pytest.raises(CheckpointError) as refused:
            load_checkpoint(path)
        message = str(refused.value)
        assert message.startswith(f"{path}: not a readable tambridge checkpoint") and "\n" not in message, attack
        assert message.endswith(START_OVER), attack
        assert not marker.exists(), attack
    # The name older versions wrote their pickles under is never loaded, only named.
    path.unlink()
    (path.parent / "checkpoint.pkl").write_bytes(payload)
    with pytest.raises(CheckpointError, match=r"checkpoint\.pkl: a checkpoint of an older tambridge, a pickle, which "
                                              r"this one never loads .*pass --overwrite instead of --resume to start over"):
        load_checkpoint(path)
    assert not marker.exists()


def test_state_encoding_round_trips_types_and_shared_objects():
    types = state_types()
    edge = PoseEdge(0, 1, np.eye(4), np.diag(np.arange(1.0, 7.0)), uncertain=True)
    consistency = LoopConsistency(3)
    consistency.groups = [({1, 2}, 1)]
    pose = np.arange(16.0).reshape(4, 4)
    weights = torch.linspace(0, 1, 5, dtype=torch.float64).requires_grad_(True)
    looped = [1]
    looped.append(looped)
    state = {"edges": [edge, edge], 7: (1, 2.5, "x", None, True), "pose": pose, "same pose": pose,
             "float32": np.float32(1.25), "count": np.int64(-3), "flag": np.bool_(True), "nan": float("nan"),
             "counter": collections.Counter({"SELECTED": 2}), "ordered": collections.OrderedDict([(5, "b"), (2, "a")]),
             "weights": weights, "steps": torch.arange(4), "selection": Selection.UNCOVERED, "consistency": consistency,
             "frozen": frozenset({3}), "looped": looped, "empty": np.zeros((0, 3), np.uint8)}
    tree, arrays = encode_state(state, types)
    assert sorted(arrays) == ["a0", "a1", "a2", "a3", "a4", "a5"]  # each array once, though the pose is met twice
    back = decode_state(json.loads(json.dumps(tree)), arrays, types)
    assert list(back) == list(state)
    assert back["edges"][0] is back["edges"][1] and back["pose"] is back["same pose"]
    assert back["looped"][1] is back["looped"]
    assert back["edges"][0].source == 0 and back["edges"][0].uncertain is True
    np.testing.assert_array_equal(back["edges"][0].information, edge.information)
    assert back[7] == (1, 2.5, "x", None, True)
    assert type(back["float32"]) is np.float32 and back["float32"] == 1.25
    assert type(back["count"]) is np.int64 and back["count"] == -3 and type(back["flag"]) is np.bool_
    assert math.isnan(back["nan"])
    assert type(back["counter"]) is collections.Counter and back["counter"]["SELECTED"] == 2
    assert type(back["ordered"]) is collections.OrderedDict and list(back["ordered"].items()) == [(5, "b"), (2, "a")]
    assert back["weights"].requires_grad and back["weights"].dtype == torch.float64
    assert torch.equal(back["weights"].detach(), weights.detach()) and back["steps"].dtype == torch.int64
    assert back["selection"] is Selection.UNCOVERED
    assert type(back["consistency"]) is LoopConsistency and back["consistency"].groups == [({1, 2}, 1)]
    assert back["frozen"] == frozenset({3}) and back["empty"].shape == (0, 3) and back["empty"].dtype == np.uint8
    with pytest.raises(TypeError, match=r"cannot store a builtins\.object in a state \(at edges/1/information\)"):
        encode_state({"edges": [edge, PoseEdge(0, 1, np.eye(4), object())]}, types)


def test_cli_resume_of_a_finished_run_is_refused_and_keeps_results(synthetic_sequence_dir, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "metrics.json").write_text("{}")  # a finished run's results
    result = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", "--resume",
                                       "--set", "mapper.enabled=false"])
    assert result.exit_code == 2
    assert result.output.strip() == f"error: {out}: holds a finished run (metrics.json); nothing to resume: pass " \
                                    "--overwrite to run it again, or give another -o"
    assert (out / "metrics.json").read_text() == "{}"


def test_resume_of_a_run_killed_before_its_first_checkpoint_starts_over(synthetic_sequence_dir, tmp_path):
    out = tmp_path / "out"
    options = ["--set", "mapper.enabled=false", "--set", "mesh.enabled=false", "--max-frames", "8"]
    first = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", *options])
    assert first.exit_code == 0, first.output
    # What a SIGKILL before the first checkpoint leaves: the run's files, no metrics.json, no checkpoint.
    (out / "metrics.json").unlink()
    (out / "trajectory.txt").unlink()
    result = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", "--resume",
                                       *options])
    assert result.exit_code == 0, result.output
    assert len(np.loadtxt(out / "trajectory.txt")) == 8
    assert "no checkpoint (the run here stopped before its first one, or there is none): starting from the first frame" in \
        (out / "run.log").read_text()


@pytest.mark.parametrize("kind", ["open3d", "open3d_f2f"])
def test_open3d_frontends_continue_from_their_state(synthetic_sequence_dir, tmp_path, kind):
    sequence = open_sequence(synthetic_sequence_dir, max_frames=12)
    config = load_config(None, [])

    def make():
        if kind == "open3d":
            return Open3dFrontend(sequence.camera, config.frontend.open3d)
        return FrameToFrameOdometry(sequence.camera, config.frontend.open3d.max_depth_m, config.frontend.open3d.depth_diff_max_m)

    uninterrupted = make()
    for frame in sequence:
        uninterrupted.track(frame)
    first = make()
    for index in range(6):
        first.track(sequence[index])
    path = tmp_path / "checkpoint.npz"
    save_checkpoint(path, Checkpoint(6, {}, {}, first.state_dict(), None, {}))
    second = make()
    second.load_state_dict(load_checkpoint(path).frontend)
    for index in range(6, len(sequence)):
        second.track(sequence[index])
    expected, got = uninterrupted.finish(), second.finish()
    np.testing.assert_allclose(got.trajectory.world_from_camera, expected.trajectory.world_from_camera, atol=1e-9)
    assert got.keyframe_frame_indices == expected.keyframe_frame_indices


def test_orb_frontend_with_mapping_thread_checkpoints_between_frames(synthetic_sequence_dir, tmp_path):
    """With the background mapping thread a state dict waits for queued keyframes; the restored frontend goes on."""
    sequence = open_sequence(synthetic_sequence_dir, max_frames=16)
    config = load_config(None, ["frontend.orb.mapping_thread=true"]).frontend.orb
    first = OrbFrontend(sequence.camera, config)
    for index in range(8):
        first.track(sequence[index])
    state = first.state_dict()
    assert first._jobs.unfinished_tasks == 0
    path = tmp_path / "checkpoint.npz"
    save_checkpoint(path, Checkpoint(8, {}, {}, state, None, {}))
    first.finish()
    second = OrbFrontend(sequence.camera, config)
    second.load_state_dict(load_checkpoint(path).frontend)
    frames_of_keyframes_before = [keyframe.frame_index for keyframe in second.map.keyframes]
    # Shared objects stay shared: the reference keyframe is the map's own.
    assert any(second._reference is keyframe for keyframe in second.map.keyframes)
    for index in range(8, len(sequence)):
        second.track(sequence[index])
    result = second.finish()
    assert len(result.trajectory.timestamps_s) == len(sequence)
    # The restored keyframes stay, and the frames after the checkpoint add more (the loop turns 12 degrees a frame).
    frames_of_keyframes = list(result.keyframe_frame_indices.values())
    assert frames_of_keyframes[:len(frames_of_keyframes_before)] == frames_of_keyframes_before
    assert len(frames_of_keyframes) > len(frames_of_keyframes_before)
    errors = evaluate_trajectory(result.trajectory, sequence.ground_truth)
    # As an uninterrupted run of these frames with the mapping thread (whose timing varies the result a little).
    assert errors.ate_rmse_m < 0.015


def test_checkpoints_wait_long_enough_to_take_at_most_their_share_of_the_run(monkeypatch, tmp_path):
    """A long session's state, and so its checkpoint's time, grows: the next checkpoint waits at least the last one's
    seconds over the share, and never less than min_interval_s."""
    now = [0.0]
    write_seconds = iter([1.0, 3.0, 0.1, 0.1])

    def save(path, checkpoint):
        now[0] += next(write_seconds)
        return 1000

    monkeypatch.setattr(checkpoint_module, "save_checkpoint", save)
    times_s = (19.0, 20.0, 40.0, 41.0, 103.9, 104.0, 124.0, 124.2)
    written = []
    checkpoints = KeyframeCheckpoints(tmp_path / "checkpoint", 1, lambda next_frame: written.append(times_s[next_frame]),
                                      min_interval_s=20.0, max_time_share=0.05, clock=lambda: now[0])
    for frame, time_s in enumerate(times_s):
        now[0] = time_s
        checkpoints.after_frame(frame, is_keyframe=True)
    # 20 s after the start; then 20 s after a 1 s write (1 / 0.05); 60 s after a 3 s write; 20 s after a quick one.
    assert written == [20.0, 41.0, 104.0, 124.2]


def test_frames_without_keyframes_still_checkpoint_after_max_interval(monkeypatch, tmp_path):
    """A camera on ground its map covers makes no keyframes (the long preset): a checkpoint still comes after the first
    frame max_interval_s after the last one, keyframe or not; the keyframe count still counts only keyframes."""
    now = [0.0]
    monkeypatch.setattr(checkpoint_module, "save_checkpoint", lambda path, checkpoint: 1000)
    written = []
    checkpoints = KeyframeCheckpoints(tmp_path / "checkpoint", 2, lambda next_frame: written.append(next_frame),
                                      min_interval_s=20.0, max_interval_s=100.0, clock=lambda: now[0])
    # (seconds, keyframe?) for frames 0-7: two keyframes by 30 s, then none.
    for frame, (time_s, is_keyframe) in enumerate([(10.0, True), (30.0, True), (60.0, False), (99.0, False),
                                                   (129.0, False), (131.0, False), (200.0, False), (231.0, False)]):
        now[0] = time_s
        checkpoints.after_frame(frame + 1, is_keyframe)
    # After the second keyframe (30 s); after the first frame 100 s later (131 s); 100 s after that (231 s).
    assert written == [2, 6, 8] and checkpoints.keyframes == 2
    never = KeyframeCheckpoints(tmp_path / "checkpoint", 2, lambda next_frame: written.append(-1),
                                min_interval_s=20.0, max_interval_s=0.0, clock=lambda: now[0])
    for frame in range(5):
        now[0] += 1000.0
        never.after_frame(frame + 1, is_keyframe=False)
    assert -1 not in written
