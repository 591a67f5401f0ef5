"""Why loops do or do not close: every loop query of the ORB frontend on a sequence with ground truth, the keyframes
the place recognition returned and the check that rejected each, beside the ground truth's revisits.

    python benchmarks/loops.py                                  # the whole TUM fr1/xyz (looked for under --data)
    python benchmarks/loops.py --sequence DIR --max-frames 300  # another sequence, or fewer frames

The frontend runs tracking only with the default preset's ORB settings (as ``tambridge reconstruct --set
mapper.enabled=false``), with :func:`~tambridge.frontend.orb.loop_closing.detect_loop` given a trace list. A
*revisit* is a pair (query keyframe, earlier keyframe) at least ``--min-gap-s`` apart in time whose ground-truth
poses lie within ``--revisit-m`` and ``--revisit-deg`` of each other: a place recognition that works returns it.
For each query the table counts what became of the returned keyframes (``LoopOutcome``: covisible, i.e. sharing
map points with the query and so already tied to it by tracking; low score; inconsistent; not tried; unverified;
accepted), and of its revisits (``missed``: not returned at all). ``drift cm`` is how far the estimate's relative
translation between the two keyframes of a revisit lies from the ground truth's (what a loop could correct). Every
returned keyframe that is not covisible carries the ground truth's distance to the query; ``nearest_non_covisible_m``
is the nearest per outcome (a false candidate lies far away). Rows go to stdout, everything to
benchmarks/results/loops.json; the trace's extra verification (to count inliers) makes the run a little slower.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import datetime
import functools
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe_machine  # noqa: E402
from benchmarks.sequences import FR1_XYZ, add_sequence_arguments, camera_file_for, find_sequence  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402

MISSED = "missed"


def revisits(times_s: np.ndarray, world_from_camera: np.ndarray, min_gap_s: float, within_m: float,
             within_deg: float) -> list[tuple[int, int]]:
    """Pairs ``(later, earlier)`` of indices into ``times_s`` (K,) / ``world_from_camera`` (K, 4, 4), ground
    truth, at least ``min_gap_s`` apart whose positions lie within ``within_m`` and viewing directions within
    ``within_deg``."""
    pairs = []
    for later in range(len(times_s)):
        for earlier in range(later):
            if times_s[later] - times_s[earlier] < min_gap_s:
                continue
            distance_m, angle_deg = pose_gap(world_from_camera[later], world_from_camera[earlier])
            if distance_m <= within_m and angle_deg <= within_deg:
                pairs.append((later, earlier))
    return pairs


def pose_gap(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Distance (m) between two poses (4x4 each) and angle (deg) between their optical axes."""
    angle = np.degrees(np.arccos(np.clip(a[:3, 2] @ b[:3, 2], -1.0, 1.0)))
    return float(np.linalg.norm(a[:3, 3] - b[:3, 3])), float(angle)


