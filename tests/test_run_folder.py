"""A user's results are safe whatever they type: inputs are checked before the output folder is touched, a finished
run is kept unless --overwrite, a folder has one run at a time, a stopped run can resume, and a run whose ground
truth cannot be compared still writes its results."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from cli import main
from pipelines.reconstruct import reconstruct
from tambridge.checkpoint import checkpoint_path
from tambridge.config import load_config
from tambridge.evaluation.metrics import read_metrics
from tambridge.evaluation.report import report_from_run
from tambridge.run_folder import LOCK_NAME, MANIFEST_NAME, OutputFolderError, RunFolder, Start, read_manifest
from tambridge.trajectory import read_tum_trajectory

ROOT = Path(__file__).resolve().parent.parent
FAST = ("frontend.orb.mapping_thread=false", "mesh.enabled=false", "mapper.iterations=4", "bridge.iterations=3",
        "mapper.final_iterations_per_view=1", "input.max_frames=12")


def _set(options) -> list[str]:
    return [argument for option in options for argument in ("--set", option)]


def _run(arguments: list[str]):
    return CliRunner().invoke(main, arguments)


@pytest.fixture(scope="module")
def finished_run(synthetic_sequence_dir, tmp_path_factory) -> Path:
    """A finished 12-frame run, with a file of the user's beside its results."""
    out = tmp_path_factory.mktemp("finished") / "out"
    result = _run(["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", *_set(FAST)])
    assert result.exit_code == 0, result.output
    return out


def _snapshot(folder: Path) -> dict[str, int]:
    return {str(path.relative_to(folder)): path.stat().st_mtime_ns for path in folder.rglob("*") if path.is_file()}


def test_a_finished_run_lists_every_file_it_wrote(finished_run):
    listed = set(read_manifest(finished_run))
    written = {name for name in _snapshot(finished_run) if name != MANIFEST_NAME}
    assert written <= listed
    assert {"config.yaml", "run.log", "trajectory.txt", "splats.ply", "metrics.json", "report/index.html"} <= written
    assert not (finished_run / LOCK_NAME).exists()


@pytest.mark.parametrize("mistake", ["typo in the sequence", "bad config value", "bad camera file"])
def test_a_mistaken_command_leaves_an_earlier_run_untouched(finished_run, synthetic_sequence_dir, tmp_path, mistake):
    before = _snapshot(finished_run)
    sequence, options = str(synthetic_sequence_dir), list(_set(FAST))
    if mistake == "typo in the sequence":
        sequence += "_typo"
    elif mistake == "bad config value":
        options += ["--set", "mapper.resolution_scale=0"]
    else:
        (tmp_path / "camera.yaml").write_text("width: 160\nheight: 120\nfx: 100\nfy: 100\ncx: 80\ncy: 60\n")
        options += ["--camera", str(tmp_path / "camera.yaml")]
    result = _run(["reconstruct", sequence, "-o", str(finished_run), "--quiet", "--overwrite", *options])
    assert result.exit_code == 2 and len(result.output.strip().splitlines()) == 1, result.output
    assert _snapshot(finished_run) == before


def test_a_finished_run_is_refused_without_overwrite(finished_run, synthetic_sequence_dir):
    before = _snapshot(finished_run)
    result = _run(["reconstruct", str(synthetic_sequence_dir), "-o", str(finished_run), "--quiet", *_set(FAST)])
    assert result.exit_code == 2
    assert result.output.strip() == f"error: {finished_run}: holds a finished run (metrics.json); pass --overwrite to " \
                                    f"replace it, or give another -o"
    assert _snapshot(finished_run) == before


def test_overwrite_removes_exactly_what_the_earlier_run_wrote(synthetic_sequence_dir, tmp_path):
    out = tmp_path / "out"
    first = _run(["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", *_set(FAST)])
    assert first.exit_code == 0, first.output
    (out / "notes.txt").write_text("the user's own file")
    (out / "report" / "mine.png").write_bytes(b"not ours")
    # The second run writes no splats (mapper off): the first run's must not stay beside its results.
    second = _run(["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", "--overwrite", *_set(FAST),
                   "--set", "mapper.enabled=false"])
    assert second.exit_code == 0, second.output
    assert not (out / "splats.ply").exists() and not (out / "report" / "renders.png").exists()
    assert (out / "notes.txt").read_text() == "the user's own file" and (out / "report" / "mine.png").exists()
    assert read_metrics(out / "metrics.json").map is None


