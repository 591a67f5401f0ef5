"""How closely the report's WebGL viewer (report/viewer/) shows what tambridge's own renderer shows, on finished runs.

    python benchmarks/web_viewer.py out/xyz37 out/synth     # any finished runs with a Gaussian map

For each run: the viewer opens from file:// in headless Chromium (WebGL on SwiftShader, Chromium's CPU
implementation) in a window of the camera's size, at the pose it starts at (the first of trajectory.txt); its
canvas's screenshot is compared with tambridge.gaussians.rasterizer's render of splats.ply, loaded back from the
file, at that pose over the same black background (no per-view exposure: the map as exported). Prints PSNR and SSIM
per run, and PSNR in the image's central half (both draw the EWA footprint; before the rasteriser did too, its
circle of radius f r / z matched the viewer's ellipse only there), and writes benchmarks/results/web_viewer.json. tests/test_web_viewer.py uses the same functions.
"""

from __future__ import annotations

import argparse
import io
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tambridge.camera import Camera  # noqa: E402
from tambridge.evaluation.rendering import psnr_db, ssim_value  # noqa: E402
from tambridge.export.splats import load_ply  # noqa: E402
from tambridge.export.web_viewer import RUN_VIEWER_FOLDER, read_viewer_view  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402
from tambridge.gaussians.rasterizer import render  # noqa: E402

CHROMIUM_FLAGS = (
    "--headless", "--no-sandbox", "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--no-first-run", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--force-device-scale-factor=1",
)  # fmt: skip
"""Headless Chromium, offline, with WebGL 2 on SwiftShader (no GPU needed)."""

OVERLAYS = ("info", "quality", "caminfo", "progress")
"""The viewer page's text overlays, hidden for a screenshot of the splats alone."""


def webgl_chromium(browser_path: str, driver_path: str, profile_dir: Path):
    """A selenium driver of headless Chromium with WebGL (the system chromedriver; works offline)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = browser_path
    for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={profile_dir}"):
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(executable_path=driver_path), options=options)


def viewer_screenshot(driver, url: str, width: int, height: int, timeout_s: float = 120.0) -> np.ndarray:
    """The viewer's canvas at ``url`` in a ``width x height`` CSS-pixel viewport, (H, W, 3) floats in [0, 1], once
    every Gaussian is drawn in the order sorted for the view shown (the page's ``window.tambridgeViewer``)."""
    from PIL import Image
    from selenium.webdriver.common.by import By

    driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride",
                           {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False})
    driver.get(url)
    deadline = time.monotonic() + timeout_s
    while (driver.execute_script("return window.tambridgeViewer && window.tambridgeViewer.sortedFrames") or 0) < 2:
        message = driver.execute_script("return document.getElementById('message').innerText")
        if message or time.monotonic() > deadline:
            raise RuntimeError(f"{url}: the viewer drew no complete frame ({message or 'timed out'})")
        time.sleep(0.1)
    driver.execute_script(f"for (const id of {list(OVERLAYS)}) document.getElementById(id).style.display = 'none';")
    driver.execute_async_script("requestAnimationFrame(() => requestAnimationFrame(arguments[0]));")
    png = driver.find_element(By.ID, "canvas").screenshot_as_png
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), np.float64) / 255.0


def rasteriser_view(splats_ply: Path, camera: Camera, world_from_camera: np.ndarray) -> np.ndarray:
    """tambridge's render of ``splats_ply`` (loaded back from the file) over black, (H, W, 3) float64 in [0, 1]."""
    return render(load_ply(splats_ply), camera, world_from_camera).rgb.numpy().astype(np.float64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="Finished run folders with report/viewer/.")
    parser.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "web_viewer.json")
    args = parser.parse_args()
    browser, driver_path = shutil.which("chromium") or shutil.which("chromium-browser"), shutil.which("chromedriver")
    if browser is None or driver_path is None:
        sys.exit("error: needs chromium and chromedriver (Debian: apt-get install -y chromium chromium-driver)")
    rows = []
    with tempfile.TemporaryDirectory(prefix="web-viewer-") as profile:
        driver = webgl_chromium(browser, driver_path, Path(profile))
        try:
            for run_dir in args.runs:
                viewer = run_dir / RUN_VIEWER_FOLDER
                camera, pose = read_viewer_view(viewer)
                shown = viewer_screenshot(driver, (viewer / "index.html").resolve().as_uri(), camera.width, camera.height)
                ours = rasteriser_view(run_dir / "splats.ply", camera, pose)
                centre = (slice(camera.height // 4, 3 * camera.height // 4), slice(camera.width // 4, 3 * camera.width // 4))
                rows.append({"run": str(run_dir), "size": f"{camera.width}x{camera.height}",
                             "gaussians": len(load_ply(run_dir / "splats.ply")),
                             "psnr_db": psnr_db(shown, ours), "ssim": ssim_value(shown, ours),
                             "psnr_centre_db": psnr_db(shown[centre].copy(), ours[centre].copy())})
                print(f"{run_dir}: {rows[-1]['size']}, {rows[-1]['gaussians']} Gaussians: viewer against the "
                      f"rasteriser {rows[-1]['psnr_db']:.2f} dB PSNR, SSIM {rows[-1]['ssim']:.4f}; in the image's "
                      f"central half {rows[-1]['psnr_centre_db']:.2f} dB")
        finally:
            driver.quit()
    atomic_write_text(args.json, json.dumps({"runs": rows}, indent=2) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
