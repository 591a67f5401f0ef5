"""The run report opens in headless Chromium from file://: every image loads, the metrics table shows the run's numbers."""

import shutil
from pathlib import Path

import numpy as np
import pytest

from tambridge.state import dotted_items
from tambridge.errors import TambridgeError
from tambridge.evaluation.metrics import (
    SCHEMA_VERSION,
    DeviceMetrics,
    RunMetrics,
    TrajectoryMetrics,
    metrics_json,
    read_metrics,
    write_metrics,
)
from tambridge.evaluation.report import RenderPair, format_metric, report_from_run, write_report
from tambridge.evaluation.trajectory import evaluate_trajectory
from tambridge.geometry import exp_se3
from tambridge.trajectory import Trajectory

CHROMIUM_FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
    "--disable-sync", "--no-first-run",
)


def _chromium_paths() -> tuple[str, str]:
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if browser is None or driver is None:
        pytest.skip("chromium and chromedriver are not installed (Debian: apt-get install -y chromium chromium-driver)")
    return browser, driver


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    """Headless Chromium driven through selenium with the system chromedriver (works offline)."""
    browser_path, driver_path = _chromium_paths()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = browser_path
    for flag in CHROMIUM_FLAGS:
        options.add_argument(flag)
    options.add_argument(f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}")
    driver = webdriver.Chrome(service=Service(executable_path=driver_path), options=options)
    yield driver
    driver.quit()


def _open(browser, index: Path) -> dict:
    """Load the page from file:// and read back what a person would see: images and the metrics table."""
    browser.get(index.resolve().as_uri())
    return browser.execute_script(
        """
        const images = Array.from(document.images).map(i => ({src: i.getAttribute('src'), complete: i.complete,
                                                              width: i.naturalWidth}));
        const cells = {};
        document.querySelectorAll('#metrics td.value').forEach(td => { cells[td.dataset.key] = td.textContent; });
        const headings = Array.from(document.querySelectorAll('h2')).map(h => h.textContent);
        return {images: images, cells: cells, headings: headings};
        """
    )


def _metrics(**fields) -> RunMetrics:
    """Run metrics of a 30-frame run without a map or ground truth; ``fields`` replace any of them."""
    values = dict(sequence="seq", frames=30, keyframes=5, frontend="orb", frames_lost=0, frames_relocalised=0,
                  frames_without_depth=0, loops_closed=0, keyframes_culled=0, frontend_seconds_per_stage={},
                  seconds_total=10.0, fps_end_to_end=3.0, seconds_per_stage={}, fps_per_stage={}, peak_memory_mb=500.0,
                  peak_memory_mb_tracking=400.0, warnings=0, trajectory=None, trajectory_unavailable="no ground truth",
                  device=DeviceMetrics(device="cpu"))
    return RunMetrics(**{**values, **fields})


def _perturbed(reference: Trajectory, seed: int, sigma_m: float, scale: float = 1.0) -> Trajectory:
    rng = np.random.default_rng(seed)
    poses = []
    for pose in reference.world_from_camera:
        moved = pose @ exp_se3(np.concatenate([rng.normal(0, sigma_m, 3), rng.normal(0, 0.002, 3)]))
        moved[:3, 3] *= scale
        poses.append(moved)
    return Trajectory(reference.timestamps_s, np.stack(poses))


@pytest.mark.slow
def test_full_report_loads_every_image(browser, tmp_path):
    from tambridge.io.synthetic import loop_path

    reference = Trajectory(np.arange(30) / 30.0, loop_path(30))
    errors = {
        "tambridge (SE(3))": evaluate_trajectory(_perturbed(reference, 0, 0.01), reference, "se3"),
        "COLMAP (Sim(3))": evaluate_trajectory(_perturbed(reference, 1, 0.005, scale=0.3), reference, "sim3"),
    }
    rng = np.random.default_rng(0)
    pairs = [RenderPair(f"frame {i}", rng.integers(0, 255, (24, 32, 3), np.uint8), rng.integers(0, 255, (24, 32, 3), np.uint8))
             for i in range(9)]
    metrics = _metrics(fps_end_to_end=3.25, seconds_per_stage={"read": 0.5, "tracking": 4.0, "mapping": 20.0},
                       frontend_seconds_per_stage={"features": 1.0, "pnp": 2.0},
                       trajectory=TrajectoryMetrics(**errors["tambridge (SE(3))"].summary()))
    index = write_report(tmp_path / "report", metrics, errors, pairs, (np.arange(30), np.arange(30) * 100))
    page = _open(browser, index)
    assert {image["src"] for image in page["images"]} == {"trajectory.png", "renders.png", "stages.png", "gaussians.png"}
    assert all(image["complete"] and image["width"] > 0 for image in page["images"]), page["images"]
    assert page["headings"] == ["Trajectory", "Renders", "Time per stage", "Gaussians", "Metrics"]
    assert page["cells"]["trajectory.ate_rmse_m"] == format_metric(errors["tambridge (SE(3))"].ate_rmse_m)
    assert page["cells"]["fps_end_to_end"] == "3.25"
    assert len(page["cells"]) == len(dotted_items(metrics_json(metrics)))
    assert not list((tmp_path / "report").glob("*.partial"))