def test_export_mesh_output_is_listed_in_the_manifest(synthetic_sequence_dir, tmp_path):
    out = tmp_path / "out"
    options = [option for option in FAST if not option.startswith("mesh.")] + ["mapper.enabled=false"]
    assert _run(["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", *_set(options)]).exit_code == 0
    assert _run(["export-mesh", str(out), "--format", "obj"]).exit_code == 0
    assert "mesh.obj" in read_manifest(out)
    assert _run(["export-mesh", str(out), "--format", "obj"]).exit_code == 0  # its own file, written again
    # A file of the run itself is no target (splats.ply, a .ply too).
    (out / "splats.ply").write_bytes(b"the run's splats")
    refused = _run(["export-mesh", str(out), "--format", "ply", "-o", str(out / "splats.ply")])
    assert refused.exit_code == 2 and refused.output == (f"error: -o {(out / 'splats.ply').resolve()}: is a file of the run "
                                                         f"in {out.resolve()} (its manifest.json lists it); name another file\n")
    assert (out / "splats.ply").read_bytes() == b"the run's splats"
    assert _run(["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", "--overwrite",
                 *_set(options)]).exit_code == 0
    assert not (out / "mesh.obj").exists()


@pytest.mark.parametrize("output, message", [
    ("", "Invalid value for '-o' / '--output': is empty (an unset shell variable?)"),
    ("FILE", "is a file; give a folder"),
    ("FOREIGN", "is not empty and holds no tambridge run (notes.txt)"),
])
def test_output_folders_that_are_not_a_runs_are_refused(synthetic_sequence_dir, tmp_path, output, message):
    (tmp_path / "FILE").write_text("x")
    (tmp_path / "FOREIGN").mkdir()
    (tmp_path / "FOREIGN" / "notes.txt").write_text("x")
    target = "" if output == "" else str(tmp_path / output)
    for start in ([], ["--resume"], ["--overwrite"]):
        result = _run(["reconstruct", str(synthetic_sequence_dir), "-o", target, "--quiet", *start, *_set(FAST)])
        assert result.exit_code == 2 and message in result.output, (start, result.output)
    assert (tmp_path / "FILE").read_text() == "x" and sorted(os.listdir(tmp_path / "FOREIGN")) == ["notes.txt"]


def test_a_second_run_into_a_locked_folder_is_refused_and_a_stale_lock_is_taken(tmp_path):
    out = tmp_path / "out"
    with RunFolder(out, Start.NEW, ["config.yaml"]):
        with pytest.raises(OutputFolderError, match=r"out: another run \(\S+ \d+\) is writing into it"):
            with RunFolder(out, Start.OVERWRITE, ["config.yaml"]):
                pass
        assert (out / LOCK_NAME).exists()
    assert not (out / LOCK_NAME).exists()
    # The lock of a killed run: its PID no longer runs.
    finished = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (out / LOCK_NAME).write_text(f"{os.uname().nodename} {finished.stdout.strip()}\n")
    with RunFolder(out, Start.OVERWRITE, ["config.yaml"]):
        assert (out / LOCK_NAME).read_text().split()[1] == str(os.getpid())


