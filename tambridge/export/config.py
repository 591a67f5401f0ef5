"""Settings of the mesh exporter."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass
class MeshConfig:
    """TSDF fusion of the final poses into ``mesh.ply``.

    ``source``: ``tsdf`` fuses the sensor depth, ``gaussians`` the depth rendered from the Gaussian map (falls
    back to the sensor depth when no map was built). Every ``frame_stride``-th frame is fused, which keeps the
    cost at a fraction of the run (consecutive frames add little). Voxels seen in fewer than ``min_views`` fused
    views are left out of the mesh (2 or more drops single-view noise but leaves holes where views are sparse).
    """

    enabled: bool = True
    voxel_size_m: float = 0.02
    truncation_m: float = 0.08
    max_depth_m: float = 4.0
    source: str = "tsdf"
    frame_stride: int = 5
    min_views: int = 1
