"""Exporters of a run's results: Gaussian splats (:mod:`~tambridge.export.splats`, INRIA 3DGS .ply) and meshes
(:mod:`~tambridge.export.mesh`). The trajectory's TUM format is read as well as written, so it lives with the
type in :mod:`tambridge.trajectory`; every file is written atomically (:mod:`tambridge.files`)."""
