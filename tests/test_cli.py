import http.server
import importlib.util
import io
import json
import tarfile
import threading
import zlib

import click
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from cli import main
from tambridge.evaluation.metrics import read_metrics
from tambridge.io.tum import open_sequence
from tambridge.trajectory import read_tum_trajectory


@pytest.mark.slow
def test_reconstruct_writes_outputs_and_a_real_ate(synthetic_sequence_dir, tmp_path):
    out = tmp_path / "out"
    # Tracking only: the test is about the run's files and its trajectory (the bridge leaves the poses by default).
    result = CliRunner().invoke(
        main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", "--set", "frontend.kind=open3d_f2f",
               "--set", "mapper.enabled=false", "--set", "mesh.enabled=false"]
    )
    assert result.exit_code == 0, result.output
    assert "ATE RMSE" in result.output
    metrics = read_metrics(out / "metrics.json")
    assert metrics.frames == 30 and metrics.colour_images_without_depth == 0
    assert metrics.keyframes_culled == 0  # only the ORB frontend culls keyframes
    # Frame-to-frame odometry drifts on the noise-free 160x120 loop (no loop closure): the error is centimetres,
    # never the zero of a trajectory copied from the ground truth.
    assert 0.028 < metrics.trajectory.ate_rmse_m < 0.048  # 1 cm either side of this deterministic run's
    trajectory = read_tum_trajectory(out / "trajectory.txt")
    assert len(trajectory) == 30
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["frontend"]["kind"] == "open3d_f2f"
    log = (out / "run.log").read_text()
    assert "finished" in log and "colour images of rgb.txt" not in log and "times the size of groundtruth.txt's" not in log


def test_the_run_summary_counts_lost_frames(capsys, tmp_path):
    from types import SimpleNamespace

    from cli import _print_run_summary
    from tests.test_report import _metrics

    for lost, said in ((0, "30 frames at 3.0 frames/s\n"),
                       (2, "30 frames at 3.0 frames/s, 2 lost (run.log names them)\n")):
        _print_run_summary(SimpleNamespace(metrics=_metrics(frames_lost=lost), output_dir=tmp_path))
        assert capsys.readouterr().out == f"{said}outputs: {tmp_path}\n"


def test_stride_and_max_frames_reach_the_run(synthetic_sequence_dir, tmp_path):
    out = tmp_path / "out"
    result = CliRunner().invoke(
        main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(out), "--quiet", "--stride", "2", "--max-frames", "5",
               "--set", "frontend.kind=open3d_f2f", "--set", "mapper.enabled=false", "--set", "mesh.enabled=false"]
    )  # the frames a run reads are decided before mapping: no map is needed to see which ones it took
    assert result.exit_code == 0, result.output
    trajectory = read_tum_trajectory(out / "trajectory.txt")
    np.testing.assert_allclose(trajectory.timestamps_s, np.arange(0, 10, 2) / 30.0, atol=1e-6)


def test_bad_input_exits_with_one_line_and_no_results(tmp_path):
    (tmp_path / "empty").mkdir()
    out = tmp_path / "out"
    result = CliRunner().invoke(main, ["reconstruct", str(tmp_path / "empty"), "-o", str(out), "--quiet"])
    assert result.exit_code == 2
    assert result.output.strip().startswith("error: ") and "not a sequence folder" in result.output
    assert len(result.output.strip().splitlines()) == 1
    # The input is checked before anything is written: not even the output folder is made.
    assert not out.exists()


def test_evaluate_prints_a_table_and_writes_a_plot(synthetic_sequence_dir, tmp_path):
    ground_truth = synthetic_sequence_dir / "groundtruth.txt"
    estimate = tmp_path / "estimate.txt"  # a copy: the same file as both is refused
    estimate.write_bytes(ground_truth.read_bytes())
    result = CliRunner().invoke(
        main, ["evaluate", str(estimate), str(ground_truth), "--plot", str(tmp_path / "p.png"), "--json", str(tmp_path / "m.json")]
    )
    assert result.exit_code == 0, result.output
    assert "ATE RMSE" in result.output and "0.000 cm" in result.output
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((tmp_path / "m.json").read_text())["ate_rmse_m"] < 1e-9