def test_report_without_optional_inputs_skips_their_sections(browser, tmp_path):
    index = write_report(tmp_path / "report", _metrics(frames=3))
    page = _open(browser, index)
    assert page["images"] == []
    assert page["headings"] == ["Metrics"]
    assert page["cells"]["frames"] == "3" and page["cells"]["trajectory"] == "-" and page["cells"]["device"] == "cpu"
    assert page["cells"]["schema_version"] == str(SCHEMA_VERSION) and "gaussians" not in page["cells"]


def test_reconstruct_run_report_shows_the_run_metrics(browser, synthetic_sequence_dir, tmp_path):
    """A real (short) run: its report/index.html shows metrics.json's numbers and all its images load."""
    from pipelines.reconstruct import reconstruct
    from tambridge.config import load_config

    config = load_config(None, ["mapper.enabled=false", "input.max_frames=12"])
    reconstruct(synthetic_sequence_dir, tmp_path / "run", config, progress=False)
    metrics = read_metrics(tmp_path / "run" / "metrics.json")
    assert (tmp_path / "run" / "report" / "index.html").is_file()
    page = _open(browser, tmp_path / "run" / "report" / "index.html")
    assert page["images"] and all(image["complete"] and image["width"] > 0 for image in page["images"])
    assert page["cells"]["trajectory.ate_rmse_m"] == format_metric(metrics.trajectory.ate_rmse_m)
    assert page["cells"]["frames"] == "12"
    # Rebuilt from the run's files (tambridge report): the same table.
    rebuilt = _open(browser, report_from_run(tmp_path / "run"))
    assert rebuilt["cells"] == page["cells"]


def test_metrics_files_round_trip_and_bad_ones_are_refused_in_one_line(tmp_path):
    path = tmp_path / "metrics.json"
    metrics = _metrics(trajectory=TrajectoryMetrics(alignment="se3", pose_count=30, ate_rmse_m=0.02, ate_mean_m=0.01,
                                                    ate_median_m=0.01, ate_max_m=0.05, rpe_trans_rmse_m=0.03,
                                                    rpe_rot_rmse_deg=0.5, scale=1.0))
    write_metrics(path, metrics)
    assert read_metrics(path) == metrics
    written = path.read_text()
    assert written.startswith(f'{{\n  "schema_version": {SCHEMA_VERSION},\n  "sequence": "seq",')
    assert '"map"' not in written and '"rendering"' not in written  # no map: its keys are absent
    for text, message in (
        ("{", "not JSON"),
        (written.replace(f'"schema_version": {SCHEMA_VERSION}', '"schema_version": 0'),
         f"schema_version 0; this tambridge reads schema_version {SCHEMA_VERSION}"),
        (written.replace(f'  "schema_version": {SCHEMA_VERSION},\n', ""), "no schema_version"),
        (written.replace('"frames_lost"', '"lost_frames"'), "lacks key 'frames_lost'"),
        (written.replace('"ate_mean_m"', '"ate_average_m"'), "lacks key 'trajectory.ate_mean_m'"),
    ):
        path.write_text(text)
        with pytest.raises(TambridgeError, match=message) as error:
            read_metrics(path)
        assert str(path) in str(error.value) and "\n" not in str(error.value)
    with pytest.raises(TambridgeError, match="not found; is .* the output folder of a finished reconstruct run"):
        read_metrics(tmp_path / "none" / "metrics.json")