def relative_drift_m(estimate: np.ndarray, truth: np.ndarray, a: int, b: int) -> float:
    """Translation error (m) of the estimate's pose of ``a`` relative to ``b`` against the truth's ((K, 4, 4) each)."""
    from tambridge.geometry import inverse

    error = inverse(inverse(truth[b]) @ truth[a]) @ (inverse(estimate[b]) @ estimate[a])
    return float(np.linalg.norm(error[:3, 3]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_sequence_arguments(parser, FR1_XYZ)
    parser.add_argument("--max-frames", type=int)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="config override, e.g. frontend.orb.loop_min_inliers=30")
    parser.add_argument("--min-gap-s", type=float, default=5.0)
    parser.add_argument("--revisit-m", type=float, default=0.05)
    parser.add_argument("--revisit-deg", type=float, default=10.0)
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "loops.json")
    arguments = parser.parse_args()
    folder = find_sequence(arguments.sequence, arguments.data)

    import tambridge.frontend.orb.frontend as orb_frontend
    from tambridge.config import load_config
    from tambridge.evaluation.trajectory import evaluate_trajectory
    from tambridge.frontend.orb.loop_closing import LoopOutcome, detect_loop
    from tambridge.io.tum import open_sequence

    config = load_config(ROOT / "configs" / "default.yaml", arguments.set)
    sequence = open_sequence(folder, camera_file=camera_file_for(folder), max_frames=arguments.max_frames)
    if sequence.ground_truth is None:
        parser.exit(2, f"{folder}: no groundtruth.txt; revisits are found from the ground truth\n")
    queries = []
    # The frontend calls the module's detect_loop: the traced one records every query (its decisions unchanged).
    orb_frontend.detect_loop = functools.partial(detect_loop, trace=queries)
    frontend = orb_frontend.OrbFrontend(sequence.camera, config.frontend.orb)
    started = time.perf_counter()
    for index in range(len(sequence)):
        frontend.track(sequence[index])
    result = frontend.finish()
    seconds = time.perf_counter() - started
    errors = evaluate_trajectory(result.trajectory, sequence.ground_truth, align="se3")

    # Keyframes with a ground-truth pose, at their frames' times; the estimate's final keyframe poses.
    frame_of = result.keyframe_frame_indices
    times = result.trajectory.timestamps_s
    keyframe_ids = sorted(frame_of)
    truth_at = sequence.ground_truth.nearest(times[[frame_of[k] for k in keyframe_ids]])
    close = np.abs(truth_at.timestamps_s - times[[frame_of[k] for k in keyframe_ids]]) <= 0.02
    keyframe_ids = [k for k, ok in zip(keyframe_ids, close) if ok]
    truth = truth_at.world_from_camera[close]
    estimate = np.stack([result.keyframe_poses[k] for k in keyframe_ids])
    row_of = {k: i for i, k in enumerate(keyframe_ids)}
    pairs = revisits(times[[frame_of[k] for k in keyframe_ids]], truth, arguments.min_gap_s, arguments.revisit_m,
                     arguments.revisit_deg)
    revisits_of = collections.defaultdict(list)
    for later, earlier in pairs:
        revisits_of[keyframe_ids[later]].append(keyframe_ids[earlier])

    def ground_truth_gap(query, candidate) -> dict:
        """How far the ground truth puts a returned keyframe from the query (None: one of them has no pose)."""
        if query.keyframe_id not in row_of or candidate.keyframe_id not in row_of:
            return {"gt_distance_m": None, "gt_angle_deg": None}
        gap = pose_gap(truth[row_of[query.keyframe_id]], truth[row_of[candidate.keyframe_id]])
        return {"gt_distance_m": gap[0], "gt_angle_deg": gap[1]}

    rows, totals, revisit_totals, drifts = [], collections.Counter(), collections.Counter(), []
    for query in queries:
        outcome_of = {c.keyframe_id: c for c in query.candidates}
        counts = collections.Counter(str(c.outcome) for c in query.candidates)
        totals.update(counts)
        true = []
        for earlier in revisits_of.get(query.keyframe_id, []):
            candidate = outcome_of.get(earlier)
            outcome = MISSED if candidate is None else str(candidate.outcome)
            drift = (relative_drift_m(estimate, truth, row_of[query.keyframe_id], row_of[earlier])
                     if query.keyframe_id in row_of else None)
            revisit_totals[outcome] += 1
            if drift is not None:
                drifts.append(drift)
            rank = None if candidate is None else [c.keyframe_id for c in query.candidates].index(earlier) + 1
            true.append({"keyframe_id": earlier, "frame_index": frame_of[earlier], "outcome": outcome, "rank": rank,
                         "score": None if candidate is None else candidate.score,
                         "inliers": None if candidate is None else candidate.inliers, "drift_m": drift})
        rows.append({"keyframe_id": query.keyframe_id, "frame_index": query.frame_index,
                     "time_s": float(times[query.frame_index] - times[0]), "min_score": query.min_score,
                     "returned": len(query.candidates), "outcomes": dict(counts), "revisits": true,
                     "candidates": [dataclasses.asdict(c) | {"outcome": str(c.outcome)} | ground_truth_gap(query, c)
                                    for c in query.candidates if c.outcome != LoopOutcome.covisible]})
        # One line per query: what the database returned and what became of it; the revisits' fate.
        fate = collections.Counter(t["outcome"] for t in true)
        print(f"keyframe {query.keyframe_id:3d} (frame {query.frame_index:3d}, {rows[-1]['time_s']:5.1f} s): "
              f"{len(query.candidates):3d} returned ({', '.join(f'{k} {v}' for k, v in sorted(counts.items()))}); "
              f"{len(true)} revisits ({', '.join(f'{k} {v}' for k, v in sorted(fate.items())) or '-'})")
    summary = {
        "sequence": folder.name, "frames": len(sequence), "keyframes": len(result.keyframe_poses),
        "loop_queries": len(queries), "loops_closed": result.loops_closed, "ate_cm": 100 * errors.ate_rmse_m,
        "tracking_s": seconds, "returned_outcomes": dict(totals), "revisit_pairs": len(pairs),
        "revisit_outcomes": dict(revisit_totals),
        "revisit_drift_cm_median": 100 * float(np.median(drifts)) if drifts else None,
        "revisit_drift_cm_max": 100 * float(np.max(drifts)) if drifts else None,
    }
    # The nearest (ground truth) of the keyframes that passed the covisibility exclusion, per outcome.
    nearest = collections.defaultdict(lambda: None)
    for row in rows:
        for candidate in row["candidates"]:
            distance = candidate["gt_distance_m"]
            if distance is not None and (nearest[candidate["outcome"]] is None or distance < nearest[candidate["outcome"]]):
                nearest[candidate["outcome"]] = distance
    summary["nearest_non_covisible_m"] = dict(nearest)
    print(json.dumps(summary, indent=1))
    report = {"date": datetime.datetime.now().isoformat(timespec="seconds"),
              "machine": describe_machine(),
              "command": " ".join(["python", "benchmarks/loops.py", *sys.argv[1:]]),
              "revisit": {"min_gap_s": arguments.min_gap_s, "within_m": arguments.revisit_m,
                          "within_deg": arguments.revisit_deg},
              "loop_settings": {k: getattr(config.frontend.orb, k) for k in (
                  "loop_min_score_ratio", "loop_consistency", "loop_candidates", "loop_min_inliers",
                  "loop_cooldown_keyframes")},
              "summary": summary, "queries": rows}
    atomic_write_text(arguments.output, json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