def test_evaluate_in_a_run_folder_lists_its_plot_so_overwrite_removes_it(synthetic_sequence_dir, tmp_path):
    from tambridge.run_folder import RunFolder, Start, read_manifest

    run = tmp_path / "run"
    with RunFolder(run, Start.NEW, ["trajectory.txt"]):
        (run / "trajectory.txt").write_bytes((synthetic_sequence_dir / "groundtruth.txt").read_bytes())
    result = CliRunner().invoke(main, ["evaluate", str(run / "trajectory.txt"), str(synthetic_sequence_dir / "groundtruth.txt"),
                                       "--json", str(run / "ate.json")])
    assert result.exit_code == 0, result.output
    assert read_manifest(run) == ["trajectory.txt", "trajectory.png", "ate.json"]
    with RunFolder(run, Start.OVERWRITE, ["trajectory.txt"]):
        assert sorted(path.name for path in run.iterdir()) == ["manifest.json", "run.lock"]


def test_reconstruct_refuses_a_bad_setting_in_one_line_before_writing(synthetic_sequence_dir, tmp_path):
    """What load_config refuses (tests/test_config.py) reaches the user as one line, before any output exists."""
    preset = tmp_path / "p.yaml"
    preset.write_text("mapper:\n  iterations: 7\n")
    for arguments, message in ((["--set", "mapper.iteration=3"], "error: unknown config key 'mapper.iteration'; known "
                                "keys here: enabled, "),
                               (["--config", str(preset), "--set", "mapper.iterations=many"],
                                "error: mapper.iterations: expected int"),
                               (["--config", str(tmp_path / "missing.yaml")],
                                f"error: {tmp_path / 'missing.yaml'}: config file not found; give a YAML file, or a "
                                "preset's name (default, fast, ")):
        result = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(tmp_path / "out"),
                                           *arguments])
        assert result.exit_code == 2 and result.output.startswith(message), result.output
        assert len(result.output.strip().splitlines()) == 1
        assert not (tmp_path / "out").exists()


def _serve(folder):
    handler = lambda *args, **kwargs: http.server.SimpleHTTPRequestHandler(*args, directory=str(folder), **kwargs)  # noqa: E731
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def test_download_fetches_and_unpacks_from_a_local_mirror(synthetic_sequence_dir, tmp_path):
    mirror = tmp_path / "mirror" / "freiburg1"
    mirror.mkdir(parents=True)
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        tar.add(synthetic_sequence_dir, arcname="rgbd_dataset_freiburg1_desk")
    (mirror / "rgbd_dataset_freiburg1_desk.tgz").write_bytes(buffer.getvalue())
    server = _serve(tmp_path / "mirror")
    try:
        base_url = f"http://127.0.0.1:{server.server_address[1]}"
        result = CliRunner().invoke(main, ["download", "fr1/desk", "--to", str(tmp_path / "data"), "--base-url", base_url])
        assert result.exit_code == 0, result.output
        folder = tmp_path / "data" / "rgbd_dataset_freiburg1_desk"
        assert (folder / "rgb.txt").read_text() == (synthetic_sequence_dir / "rgb.txt").read_text()
        assert len(list((folder / "depth").glob("*.png"))) == 30
        missing = CliRunner().invoke(main, ["download", "fr2/nothing", "--to", str(tmp_path / "data"), "--base-url", base_url])
        assert missing.exit_code == 2 and "download failed" in missing.output
        assert not (tmp_path / "data" / "rgbd_dataset_freiburg2_nothing").exists()
        # A failed download into a new folder leaves none behind.
        missing = CliRunner().invoke(main, ["download", "fr2/nothing", "--to", str(tmp_path / "new" / "data"),
                                            "--base-url", base_url])
        assert missing.exit_code == 2 and not (tmp_path / "new").exists()
        # A folder of the sequence's name that holds no sequence is the user's: refused before the download, kept.
        mine = tmp_path / "mine" / "rgbd_dataset_freiburg1_desk"
        mine.mkdir(parents=True)
        (mine / "notes.txt").write_text("precious")
        refused = CliRunner().invoke(main, ["download", "fr1/desk", "--to", str(tmp_path / "mine"), "--base-url", base_url])
        assert refused.output == (f"error: {mine}: exists and holds no sequence (no rgb.txt); move it away or give "
                                  "another --to\n")
        assert refused.exit_code == 2 and sorted(path.name for path in mine.iterdir()) == ["notes.txt"]
    finally:
        server.shutdown()
    bad_name = CliRunner().invoke(main, ["download", "desk", "--to", str(tmp_path / "data")])
    assert bad_name.exit_code == 2 and "expected a TUM sequence name" in bad_name.output


