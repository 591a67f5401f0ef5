"""The frontend a config names (imports Open3D and numba: the contract and the configs do not)."""

from __future__ import annotations

from tambridge.camera import Camera
from tambridge.errors import ConfigError
from tambridge.frontend.config import FrontendConfig
from tambridge.frontend.contract import Frontend
from tambridge.frontend.open3d.frontend import Open3dFrontend
from tambridge.frontend.open3d.odometry import FrameToFrameOdometry
from tambridge.frontend.orb.frontend import OrbFrontend


def make_frontend(settings: FrontendConfig, camera: Camera) -> Frontend:
    """The frontend named by ``settings.kind`` (``orb``, ``open3d`` or ``open3d_f2f``), for images of ``camera``."""
    if settings.kind == "orb":
        return OrbFrontend(camera, settings.orb)
    if settings.kind == "open3d":
        return Open3dFrontend(camera, settings.open3d)
    if settings.kind == "open3d_f2f":
        return FrameToFrameOdometry(camera, settings.open3d.max_depth_m, settings.open3d.depth_diff_max_m)
    raise ConfigError(f"frontend.kind={settings.kind!r}: expected one of orb, open3d, open3d_f2f")
