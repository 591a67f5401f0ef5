"""Pose-graph optimisation over keyframes with Open3D's ``global_optimization`` (used by both frontends).

Open3D's conventions, checked in tests: a node's pose is ``world_from_node``; an edge (source, target) holds
``target_from_source`` (it maps source-camera points into the target camera). Edges marked ``uncertain``
(loop closures) may be pruned by Open3D's line process when they disagree with the rest of the graph.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import open3d as o3d


@dataclasses.dataclass
class PoseEdge:
    """A relative-pose constraint ``target_from_source`` (4, 4) with its 6x6 information (Open3D's order)."""

    source: int
    target: int
    target_from_source: np.ndarray
    information: np.ndarray
    uncertain: bool = False


def optimise_pose_graph(
    world_from_node: np.ndarray,
    edges: list[PoseEdge],
    reference_node: int = 0,
    edge_prune_threshold: float = 0.25,
    preference_loop_closure: float = 1.0,
    max_correspondence_distance_m: float = 0.05,
) -> tuple[np.ndarray, int]:
    """Optimise node poses (N, 4, 4) under the edges (Levenberg-Marquardt); ``reference_node`` stays fixed.

    Returns ``(world_from_node (N, 4, 4), count of uncertain edges kept)``.
    """
    registration = o3d.pipelines.registration
    graph = registration.PoseGraph()
    for pose in world_from_node:
        graph.nodes.append(registration.PoseGraphNode(np.asarray(pose, np.float64)))
    for edge in edges:
        graph.edges.append(registration.PoseGraphEdge(
            edge.source, edge.target, np.asarray(edge.target_from_source, np.float64),
            np.asarray(edge.information, np.float64), edge.uncertain,
        ))
    option = registration.GlobalOptimizationOption(
        max_correspondence_distance=max_correspondence_distance_m,
        edge_prune_threshold=edge_prune_threshold,
        preference_loop_closure=preference_loop_closure,
        reference_node=reference_node,
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        registration.global_optimization(
            graph, registration.GlobalOptimizationLevenbergMarquardt(),
            registration.GlobalOptimizationConvergenceCriteria(), option,
        )
    kept = sum(1 for e in graph.edges if e.uncertain)
    return np.stack([np.asarray(node.pose) for node in graph.nodes]), kept