def _tgz(files: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        for name, data in files.items():
            member = tarfile.TarInfo(name)
            member.size = len(data)
            tar.addfile(member, io.BytesIO(data))
    return buffer.getvalue()


def test_a_bad_mirror_answer_is_one_line_that_says_what_it_is(tmp_path):
    """Cut short, not an archive, unsafe, or not a whole sequence: one line each, nothing left in --to."""
    mirror = tmp_path / "mirror" / "freiburg1"
    mirror.mkdir(parents=True)
    whole = _tgz({"rgbd_dataset_freiburg1_a/rgb.txt": b"1.0 rgb/1.png\n", "rgbd_dataset_freiburg1_a/depth.txt": b"",
                  "rgbd_dataset_freiburg1_a/rgb/1.png": b"x" * 50000, "rgbd_dataset_freiburg1_a/depth/1.png": b"y"})
    answers = {
        "cut": (whole[: len(whole) // 2], "archive is corrupt or truncated"),
        "page": (b"<html>Not here</html>", "not a .tgz archive (an error page?); check --base-url"),
        "unsafe": (_tgz({"rgbd_dataset_freiburg1_unsafe/rgb.txt": b"", "../escaped.txt": b"x"}), "the archive is unsafe ("),
        "partial": (_tgz({"rgbd_dataset_freiburg1_partial/rgb.txt": b""}),
                    "the archive's sequence lacks depth.txt, rgb, depth; not a TUM sequence"),
    }
    for name, (data, _) in answers.items():
        (mirror / f"rgbd_dataset_freiburg1_{name}.tgz").write_bytes(data)
    server = _serve(tmp_path / "mirror")
    try:
        base_url = f"http://127.0.0.1:{server.server_address[1]}"
        for name, (_, message) in answers.items():
            result = CliRunner().invoke(main, ["download", f"fr1/{name}", "--to", str(tmp_path / "data"), "--base-url",
                                               base_url])
            # (The output holds the test server's request log and the progress bar too.)
            errors = [line for line in result.output.splitlines() if line.startswith("error: ")]
            assert result.exit_code == 2 and len(errors) == 1, result.output
            assert errors[0].startswith(f"error: {base_url}/freiburg1/rgbd_dataset_freiburg1_{name}.tgz: {message}"), \
                result.output
    finally:
        server.shutdown()
    assert not (tmp_path / "data").exists() and not (tmp_path / "escaped.txt").exists()


def test_synth_refuses_a_size_it_could_not_hold_before_making_anything(tmp_path):
    result = CliRunner().invoke(main, ["synth", str(tmp_path / "huge"), "--size", "100000x100000", "--frames", "1"])
    assert result.exit_code == 2 and len(result.output.splitlines()) == 1, result.output
    assert "'100000x100000': images must be at most 4096x4096" in result.output and not (tmp_path / "huge").exists()


def test_a_stopped_synth_leaves_no_partial_sequence(tmp_path, monkeypatch):
    import tambridge.io.synthetic as synthetic

    def stopped_midway(folder, options):
        (folder / "rgb").mkdir(parents=True)
        (folder / "rgb" / "0.png").write_bytes(b"a frame")
        raise KeyboardInterrupt

    monkeypatch.setattr(synthetic, "write_synthetic_sequence", stopped_midway)
    for target in (tmp_path / "new", tmp_path / "empty"):
        (tmp_path / "empty").mkdir(exist_ok=True)
        result = CliRunner().invoke(main, ["synth", str(target), "--frames", "2"])
        assert (result.exit_code, result.output) == (130, "error: stopped by SIGINT\n")
    assert sorted(path.name for path in tmp_path.iterdir()) == ["empty"] and not any((tmp_path / "empty").iterdir())


def test_evaluate_and_compare_refuse_bad_output_paths_before_any_work(synthetic_sequence_dir, tmp_path):
    estimate, ground_truth = tmp_path / "estimate.txt", tmp_path / "truth.txt"
    for path in (estimate, ground_truth):
        path.write_bytes((synthetic_sequence_dir / "groundtruth.txt").read_bytes())
    (tmp_path / "a_file").write_text("x")
    inputs = {path: path.read_bytes() for path in (estimate, ground_truth)}
    for command, message in (
        (["evaluate", estimate, ground_truth, "--plot", estimate], f"--plot {estimate}: is an input of this command"),
        (["evaluate", estimate, ground_truth, "--json", ground_truth], f"--json {ground_truth}: is an input"),
        (["evaluate", estimate, ground_truth, "--plot", tmp_path / "p.png", "--json", tmp_path],
         f"--json {tmp_path}: is a folder"),
        (["evaluate", estimate, ground_truth, "--plot", tmp_path / "a_file" / "p.png"],
         f"--plot {tmp_path / 'a_file' / 'p.png'}: {tmp_path / 'a_file'} is a file, not a folder"),
        (["compare", estimate, "--gt", ground_truth, "--plot", ground_truth], f"--plot {ground_truth}: is an input"),
        (["evaluate", estimate, ground_truth, "--plot", tmp_path / "e.png", "--json", tmp_path / "e.png"],
         f"--json {tmp_path / 'e.png'}: is also the --plot file; name two different files"),
        (["compare", estimate, "--gt", ground_truth, "--plot", tmp_path / "c.png", "--json", tmp_path / "c.png"],
         f"--json {tmp_path / 'c.png'}: is also the --plot file"),
        (["evaluate", estimate, ground_truth, "--plot", tmp_path / "new" / ("p" * 300 + ".png")],
         f"--plot {tmp_path / 'new' / ('p' * 300 + '.png')}: its part {'p' * 24}... is 304 bytes"),
        (["compare", estimate, "--gt", ground_truth, "--plot", tmp_path / "c.pdf"],
         f"--plot {tmp_path / 'c.pdf'}: the plot is a PNG; name the file *.png"),
        (["evaluate", estimate, estimate], f"{estimate}: is both ESTIMATE and GROUND_TRUTH"),
    ):
        result = CliRunner().invoke(main, [str(argument) for argument in command])
        assert result.exit_code == 2 and result.output.startswith(f"error: {message}"), result.output
        assert len(result.output.splitlines()) == 1
    assert {path: path.read_bytes() for path in inputs} == inputs
    assert sorted(path.name for path in tmp_path.iterdir()) == ["a_file", "estimate.txt", "truth.txt"]
    result = CliRunner().invoke(main, ["evaluate", str(estimate), str(ground_truth), "--plot", str(tmp_path / "new" / "p.png")])
    assert result.exit_code == 0 and (tmp_path / "new" / "p.png").read_bytes().startswith(b"\x89PNG")


def test_evaluate_never_writes_over_a_runs_own_files(synthetic_sequence_dir, tmp_path):
    """A run folder's files (its manifest lists them) are the run's: --json RUN/metrics.json would end the run as one
    that export and report read; what evaluate itself added there it may write again."""
    from tambridge.run_folder import RunFolder, Start

    run = tmp_path / "run"
    with RunFolder(run, Start.NEW, ["metrics.json", "trajectory.txt", "report/trajectory.png"]):
        for name in ("metrics.json", "trajectory.txt"):
            (run / name).write_bytes((synthetic_sequence_dir / "groundtruth.txt").read_bytes())
    estimate, truth = run / "trajectory.txt", synthetic_sequence_dir / "groundtruth.txt"
    before = (run / "metrics.json").read_bytes()
    for option, name in (("--json", "metrics.json"), ("--json", "manifest.json"), ("--plot", "report/trajectory.png")):
        result = CliRunner().invoke(main, ["evaluate", str(estimate), str(truth), option, str(run / name)])
        assert result.exit_code == 2 and result.output == (f"error: {option} {(run / name).resolve()}: is a file of the run in "
                                                           f"{run.resolve()} (its manifest.json lists it); name another file\n")
    assert (run / "metrics.json").read_bytes() == before
    for _ in range(2):  # the default plot beside trajectory.txt, written again
        result = CliRunner().invoke(main, ["evaluate", str(estimate), str(truth), "--json", str(run / "ate.json")])
        assert result.exit_code == 0, result.output
    assert (run / "trajectory.png").is_file() and (run / "ate.json").is_file()


@pytest.mark.parametrize("arguments, message", [
    (["synth", "{tmp}/s", "--frames", "0"], "Invalid value for '--frames': 0 is not in the range x>=1. (see main synth --help)"),
    (["synth", "{tmp}/s", "--depth-noise", "-1"], "Invalid value for '--depth-noise'"),
    (["synth", "{tmp}/s", "--colour-focal-scale", "0"], "Invalid value for '--colour-focal-scale'"),
    (["synth", "{tmp}/s", "--size", "abc"], "Invalid value for --size: 'abc': expected WIDTHxHEIGHT, e.g. 160x120"),
    (["reconstruct", "{tmp}", "-o", "{tmp}/out", "--viewer", "rerun:{tmp}/bad.yaml/run.rrd"],
     "--viewer {tmp}/bad.yaml/run.rrd: {tmp}/bad.yaml is a file, not a folder"),
    (["export", "{tmp}/run"], "Missing option '--format'. Choose from: colmap, nerfstudio (see main export --help)"),
    (["download", "fr1/desk", "--to", "{tmp}/data", "--base-url", "notaurl"],
     "--base-url 'notaurl': expected an http://, https:// or file:// address"),
    (["config", "--config", "{tmp}/bad.yaml"], "{tmp}/bad.yaml: not valid YAML (expected ',' or ']', but got '<stream end>' "
                                               "at line 2, column 1)"),
    (["config", "--set", "mapper.iterations=[1"], "--set 'mapper.iterations=[1': the value is not valid YAML"),
    (["synth", "{tmp}/deeper/" + "x" * 300], "{tmp}/deeper/" + "x" * 300 + ": its part " + "x" * 24 + "... is 300 bytes"),
])
def test_argument_errors_are_one_line_and_write_nothing(tmp_path, arguments, message):
    (tmp_path / "bad.yaml").write_text("mapper: [1, 2\n")
    result = CliRunner().invoke(main, [argument.format(tmp=tmp_path) for argument in arguments])
    assert result.exit_code == 2 and result.output.startswith("error: " + message.format(tmp=tmp_path)), result.output
    assert len(result.output.splitlines()) == 1
    assert sorted(path.name for path in tmp_path.iterdir()) == ["bad.yaml"]


def test_synth_writes_only_into_a_new_or_empty_folder(tmp_path):
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "mine.txt").write_text("mine")
    (tmp_path / "a_file").write_text("x")
    for target, message in ((tmp_path / "notes", "is not empty (mine.txt); give a new or empty folder"),
                            (tmp_path / "a_file", "is a file; give a folder")):
        result = CliRunner().invoke(main, ["synth", str(target), "--frames", "2", "--size", "32x24"])
        assert result.exit_code == 2 and result.output.startswith(f"error: {target}: {message}"), result.output
    assert sorted(path.name for path in (tmp_path / "notes").iterdir()) == ["mine.txt"]
    (tmp_path / "empty").mkdir()
    result = CliRunner().invoke(main, ["synth", str(tmp_path / "empty"), "--frames", "2", "--size", "32x24"])
    assert result.exit_code == 0 and len(open_sequence(tmp_path / "empty")) == 2


def test_a_camera_file_of_another_size_is_refused_before_the_output_folder_is_made(synthetic_sequence_dir, tmp_path):
    camera = yaml.safe_load((synthetic_sequence_dir / "camera.yaml").read_text())
    (tmp_path / "camera.yaml").write_text(yaml.safe_dump({**camera, "width": 320, "height": 240}))
    result = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(tmp_path / "out"),
                                       "--camera", str(tmp_path / "camera.yaml")])
    first_image = open_sequence(synthetic_sequence_dir).rgb_paths[0]
    assert result.output == (f"error: {first_image}: image is 160x120 but the camera is 320x240; fix width/height in "
                             "camera.yaml (--camera), or this image if the sequence's others are 320x240\n")
    assert result.exit_code == 2 and not (tmp_path / "out").exists()


