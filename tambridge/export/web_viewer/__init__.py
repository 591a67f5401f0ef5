"""An interactive WebGL viewer of a run's splats.ply that opens from the file system, with no network.

The viewer is antimatter15/splat (MIT; ``LICENSE`` and ``README.md`` in this folder say from where), adapted to
start at a given camera (principal point included) and to read its data from ``splats.js``: the .ply's bytes in
base64 and the camera, in one ``<script>``, because a page opened from ``file://`` may not ``fetch()`` a local file.
The same folder works from a local server (``tambridge view RUN``). The viewer parses the .ply itself (its own
INRIA-layout reader), so what it shows is what any 3DGS viewer reads from the file.
"""

from __future__ import annotations

import base64
import importlib.resources
import json
from pathlib import Path

import numpy as np

from tambridge.camera import Camera
from tambridge.files import atomic_write_bytes, atomic_write_text
from tambridge.trajectory import read_tum_trajectory

ASSETS = ("index.html", "main.js", "LICENSE")
"""The vendored viewer's files, copied unchanged into every viewer folder."""
DATA_NAME = "splats.js"
"""The script holding the splats and the camera (``window.TAMBRIDGE_VIEW``)."""
VIEWER_FILES = (*ASSETS, DATA_NAME)
"""Every file :func:`write_web_viewer` writes into its folder."""
RUN_VIEWER_FOLDER = Path("report") / "viewer"
"""Where a run's viewer lives, relative to the run folder."""


def viewer_camera(camera: Camera, world_from_camera: np.ndarray) -> dict:
    """The viewer's camera: an INRIA ``cameras.json`` entry (``rotation`` the 3x3 world_from_camera rotation, row by
    row, ``position`` the camera centre in the world, metres; OpenCV frame: x right, y down, z forward) with the
    principal point ``cx``, ``cy`` (pixels, centres at integer coordinates). ``world_from_camera``: (4, 4)."""
    world_from_camera = np.asarray(world_from_camera, np.float64)
    if world_from_camera.shape != (4, 4) or not np.isfinite(world_from_camera).all():
        raise ValueError(f"viewer_camera: world_from_camera must be a finite 4x4 pose, got {world_from_camera.shape}")
    return {
        "id": 0, "img_name": "first frame", "width": int(camera.width), "height": int(camera.height),
        "position": world_from_camera[:3, 3].tolist(), "rotation": world_from_camera[:3, :3].tolist(),
        "fx": float(camera.fx), "fy": float(camera.fy), "cx": float(camera.cx), "cy": float(camera.cy),
    }  # fmt: skip


def read_viewer_view(folder: Path) -> tuple[Camera, np.ndarray]:
    """The camera and (4, 4) world_from_camera a viewer folder written by :func:`write_web_viewer` starts at."""
    first_line = (Path(folder) / DATA_NAME).open(encoding="ascii").readline()
    entry = json.loads(first_line.removeprefix("window.TAMBRIDGE_VIEW = ").rstrip().removesuffix(";"))["camera"]
    camera = Camera(entry["width"], entry["height"], entry["fx"], entry["fy"], entry["cx"], entry["cy"])
    world_from_camera = np.eye(4)
    world_from_camera[:3, :3], world_from_camera[:3, 3] = entry["rotation"], entry["position"]
    return camera, world_from_camera


def write_web_viewer(folder: Path, splats_ply: Path, camera: Camera, world_from_camera: np.ndarray) -> Path:
    """Write the viewer of ``splats_ply`` into ``folder`` (created), starting at ``world_from_camera`` (4, 4) seen
    by ``camera`` (its distortion is ignored, as the renderer ignores it); returns ``folder/index.html``.

    Every file is written atomically; ``splats.js`` is about 4/3 of the .ply's size.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    view = {"camera": viewer_camera(camera, world_from_camera)}
    ply = base64.b64encode(Path(splats_ply).read_bytes()).decode("ascii")
    atomic_write_text(folder / DATA_NAME, f"window.TAMBRIDGE_VIEW = {json.dumps(view)};\n"
                                          f'window.TAMBRIDGE_VIEW.ply_base64 = "{ply}";\n')
    assets = importlib.resources.files(__package__)
    for name in ASSETS:
        atomic_write_bytes(folder / name, assets.joinpath(name).read_bytes())
    return folder / "index.html"


def write_run_viewer(run_dir: Path, camera: Camera) -> Path:
    """Write ``run_dir/report/viewer/`` from the run's own files: ``splats.ply``, seen by ``camera`` (the frames'
    undistorted camera) from the first pose of ``trajectory.txt``, so that the viewer agrees with whatever world
    those files are written in. Returns the viewer's ``index.html``."""
    run_dir = Path(run_dir)
    first_pose = read_tum_trajectory(run_dir / "trajectory.txt").world_from_camera[0]
    return write_web_viewer(run_dir / RUN_VIEWER_FOLDER, run_dir / "splats.ply", camera, first_pose)
