"""Exporters: trajectories, splats, meshes and run records, all written atomically."""