def test_a_frame_that_cannot_be_decoded_mid_run_leaves_a_run_that_says_it_is_unfinished(synthetic_sequence_dir, tmp_path):
    import shutil

    sequence_dir = tmp_path / "sequence"
    shutil.copytree(synthetic_sequence_dir, sequence_dir)
    broken = open_sequence(sequence_dir).rgb_paths[4]
    whole = broken.read_bytes()
    # Its image data zeroed under a checksum that fits: every check before the run passes, decoding fails.
    start = whole.index(b"IDAT") + 4
    end = start + int.from_bytes(whole[start - 8:start - 4], "big")
    broken.write_bytes(whole[:start] + bytes(end - start) + zlib.crc32(b"IDAT" + bytes(end - start)).to_bytes(4, "big")
                       + whole[end + 4:])
    command = ["reconstruct", str(sequence_dir), "-o", str(tmp_path / "out"), "--max-frames", "8", "--quiet",
               "--set", "mapper.enabled=false", "--set", "mesh.enabled=false"]
    result = CliRunner().invoke(main, command)
    assert result.output.splitlines()[-1] == (
        f"error: {broken}: cannot decode image (corrupt, truncated or not an image); re-extract the sequence "
        f"({tmp_path / 'out'} holds the unfinished run: the same command replaces it once that is fixed)")
    assert result.exit_code == 2 and not (tmp_path / "out" / "metrics.json").exists()
    broken.write_bytes(whole)
    result = CliRunner().invoke(main, command)
    assert result.exit_code == 0, result.output
    assert read_metrics(tmp_path / "out" / "metrics.json").frames == 8


