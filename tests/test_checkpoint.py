"""Checkpoints and ``reconstruct --resume``: a run killed with SIGKILL and resumed ends where an uninterrupted run does."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli import main
from pipelines.reconstruct import reconstruct
from tambridge.checkpoint import (
    Checkpoint,
    CheckpointError,
    check_resumable,
    checkpoint_path,
    load_checkpoint,
    save_checkpoint,
    sequence_fingerprint,
)
from tambridge.config import load_config, to_dict
from tambridge.evaluation.trajectory import evaluate_trajectory
from tambridge.frontend.open3d.frontend import Open3dFrontend
from tambridge.frontend.open3d.odometry import FrameToFrameOdometry
from tambridge.frontend.orb.frontend import OrbFrontend
from tambridge.io.tum import open_sequence

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
    child.send_signal(signal.SIGKILL)
    child.wait()


@pytest.mark.slow
def test_killed_run_resumes_to_the_uninterrupted_result(synthetic_sequence_dir, tmp_path):
    killed_dir, full_dir = tmp_path / "killed", tmp_path / "full"
    command = [sys.executable, str(ROOT / "cli.py"), "reconstruct", str(synthetic_sequence_dir), "-o", str(killed_dir),
               "--quiet", *_set_options(RUN_OPTIONS + (f"checkpoint.every_keyframes={CHECKPOINT_EVERY}",))]
    child = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                             env=dict(os.environ, PYTHONPATH=str(ROOT)))
    # The uninterrupted run (no checkpoints: writing them must not change the result) runs here meanwhile.
    killer = threading.Thread(target=_kill_at_first_checkpoint, args=(child, checkpoint_path(killed_dir), 300.0))
    killer.start()
    full = reconstruct(synthetic_sequence_dir, full_dir, load_config(None, RUN_OPTIONS), progress=False)
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
    np.testing.assert_array_equal(resumed[:, 0], uninterrupted[:, 0])
    assert np.abs(resumed[:, 1:4] - uninterrupted[:, 1:4]).max() < 1e-3  # metres
    metrics = json.loads((killed_dir / "metrics.json").read_text())
    assert metrics["keyframes"] == full.metrics["keyframes"]
    assert metrics["frames"] == sequence_length
    psnr = metrics["rendering"]["novel_views"]["psnr_db"]
    assert abs(psnr - full.metrics["rendering"]["novel_views"]["psnr_db"]) < 0.5
    assert (killed_dir / "splats.ply").is_file()
    # The finished run leaves nothing to resume; its log holds the killed part and the resumption.
    assert not checkpoint_path(killed_dir).exists()
    log = (killed_dir / "run.log").read_text()
    assert f"checkpoint at frame {written.next_frame}" in log and "resuming from" in log


def _checkpoint(config: dict, fingerprint: dict, next_frame: int = 5) -> Checkpoint:
    return Checkpoint(next_frame, config, fingerprint, frontend={}, mapping=None, run={})


def test_resume_refuses_another_config_or_sequence(synthetic_sequence_dir, tmp_path):
    sequence = open_sequence(synthetic_sequence_dir)
    fingerprint = sequence_fingerprint(sequence.folder, sequence.timestamps_s, sequence.sensor)
    config = to_dict(load_config(None, ["checkpoint.every_keyframes=2"]))
    path = tmp_path / "checkpoint.pkl"
    # How often a run checkpoints may change; everything else must match.
    check_resumable(path, _checkpoint(config, fingerprint), to_dict(load_config(None, ["checkpoint.every_keyframes=7"])),
                    fingerprint)
    with pytest.raises(CheckpointError, match=r"checkpoint\.pkl: .*another config \(mapper\.iterations: 30 in the checkpoint, 5 now"):
        check_resumable(path, _checkpoint(config, fingerprint), to_dict(load_config(None, ["mapper.iterations=5"])),
                        fingerprint)
    shorter = open_sequence(synthetic_sequence_dir, max_frames=20)
    with pytest.raises(CheckpointError, match="another sequence"):
        check_resumable(path, _checkpoint(config, fingerprint), config,
                        sequence_fingerprint(shorter.folder, shorter.timestamps_s, shorter.sensor))
    with pytest.raises(CheckpointError, match="at frame 99 of a 30-frame"):
        check_resumable(path, _checkpoint(config, fingerprint, next_frame=99), config, fingerprint)


def test_missing_corrupt_or_foreign_checkpoints_give_clear_errors(tmp_path):
    path = tmp_path / "checkpoint" / "checkpoint.pkl"
    with pytest.raises(CheckpointError, match=r"checkpoint\.pkl: no checkpoint to resume from.*every_keyframes"):
        load_checkpoint(path)
    path.parent.mkdir()
    path.write_bytes(b"\x80\x05not a pickle")
    with pytest.raises(CheckpointError, match=r"checkpoint\.pkl: not a readable tambridge checkpoint"):
        load_checkpoint(path)
    old = _checkpoint({}, {})
    old.version = 0
    save_checkpoint(path, old)
    with pytest.raises(CheckpointError, match="version 0"):
        load_checkpoint(path)
    assert [p.name for p in path.parent.iterdir()] == ["checkpoint.pkl"]  # atomic: no temp file left


def test_cli_resume_without_checkpoint_names_the_file_and_keeps_results(synthetic_sequence_dir, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "metrics.json").write_text("{}")  # a finished run's results
    result = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", "--resume",
                                       "--set", "mapper.enabled=false"])
    assert result.exit_code == 2
    assert "checkpoint.pkl: no checkpoint to resume from" in result.output
    assert (out / "metrics.json").read_text() == "{}"


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
    path = tmp_path / "checkpoint.pkl"
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
    path = tmp_path / "checkpoint.pkl"
    save_checkpoint(path, Checkpoint(8, {}, {}, state, None, {}))
    first.finish()
    second = OrbFrontend(sequence.camera, config)
    second.load_state_dict(load_checkpoint(path).frontend)
    keyframes_before = len(second.map.keyframes)
    # Shared objects stay shared: the reference keyframe is the map's own.
    assert any(second._reference is keyframe for keyframe in second.map.keyframes)
    for index in range(8, len(sequence)):
        second.track(sequence[index])
    result = second.finish()
    assert len(result.trajectory.timestamps_s) == len(sequence)
    assert len(result.keyframe_trajectory.timestamps_s) >= keyframes_before
    errors = evaluate_trajectory(result.trajectory, sequence.ground_truth)
    # As an uninterrupted run of these frames with the mapping thread (whose timing varies the result a little).
    assert errors.ate_rmse_m < 0.05
