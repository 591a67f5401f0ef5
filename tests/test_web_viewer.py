"""The run's splat viewer (antimatter15/splat, vendored) shows what tambridge's renderer shows: a headless-Chromium
screenshot at the run's first pose, opened from file:// and from `tambridge view`'s server, against the rasteriser's
render of the splats loaded back from the .ply (no exposure)."""

import base64
import dataclasses
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from benchmarks.web_viewer import rasteriser_view, viewer_screenshot, webgl_chromium
from tambridge.camera import Camera
from tambridge.errors import ViewerError
from tambridge.evaluation.metrics import write_metrics
from tambridge.evaluation.rendering import psnr_db
from tambridge.export.splats import load_ply, save_ply
from tambridge.export.web_viewer import RUN_VIEWER_FOLDER, VIEWER_FILES, read_viewer_view, write_run_viewer
from tambridge.gaussians.model import GaussianTensors
from tambridge.geometry import exp_se3
from tambridge.io.synthetic import default_camera, loop_path, make_room_scene, render as ray_cast
from tambridge.trajectory import Trajectory, read_tum_trajectory, write_tum_trajectory
from tests.test_report import _chromium_paths, _metrics

ROOT = Path(__file__).resolve().parent.parent

CAMERA = default_camera(160, 120)
"""The viewer's camera: the run's frames' camera."""

VIEWER_MIN_PSNR_DB = 42.0
"""Screenshot against the rasteriser. Both project each splat with the EWA Jacobian; they differ by design in small
ways: the viewer quantises colour and opacity to 8 bits and covariances to half floats, cuts a splat off at 2.8
instead of 3 standard deviations, does not clamp alpha at 0.99 nor stop at the transmittance floor, does not clamp
the Jacobian off the image, and sorts by a 16-bit depth key. The bound
is set above what the smallest error of a wrong view below scores and above what a rasteriser drawing circles of
radius f r / z instead of the EWA footprint scored (docs/viewer.md), with a margin for the viewer's own differences."""
WRONG_MAX_PSNR_DB = 34.0
"""The screenshot against a render that is wrong by a mirror, an up-down flip, the inverse pose, a degree of yaw,
2 cm sideways or half a pixel of principal point (the pixel-centre convention) must score below this: the
agreement is about the pose and the projection, not about the map's blur."""


def _room_map() -> tuple[GaussianTensors, np.ndarray]:
    """Gaussians on the synthetic room's surfaces as an 80x60 depth camera at a loop pose sees them (one per pixel,
    a pixel's footprint in radius), and that pose: a tilted, moved camera, so a transposed or inverted pose shows."""
    pose = loop_path(30)[7]
    camera = default_camera(80, 60)
    rgb, depth_m = ray_cast(make_room_scene(0), camera, pose)
    columns, rows = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
    points_camera = camera.backproject(np.stack([columns, rows], axis=-1), depth_m.astype(np.float64)).reshape(-1, 3)
    seen = depth_m.reshape(-1) > 0
    points_world = points_camera[seen] @ pose[:3, :3].T + pose[:3, 3]
    radii_m = depth_m.reshape(-1)[seen] / camera.fx * 0.8
    gaussians = GaussianTensors(
        means_m=torch.tensor(points_world, dtype=torch.float32),
        rgb=torch.tensor(rgb.reshape(-1, 3)[seen], dtype=torch.float32),
        log_radii_m=torch.tensor(np.log(radii_m), dtype=torch.float32),
        opacity_logits=torch.full((int(seen.sum()),), 3.0),
    )
    return gaussians, pose


@pytest.fixture(scope="module")
def splat_run(tmp_path_factory) -> Path:
    """A finished run's folder as reconstruct leaves it, as far as the viewer reads it: splats.ply, trajectory.txt
    (first pose the map's), metrics.json and report/viewer/."""
    run_dir = tmp_path_factory.mktemp("run")
    gaussians, pose = _room_map()
    save_ply(run_dir / "splats.ply", gaussians)
    poses = np.stack([pose, pose @ exp_se3(np.array([0.05, 0.0, 0.0, 0.0, 0.1, 0.0]))])
    write_tum_trajectory(run_dir / "trajectory.txt", Trajectory(np.array([0.0, 0.1]), poses))
    write_metrics(run_dir / "metrics.json", _metrics())
    write_run_viewer(run_dir, CAMERA)
    return run_dir


@pytest.fixture(scope="module")
def webgl_browser(tmp_path_factory):
    """Headless Chromium with WebGL on SwiftShader (skipped without chromium and chromedriver, as the report test)."""
    driver = webgl_chromium(*_chromium_paths(), tmp_path_factory.mktemp("chromium-profile"))
    yield driver
    driver.quit()


def _ours(run_dir: Path, camera: Camera, world_from_camera: np.ndarray) -> np.ndarray:
    return rasteriser_view(run_dir / "splats.ply", camera, world_from_camera)