def test_a_full_disk_or_a_refused_path_is_one_line_with_what_to_do(synthetic_sequence_dir, tmp_path, monkeypatch):
    import errno

    import pipelines.reconstruct

    for number, strerror, fix in ((errno.ENOSPC, "No space left on device", "free some space or write the outputs "
                                                                            "elsewhere (-o)"),
                                  (errno.EACCES, "Permission denied", "give a path you may read or write, or change "
                                                                      "its permissions"),
                                  (errno.EIO, "Input/output error", "check the path")):
        def refused(*arguments, **options):
            raise OSError(number, strerror, str(tmp_path / "out" / "splats.ply"))

        monkeypatch.setattr(pipelines.reconstruct, "reconstruct", refused)
        result = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(tmp_path / "out")])
        # A full disk or a failing file system is not bad input (exit 1: tambridge batch retries it).
        assert result.exit_code == (2 if number == errno.EACCES else 1)
        assert result.output == f"error: {tmp_path / 'out' / 'splats.ply'}: {strerror}; {fix}\n"


def test_an_output_folder_with_too_long_a_name_is_refused_before_its_parents_are_made(synthetic_sequence_dir, tmp_path):
    (tmp_path / "existing").mkdir()
    for output, message in ((tmp_path / "runs" / "today" / ("x" * 300), "its part " + "x" * 24 + "... is 300 bytes"),
                            (tmp_path / "existing" / ("x" * 300), "its part " + "x" * 24 + "... is 300 bytes"),
                            (tmp_path / "existing" / "/".join(["y" * 200] * 25), "is ")):
        result = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(output)])
        assert result.exit_code == 2 and result.output.startswith(f"error: {output}: {message}"), result.output
        assert result.output.endswith("may have here; give a shorter path\n") and len(result.output.splitlines()) == 1
    assert [path.name for path in tmp_path.iterdir()] == ["existing"] and not any((tmp_path / "existing").iterdir())


