"""Settings of the exporters: the mesh, and the world frame every exported file is written in."""

from __future__ import annotations

import dataclasses

from tambridge.settings import POSITIVE, Choice, at_least, setting


class MeshSource(Choice):
    """The depth that TSDF fusion integrates into ``mesh.ply``."""

    sensor = "sensor"
    rendered = "rendered"

    @classmethod
    def renamed(cls) -> dict[str, str]:
        return {"tsdf": "sensor", "gaussians": "rendered"}


@dataclasses.dataclass
class MeshConfig:
    """TSDF fusion of the final poses into ``mesh.ply``.

    ``source``: ``sensor`` fuses the sensor's depth, ``rendered`` the depth rendered from the Gaussian map (the
    sensor's when no map was built). Every ``frame_stride``-th frame is fused, which keeps the cost at a fraction of
    the run (consecutive frames add little). Voxels seen in fewer than ``min_views`` fused views are left out of the
    mesh (2 or more drops single-view noise but leaves holes where views are sparse).
    """

    enabled: bool = setting(True, "write mesh.ply by TSDF fusion at the final poses")
    voxel_size_m: float = setting(0.02, "TSDF voxel size (m)", POSITIVE)
    truncation_m: float = setting(0.08, "TSDF truncation distance (m; larger than the voxel size)", POSITIVE)
    max_depth_m: float = setting(4.0, "depth beyond this is not fused (m)", POSITIVE)
    source: MeshSource = setting(MeshSource.sensor, "depth fused: sensor (the sensor's) or rendered (rendered from the "
                                                    "Gaussian map)")
    frame_stride: int = setting(5, "every n-th frame is fused", at_least(1))
    min_views: int = setting(1, "voxels seen in fewer fused views than this are left out of the mesh", at_least(1))

    def conflict(self) -> str | None:
        if self.truncation_m <= self.voxel_size_m:
            return (f"truncation_m={self.truncation_m:g} must be larger than voxel_size_m={self.voxel_size_m:g} "
                    f"(3-5 voxels is usual)")
        return None


class ExportWorld(Choice):
    """The world frame of the exported files (:mod:`tambridge.export.world`)."""

    upright = "upright"
    first_camera = "first_camera"


@dataclasses.dataclass
class ExportConfig:
    """The world of trajectory.txt, keyframes.txt, sparse_map.npz, splats.ply and mesh.ply (and so of ``tambridge
    export``'s COLMAP and nerfstudio folders); the run itself always works in the first camera's frame."""

    world: ExportWorld = setting(ExportWorld.upright, "frame of the exported files: upright (z up, gravity from "
                                                      "accelerometer.txt, else from the floor or wall planes) or "
                                                      "first_camera (the first camera's OpenCV frame, y down)")