def _first_pose(run_dir: Path) -> np.ndarray:
    return read_tum_trajectory(run_dir / "trajectory.txt").world_from_camera[0]


def test_the_viewer_starts_at_the_runs_first_pose_and_camera(splat_run):
    camera, world_from_camera = read_viewer_view(splat_run / RUN_VIEWER_FOLDER)
    assert camera == dataclasses.replace(CAMERA, distortion=camera.distortion)
    np.testing.assert_allclose(world_from_camera, _first_pose(splat_run), atol=1e-12)
    data = (splat_run / RUN_VIEWER_FOLDER / "splats.js").read_text()
    assert base64.b64decode(data.split('ply_base64 = "')[1].split('"')[0]) == (splat_run / "splats.ply").read_bytes()


def test_tambridge_report_shows_splats_ply_as_it_is_now(splat_run, tmp_path, caplog):
    """A user cleans the map in another tool and rebuilds the report: its viewer shows the cleaned file, from the
    same first view; with splats.ply gone, the report has no viewer and says why."""
    from tambridge.evaluation.report import report_from_run

    run = tmp_path / "run"
    shutil.copytree(splat_run, run)
    gaussians = load_ply(run / "splats.ply")
    save_ply(run / "splats.ply", GaussianTensors(*(tensor[: len(gaussians) // 2] for tensor in dataclasses.astuple(gaussians))))
    assert 'src="viewer/index.html"' in report_from_run(run).read_text()
    data = (run / RUN_VIEWER_FOLDER / "splats.js").read_text()
    assert base64.b64decode(data.split('ply_base64 = "')[1].split('"')[0]) == (run / "splats.ply").read_bytes()
    assert read_viewer_view(run / RUN_VIEWER_FOLDER)[0] == read_viewer_view(splat_run / RUN_VIEWER_FOLDER)[0]
    (run / "splats.ply").unlink()
    assert "viewer/index.html" not in report_from_run(run).read_text()
    assert f"{run / 'splats.ply'}: not found: the rebuilt report has no viewer" in caplog.text
    # A run without a viewer (the mapper off) gets none.
    write_metrics(tmp_path / "metrics.json", _metrics())
    write_tum_trajectory(tmp_path / "trajectory.txt", read_tum_trajectory(splat_run / "trajectory.txt"))
    assert "viewer/index.html" not in report_from_run(tmp_path).read_text()


def _assert_agrees_and_beats_wrong_views(shown: np.ndarray, run_dir: Path, camera: Camera) -> None:
    pose = _first_pose(run_dir)
    ours = _ours(run_dir, camera, pose)
    assert shown.shape == ours.shape
    agreement = psnr_db(shown, ours)
    shift_px = 0.5 * camera.width / CAMERA.width  # half a pixel of the frames' camera, in the window's pixels
    wrong = {
        "mirrored": psnr_db(shown, np.fliplr(ours).copy()),
        "upside down": psnr_db(shown, np.flipud(ours).copy()),
        "inverse pose": psnr_db(shown, _ours(run_dir, camera, np.linalg.inv(pose))),
        "1 degree yaw": psnr_db(shown, _ours(run_dir, camera, pose @ exp_se3(np.r_[0, 0, 0, 0, np.deg2rad(1.0), 0]))),
        "2 cm right": psnr_db(shown, _ours(run_dir, camera, pose @ exp_se3(np.r_[0.02, 0, 0, 0, 0, 0]))),
        "half a pixel": psnr_db(shown, _ours(run_dir, dataclasses.replace(camera, cx=camera.cx + shift_px,
                                                                          cy=camera.cy + shift_px), pose)),
    }
    print(f"viewer against the rasteriser: {agreement:.2f} dB; wrong views: {wrong}")
    assert agreement > VIEWER_MIN_PSNR_DB, (agreement, wrong)
    assert max(wrong.values()) < WRONG_MAX_PSNR_DB, (agreement, wrong)


@pytest.mark.slow
def test_viewer_from_the_file_system_shows_the_renderers_image_at_the_first_pose(webgl_browser, splat_run):
    index = splat_run / RUN_VIEWER_FOLDER / "index.html"
    shown = viewer_screenshot(webgl_browser, index.resolve().as_uri(), CAMERA.width, CAMERA.height)
    _assert_agrees_and_beats_wrong_views(shown, splat_run, CAMERA)
    assert webgl_browser.execute_script("return window.tambridgeViewer.vertexCount") == len(load_ply(splat_run / "splats.ply"))


@pytest.mark.slow
def test_tambridge_view_serves_the_viewer_on_localhost_fitted_to_the_window(webgl_browser, splat_run):
    """Through the server, in a window twice the camera's size: the image is the camera's, scaled."""
    from pipelines.view import ViewerServer

    with ViewerServer(splat_run) as server:
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        try:
            assert server.server_address[0] == "127.0.0.1" and server.url.startswith("http://127.0.0.1:")
            shown = viewer_screenshot(webgl_browser, server.url, 2 * CAMERA.width, 2 * CAMERA.height)
            with pytest.raises(urllib.error.HTTPError, match="404"):  # the report folder only, not the run's
                urllib.request.urlopen(server.url.replace("viewer/index.html", "../metrics.json"))
        finally:
            server.shutdown()
            thread.join()
    _assert_agrees_and_beats_wrong_views(shown, splat_run, CAMERA.scaled(2.0))


@pytest.mark.slow
def test_a_run_report_embeds_a_working_viewer_of_its_splats(webgl_browser, synthetic_sequence_dir, tmp_path):
    from pipelines.reconstruct import RUN_FILES, reconstruct
    from tambridge.config import load_config

    config = load_config(None, ["input.max_frames=4", "mapper.iterations=2", "mesh.enabled=false"])
    reconstruct(synthetic_sequence_dir, tmp_path / "run", config, progress=False)
    assert {f"{RUN_VIEWER_FOLDER.as_posix()}/{name}" for name in VIEWER_FILES} <= set(RUN_FILES)
    webgl_browser.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})
    webgl_browser.get((tmp_path / "run" / "report" / "index.html").resolve().as_uri())
    headings = webgl_browser.execute_script("return Array.from(document.querySelectorAll('h2')).map(h => h.textContent)")
    assert "Splats" in headings
    # The iframe loads lazily (a report opens without decoding the splats): bring it into view.
    webgl_browser.execute_script("document.getElementById('web-viewer').scrollIntoView()")
    webgl_browser.switch_to.frame("web-viewer")
    try:
        deadline = time.monotonic() + 60.0
        while (webgl_browser.execute_script("return window.tambridgeViewer.sortedFrames") or 0) < 1:
            assert time.monotonic() < deadline, "the embedded viewer did not draw"
            time.sleep(0.1)
        assert webgl_browser.execute_script("return window.tambridgeViewer.vertexCount") == \
            len(load_ply(tmp_path / "run" / "splats.ply"))
    finally:
        webgl_browser.switch_to.default_content()


def test_view_refuses_what_is_no_finished_runs_viewer_in_one_line(tmp_path, splat_run):
    from cli import main
    from pipelines.view import ViewerServer

    (tmp_path / "unfinished").mkdir()
    (tmp_path / "no-map").mkdir()
    write_metrics(tmp_path / "no-map" / "metrics.json", _metrics())
    for folder, message in ((tmp_path / "none", "not a folder"), (tmp_path / "unfinished", "holds no finished run"),
                            (tmp_path / "no-map", "report/viewer/index.html: not found")):
        with pytest.raises(ViewerError, match=message):
            ViewerServer(folder)
        result = CliRunner().invoke(main, ["view", str(folder)])
        assert result.exit_code == 2 and message in result.output and len(result.output.strip().splitlines()) == 1
    with ViewerServer(splat_run) as taken, pytest.raises(ViewerError, match=f"127.0.0.1:{taken.server_address[1]}: "
                                                                             "cannot listen there"):
        ViewerServer(splat_run, taken.server_address[1])


def test_a_signal_that_lands_while_a_request_is_handled_still_stops_the_server(splat_run):
    """socketserver catches any Exception raised while it hands a request to a thread, and a stop raised by a signal
    handler there would be lost (CI once saw `tambridge view` keep serving after SIGINT)."""
    from pipelines.view import ViewerServer

    class SignalledWhileHandling(ViewerServer):
        def process_request(self, request, client_address):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.2)  # the signal is taken while this request is still being handed over
            super().process_request(request, client_address)

    with SignalledWhileHandling(splat_run) as server:
        watchdog = threading.Timer(20.0, server.shutdown)
        watchdog.start()
        threading.Thread(target=lambda: urllib.request.urlopen(server.url).read(), daemon=True).start()
        started = time.monotonic()
        server.serve_until_stopped()
        watchdog.cancel()
    assert time.monotonic() - started < 10.0, "the server served on after SIGTERM"


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_view_command_prints_the_url_serves_the_page_and_stops_on_ctrl_c(splat_run, signum):
    """Ctrl-C or a kill stops the server cleanly, also where it was started with SIGINT ignored (as a shell starts
    a background job)."""
    process = subprocess.Popen([sys.executable, str(ROOT / "cli.py"), "view", str(splat_run)], cwd=ROOT,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "PYTHONPATH": str(ROOT)},
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        url = process.stdout.readline().strip().removeprefix("viewer: ")
        assert url.startswith("http://127.0.0.1:") and url.endswith("/viewer/index.html"), url
        with urllib.request.urlopen(url) as response:
            assert b'<script src="splats.js"></script>' in response.read()
        with urllib.request.urlopen(url.replace("index.html", "splats.js")) as response:
            assert response.read().startswith(b"window.TAMBRIDGE_VIEW = ")
        process.send_signal(signum)
        stdout, stderr = process.communicate(timeout=30)
    finally:
        process.kill()
    assert process.returncode == 0 and "stopped" in stdout and "Traceback" not in stderr, (stdout, stderr)