def test_ctrl_c_before_a_run_starts_is_one_line_with_the_status_of_sigint(synthetic_sequence_dir, tmp_path, monkeypatch):
    """Ctrl-C while a command loads its libraries (open3d, torch), before a run installs its own handlers."""
    import pipelines.reconstruct

    def interrupted(*arguments, **options):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipelines.reconstruct, "reconstruct", interrupted)
    result = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(tmp_path / "out")])
    assert (result.exit_code, result.output) == (130, "error: stopped by SIGINT\n")
    assert not (tmp_path / "out").exists()


def test_ctrl_c_that_a_library_wraps_while_it_loads_is_the_same_line(synthetic_sequence_dir, tmp_path, monkeypatch):
    """pycolmap turns a Ctrl-C during its import into ImportError, then RuntimeError ("Cannot import the C++
    backend"); an error with no Ctrl-C behind it still propagates."""
    import pipelines.reconstruct

    def interrupted_import(*arguments, **options):
        try:
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as interrupt:
                raise ImportError("initialization failed") from interrupt
        except ImportError as error:
            raise RuntimeError("Cannot import the C++ backend") from error

    monkeypatch.setattr(pipelines.reconstruct, "reconstruct", interrupted_import)
    result = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(tmp_path / "out")])
    assert (result.exit_code, result.output) == (130, "error: stopped by SIGINT\n")

    def broken(*arguments, **options):
        raise RuntimeError("a real failure")

    monkeypatch.setattr(pipelines.reconstruct, "reconstruct", broken)
    result = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(tmp_path / "out")])
    assert result.exit_code == 1 and isinstance(result.exception, RuntimeError)