def test_a_tampered_manifest_cannot_remove_files_outside_the_folder(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (tmp_path / "precious.txt").write_text("keep")
    (out / MANIFEST_NAME).write_text(json.dumps({"format": "tambridge run manifest", "files": ["../precious.txt"]}))
    with pytest.raises(OutputFolderError, match=r"manifest\.json: lists '\.\./precious\.txt', outside its folder"):
        with RunFolder(out, Start.OVERWRITE, ["config.yaml"]):
            pass
    assert (tmp_path / "precious.txt").read_text() == "keep"


# The stop comes while tracking: the sharpening pass after it is not what is tested.
STOPPED_OPTIONS = [option for option in FAST if not option.startswith("input.")] + ["mapper.sharp_iterations_per_view=0"]


@pytest.fixture(scope="module")
def uninterrupted_trajectory(synthetic_sequence_dir, tmp_path_factory) -> np.ndarray:
    """trajectory.txt of the synthetic loop reconstructed with :data:`STOPPED_OPTIONS`, without a stop."""
    full = tmp_path_factory.mktemp("uninterrupted") / "full"
    reconstruct(synthetic_sequence_dir, full, load_config(None, STOPPED_OPTIONS), progress=False)
    return np.loadtxt(full / "trajectory.txt")


@pytest.mark.slow
@pytest.mark.parametrize("signum, status", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_writes_a_checkpoint_and_resume_ends_as_an_uninterrupted_run(synthetic_sequence_dir, tmp_path,
                                                                               uninterrupted_trajectory, signum, status):
    out = tmp_path / "stopped"
    command = [sys.executable, str(ROOT / "cli.py"), "reconstruct", str(synthetic_sequence_dir), "-o", str(out),
               "--quiet", *_set(STOPPED_OPTIONS)]
    child = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             env=dict(os.environ, PYTHONPATH=str(ROOT)))
    deadline = time.monotonic() + 300
    while child.poll() is None and time.monotonic() < deadline:
        # Stop it once it tracks: the first keyframes are mapped by then.
        if (out / "run.log").is_file() and "view 2 " in (out / "run.log").read_text():
            break
        time.sleep(0.05)
    child.send_signal(signum)
    stdout, stderr = child.communicate(timeout=300)
    assert child.returncode == status, stderr
    assert stderr.strip().startswith(f"error: stopped by {signal.Signals(signum).name} after frame ")
    assert len(stderr.strip().splitlines()) == 1 and "Aborted" not in stderr
    log = (out / "run.log").read_text()
    assert f"run stopped: RunStopped: stopped by {signal.Signals(signum).name}" in log
    assert checkpoint_path(out).is_file() and not (out / "metrics.json").exists()

    resumed = _run(["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", "--resume",
                    *_set(STOPPED_OPTIONS)])
    assert resumed.exit_code == 0, resumed.output
    np.testing.assert_array_equal(np.loadtxt(out / "trajectory.txt"), uninterrupted_trajectory)


@pytest.mark.slow
def test_a_stop_after_tracking_resumes_from_the_checkpoint_of_its_last_frame(synthetic_sequence_dir, tmp_path,
                                                                             uninterrupted_trajectory, monkeypatch):
    """A signal while the map is finished (global BA, the map's last rounds, mesh, evaluation) stops the run at once;
    the checkpoint written after the last frame is tracked lets --resume finish it as if uninterrupted."""
    import pipelines.reconstruct as pipeline
    from tambridge.checkpoint import load_checkpoint
    from tambridge.stop import RunStopped

    finish = pipeline.MappingStage.finish

    def stopped(*arguments, **options):
        raise RunStopped(signal.SIGINT, "stopped by SIGINT")  # as the handler raises it outside the tracking loop

    monkeypatch.setattr(pipeline.MappingStage, "finish", stopped)
    out = tmp_path / "stopped"
    result = _run(["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", *_set(STOPPED_OPTIONS)])
    frames = len(uninterrupted_trajectory)
    assert (result.exit_code, result.output) == (130, f"error: stopped by SIGINT; {out} keeps its latest checkpoint: the "
                                                      "same command with --resume continues there\n")
    assert load_checkpoint(checkpoint_path(out)).next_frame == frames and not (out / "metrics.json").exists()
    monkeypatch.setattr(pipeline.MappingStage, "finish", finish)
    resumed = _run(["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", "--resume",
                    *_set(STOPPED_OPTIONS)])
    assert resumed.exit_code == 0, resumed.output
    assert f"resuming at frame {frames} of {frames}" in (out / "run.log").read_text()
    np.testing.assert_array_equal(np.loadtxt(out / "trajectory.txt"), uninterrupted_trajectory)
    assert not checkpoint_path(out).parent.exists()

    # Without checkpoints the run says that nothing can be resumed.
    monkeypatch.setattr(pipeline.MappingStage, "finish", stopped)
    off = tmp_path / "off"
    result = _run(["reconstruct", str(synthetic_sequence_dir), "-o", str(off), "--quiet",
                   *_set([*STOPPED_OPTIONS, "input.max_frames=6", "checkpoint.every_keyframes=0"])])
    assert (result.exit_code, result.output) == (130, f"error: stopped by SIGINT; {off} holds the unfinished run, with no "
                                                      "checkpoint: run again to start over\n")

    # A first signal while the last frame's checkpoint is written is honoured once it is written, not lost.
    monkeypatch.setattr(pipeline.MappingStage, "finish", finish)
    write = pipeline.KeyframeCheckpoints.write_unless_written

    signals = []

    def signalled(self, next_frame):
        write(self, next_frame)
        if next_frame == 6 and not signals:  # once: a second signal stops a run at once
            signals.append(os.kill(os.getpid(), signal.SIGINT))

    monkeypatch.setattr(pipeline.KeyframeCheckpoints, "write_unless_written", signalled)
    late = tmp_path / "late"
    result = _run(["reconstruct", str(synthetic_sequence_dir), "-o", str(late), "--quiet",
                   *_set([*STOPPED_OPTIONS, "input.max_frames=6"])])
    assert (result.exit_code, result.output) == (130, "error: stopped by SIGINT after frame 6 of 6; checkpoint written: the "
                                                      "same command with --resume continues there\n")
    assert load_checkpoint(checkpoint_path(late)).next_frame == 6


def test_a_run_without_the_gaussian_map_writes_no_checkpoint_after_its_last_frame(synthetic_sequence_dir, tmp_path,
                                                                                  monkeypatch):
    """Without the Gaussian map only global BA, exports and evaluation follow the last frame, seconds of work: the
    run does not spend a checkpoint on them; with the map on it is still written (the test above resumes from it)."""
    import pipelines.reconstruct as pipeline

    written = []
    monkeypatch.setattr(pipeline.KeyframeCheckpoints, "write_unless_written",
                        lambda self, next_frame: written.append(next_frame))
    for mapper in (False, True):
        config = load_config(None, [*FAST, f"mapper.enabled={str(mapper).lower()}",
                                    "mapper.sharp_iterations_per_view=0", "input.max_frames=6"])
        reconstruct(synthetic_sequence_dir, tmp_path / str(mapper), config, progress=False)
        assert written == ([6] if mapper else [])


def test_ground_truth_on_another_clock_leaves_the_results_and_says_why(synthetic_sequence_dir, tmp_path):
    sequence = tmp_path / "seq"
    shutil.copytree(synthetic_sequence_dir, sequence)
    truth = read_tum_trajectory(sequence / "groundtruth.txt")
    lines = [" ".join(f"{value:.9f}" for value in [stamp + 1000.0, *row])
             for stamp, row in zip(truth.timestamps_s, np.loadtxt(sequence / "groundtruth.txt")[:, 1:])]
    (sequence / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    result = reconstruct(sequence, tmp_path / "out", load_config(None, FAST), progress=False)
    metrics = read_metrics(tmp_path / "out" / "metrics.json")
    assert metrics.trajectory is None and result.metrics.trajectory is None
    assert metrics.trajectory_unavailable.startswith("only 0 of 12 estimated poses lie within 0.02 s of a reference pose")
    assert (tmp_path / "out" / "trajectory.txt").is_file() and (tmp_path / "out" / "splats.ply").is_file()
    # `tambridge report` rebuilds it the same way: without ATE, saying why.
    (tmp_path / "out" / "report" / "index.html").unlink()
    assert "only 0 of 12 estimated poses" in report_from_run(tmp_path / "out").read_text()


def test_report_from_another_folder_finds_the_sequence(finished_run, synthetic_sequence_dir, tmp_path, monkeypatch):
    assert read_metrics(finished_run / "metrics.json").sequence == str(synthetic_sequence_dir.resolve())
    headings = re.findall(r"<h2>(.*?)</h2>", (finished_run / "report" / "index.html").read_text())
    monkeypatch.chdir(tmp_path)
    result = _run(["report", str(finished_run)])
    assert result.exit_code == 0, result.output
    rebuilt = (finished_run / "report" / "index.html").read_text()
    # Every section of the run's own report, the renders' figures included (kept from the run).
    assert "ATE" in rebuilt and re.findall(r"<h2>(.*?)</h2>", rebuilt) == headings
    assert {"Trajectory", "Renders", "As exported", "Gaussians"} <= set(headings)


def test_report_rebuilt_without_its_folder_has_the_viewer_again_and_says_what_is_gone(finished_run, tmp_path, caplog):
    """report/ deleted: the viewer is written again from splats.ply, from the frames' camera read as the run read it;
    the renders, which lived only during the run, are gone, and the rebuild says so."""
    from tambridge.export.web_viewer import RUN_VIEWER_FOLDER, read_viewer_view

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    camera = read_viewer_view(run / RUN_VIEWER_FOLDER)[0]
    shutil.rmtree(run / "report")
    index = report_from_run(run).read_text()
    assert 'src="viewer/index.html"' in index and read_viewer_view(run / RUN_VIEWER_FOLDER)[0] == camera
    assert f"{run / 'report' / 'renders.png'}: gone: the renders lived only during the run" in caplog.text


@pytest.mark.parametrize("frames", [1, 2])
def test_one_or_two_frame_sequences_end_cleanly(synthetic_sequence_dir, tmp_path, frames):
    options = [option for option in FAST if not option.startswith("input.")] + [f"input.max_frames={frames}"]
    result = _run(["reconstruct", str(synthetic_sequence_dir), "-o", str(tmp_path / "out"), "--quiet", *_set(options)])
    assert result.exit_code == 0, result.output
    metrics = read_metrics(tmp_path / "out" / "metrics.json")
    assert metrics.frames == frames and len(np.loadtxt(tmp_path / "out" / "trajectory.txt", ndmin=2)) == frames
    assert metrics.trajectory is None
    assert metrics.trajectory_unavailable == f"the estimate has {frames} poses; ATE needs at least 3 (an alignment is fitted to them)"


def test_an_output_folder_that_cannot_be_made_is_one_line(synthetic_sequence_dir, tmp_path):
    (tmp_path / "file").write_text("x")
    result = _run(["reconstruct", str(synthetic_sequence_dir), "-o", str(tmp_path / "file" / "out"), "--quiet",
                   *_set(FAST)])
    assert result.exit_code == 2, result.output
    assert result.output.strip() == (f"error: {tmp_path / 'file' / 'out'}: Not a directory; part of the path is a "
                                     "file, not a folder; give another path")


def test_a_sequence_where_no_frame_tracks_ends_with_an_error_not_an_identity_trajectory(tmp_path):
    folder = tmp_path / "textureless"
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    for index in range(6):
        cv2.imwrite(str(folder / f"rgb/{index}.png"), np.full((120, 160, 3), 128, np.uint8))
        cv2.imwrite(str(folder / f"depth/{index}.png"), np.full((120, 160), 10000, np.uint16))
    (folder / "rgb.txt").write_text("".join(f"{index / 30:.6f} rgb/{index}.png\n" for index in range(6)))
    (folder / "depth.txt").write_text("".join(f"{index / 30:.6f} depth/{index}.png\n" for index in range(6)))
    (folder / "camera.yaml").write_text("width: 160\nheight: 120\nfx: 130\nfy: 130\ncx: 79.5\ncy: 59.5\ndepth_scale: 5000\n")
    out = tmp_path / "out"
    result = _run(["reconstruct", str(folder), "-o", str(out), "--quiet", *_set(FAST)])
    assert result.exit_code == 2
    assert result.output.strip().endswith("none of the 5 frames after the first could be tracked (run.log says why for "
                                          "each); check that the images have texture and depth and that the camera "
                                          f"file fits them ({out} holds the unfinished run: the same command "
                                          "replaces it once that is fixed)")
    assert not (out / "trajectory.txt").exists() and not (out / "metrics.json").exists()