def test_ctrl_c_while_the_arguments_are_parsed_is_the_same_line(monkeypatch):
    """Click would print "Aborted!" and exit 1 for a Ctrl-C in its own argument parsing."""
    def interrupted(*arguments, **options):
        raise KeyboardInterrupt

    monkeypatch.setattr(click.Group, "parse_args", interrupted)
    result = CliRunner().invoke(main, ["evaluate", "--help"])
    assert (result.exit_code, result.output) == (130, "error: stopped by SIGINT\n")


@pytest.mark.slow
def test_demo_replaces_only_its_own_run_and_refuses_others_before_rendering(tmp_path):
    from tambridge.checkpoint import checkpoint_path
    from tambridge.evaluation.metrics import write_metrics
    from tambridge.run_folder import RunFolder, Start
    from tests.test_report import _metrics as run_metrics

    demo = ["demo", "--frames", "30", "--size", "160x120", "--set", "mesh.enabled=false"]
    # The second replaces the first; it tracks only (no Gaussian map), so the first run's splats must be gone after it.
    for extra in ([], ["--set", "mapper.enabled=false"]):
        result = CliRunner().invoke(main, [*demo, *extra, "-o", str(tmp_path / "demo")])
        assert result.exit_code == 0, result.output
        assert read_metrics(tmp_path / "demo" / "metrics.json").trajectory.ate_rmse_m < 0.03
        assert (tmp_path / "demo" / "splats.ply").is_file() == (not extra)
    assert read_metrics(tmp_path / "demo" / "metrics.json").map is None
    other = tmp_path / "other"
    with RunFolder(other, Start.NEW, ["metrics.json"]):
        write_metrics(other / "metrics.json", run_metrics(sequence="/data/my_sequence"))
    killed = tmp_path / "killed"
    with RunFolder(killed, Start.NEW, ["checkpoint/checkpoint.npz"]):
        checkpoint_path(killed).parent.mkdir()
        checkpoint_path(killed).write_bytes(b"a killed run's state")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    for folder, message in ((other, f"-o {other}: holds a finished run that is not a demo's; give another -o"),
                            (killed, f"-o {killed}: holds a killed run's checkpoint; give another -o"),
                            (tmp_path / "mine", f"{tmp_path / 'mine'}: is not empty and holds no tambridge run")):
        before = {path: path.read_bytes() for path in folder.rglob("*") if path.is_file()}
        result = CliRunner().invoke(main, [*demo, "-o", str(folder)])
        assert result.exit_code == 2 and result.output.startswith(f"error: {message}"), result.output
        assert {path: path.read_bytes() for path in folder.rglob("*") if path.is_file()} == before


def test_a_bad_viewer_is_refused_before_the_output_folder_is_made(synthetic_sequence_dir, tmp_path):
    cases = [("foo", "--viewer 'foo': expected 'rerun'")]
    if importlib.util.find_spec("rerun") is None:
        cases.append(("rerun:x.rrd", "--viewer rerun:x.rrd: rerun-sdk is not installed"))
    for viewer, message in cases:
        result = CliRunner().invoke(main, ["reconstruct", str(synthetic_sequence_dir), "-o", str(tmp_path / "out"),
                                           "--viewer", viewer])
        assert result.exit_code == 2 and result.output.startswith(f"error: {message}"), result.output
        assert not (tmp_path / "out").exists()


def test_atomic_writes_leave_no_temp_files_and_normal_permissions(tmp_path):
    import os

    from tambridge.files import atomic_path, atomic_write_text

    target = tmp_path / "result.txt"
    atomic_write_text(target, "whole")
    assert target.read_text() == "whole"
    # A write that fails half-way leaves neither a new file nor a change to an existing one.
    for path in (tmp_path / "partial.txt", target):
        with pytest.raises(RuntimeError, match="killed mid-write"):
            with atomic_path(path) as temp_path:
                temp_path.write_text("half")
                raise RuntimeError("killed mid-write")
    assert target.read_text() == "whole"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.txt"]
    atomic_write_text(target, "again")
    assert target.read_text() == "again"
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask


def test_synth_writes_a_supersampled_sequence_and_refuses_an_even_factor(tmp_path):
    runner = CliRunner()
    result = runner.invoke(main, ["synth", str(tmp_path / "s"), "--frames", "2", "--size", "32x24", "--supersampling", "3"])
    assert result.exit_code == 0, result.output
    sequence = open_sequence(tmp_path / "s")
    assert len(sequence) == 2 and sequence[0].rgb.shape == (24, 32, 3)
    # Averaged rays: colours between texture values appear that one ray per pixel would not give.
    plain = runner.invoke(main, ["synth", str(tmp_path / "p"), "--frames", "2", "--size", "32x24"])
    assert plain.exit_code == 0
    assert not np.array_equal(open_sequence(tmp_path / "p")[0].rgb, sequence[0].rgb)
    np.testing.assert_array_equal(open_sequence(tmp_path / "p")[0].depth_m, sequence[0].depth_m)
    refused = runner.invoke(main, ["synth", str(tmp_path / "e"), "--supersampling", "2"])
    assert refused.exit_code == 2 and "must be odd" in refused.output


def test_synth_writes_a_rolling_shutter_and_refuses_one_longer_than_a_frame(tmp_path):
    runner = CliRunner()
    result = runner.invoke(main, ["synth", str(tmp_path / "r"), "--frames", "2", "--size", "32x24",
                                  "--rolling-shutter", "0.02"])
    assert result.exit_code == 0, result.output
    assert open_sequence(tmp_path / "r").camera.rolling_shutter_s == 0.02
    refused = runner.invoke(main, ["synth", str(tmp_path / "long"), "--rolling-shutter", "0.05"])
    assert refused.exit_code == 2
    assert refused.output == "error: synthetic sequence: rolling shutter readout 0.05 s: must be in [0, 1/fps = 0.03333] s\n"
    assert not (tmp_path / "long").exists()


def test_report_of_a_folder_without_current_metrics_exits_with_one_line(tmp_path):
    (tmp_path / "metrics.json").write_text(json.dumps({"frames": 3}))  # an older tambridge's file
    result = CliRunner().invoke(main, ["report", str(tmp_path)])
    assert result.exit_code == 2
    assert result.output.startswith(f"error: {tmp_path / 'metrics.json'}: no schema_version")
    assert len(result.output.strip().splitlines()) == 1
    assert not (tmp_path / "report").exists()
