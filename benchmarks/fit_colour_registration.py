"""Fit the colour camera of an unregistered RGB-D sensor to its depth camera, by edge alignment.

    python benchmarks/fit_colour_registration.py                  # 7-Scenes redkitchen, from 525 px and 2.56 cm
    python benchmarks/fit_colour_registration.py --every 35 --start-focal 525 --start-baseline -0.0256

How configs/cameras/7scenes_kinect.yaml's colour_* values were found. Every ``--every``-th frame is read raw; for
trial values of the colour camera's focal length (fx = fy), principal point and baseline (x translation of
colour_from_depth), colour is resampled into the depth camera and scored by the mean colour-gradient magnitude on
depth edges (higher when colour edges fall on depth edges); coordinate ascent, halving the steps each round.
The depth range of the frames is what separates the baseline from the principal point. On the synthetic room the
score does not single out the true values (its textures have strong edges everywhere, not mostly at depth edges),
so this is a tool for real scenes, checked by the scores it prints, not a tested calibration method.
Prints the fitted values and the score of the unregistered frames, the start and the fit; JSON to
benchmarks/results/fit_colour_registration.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tambridge.camera import Camera  # noqa: E402
from tambridge.io.registration import ColourToDepth  # noqa: E402
from tambridge.io.tum import open_sequence  # noqa: E402


def edge_alignment(colour_in_depth: np.ndarray, depth_m: np.ndarray, margin_px: int) -> float:
    """Mean colour-gradient magnitude (grey levels per pixel) on the depth image's edges: higher when colour edges
    fall on depth edges. ``colour_in_depth`` (H, W, 3) uint8 in the depth camera; ``margin_px`` of border ignored."""
    grey = cv2.GaussianBlur(cv2.cvtColor(colour_in_depth, cv2.COLOR_RGB2GRAY).astype(np.float32), (5, 5), 1.5)
    depth_mm = cv2.GaussianBlur(depth_m * 1000.0, (5, 5), 1.5)
    # Depth edges: a jump of over 3 cm per pixel (a surface boundary, not the slope of a wall), inside valid depth.
    edges = (np.hypot(*np.gradient(depth_mm)) > 30.0) & (depth_m > 0)
    edges[:margin_px], edges[-margin_px:], edges[:, :margin_px], edges[:, -margin_px:] = False, False, False, False
    if not edges.any():
        return 0.0
    return float(np.hypot(*np.gradient(grey))[edges].mean())


def fit_colour_to_depth(
    frames: list[tuple[np.ndarray, np.ndarray]], start: ColourToDepth, rounds: int = 5
) -> tuple[ColourToDepth, float]:
    """Refine a colour camera's focal length (fx = fy), principal point and baseline (x translation of
    ``colour_from_depth``) so that colour edges fall on depth edges, over ``frames`` of (colour (Hc, Wc, 3) uint8,
    depth (H, W) metres). Coordinate ascent on :func:`edge_alignment`, halving the steps each round (from 1 % of
    the focal length, 4 px and 8 mm). Returns the refined registration and its score; the rotation is kept (small
    rotations act like principal-point shifts). A calibration, not a substitute for one with a target: the depth
    range of the frames is what separates the baseline from the principal point.
    """
    margin = max(4, start.depth_camera.width // 32)

    def build(values: dict[str, float]) -> ColourToDepth:
        colour_from_depth = start.colour_from_depth.copy()
        colour_from_depth[0, 3] = values["baseline"]
        colour_camera = dataclasses.replace(
            start.colour_camera, fx=values["focal"], fy=values["focal"], cx=values["cx"], cy=values["cy"]
        )
        return ColourToDepth(start.depth_camera, colour_camera, colour_from_depth)

    def score(values: dict[str, float]) -> float:
        registration = build(values)
        return float(np.mean([
            edge_alignment(registration.colour_in_depth_camera(colour, depth_m), depth_m, margin)
            for colour, depth_m in frames
        ]))

    camera = start.colour_camera
    values = {"focal": camera.fx, "cx": camera.cx, "cy": camera.cy, "baseline": float(start.colour_from_depth[0, 3])}
    steps = {"focal": 0.01 * camera.fx, "cx": 4.0, "cy": 4.0, "baseline": 0.008}
    best = score(values)
    for _ in range(rounds):
        for key in values:
            for sign in (-1.0, 1.0):
                while True:
                    trial = dict(values, **{key: values[key] + sign * steps[key]})
                    trial_score = score(trial)
                    if trial_score <= best:
                        break
                    best, values = trial_score, trial
        steps = {key: step / 2 for key, step in steps.items()}
    return build(values), best



def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", type=Path, default=ROOT.parent / "shared" / "data" / "7scenes_redkitchen_0-699")
    parser.add_argument("--every", type=int, default=35, help="use every n-th frame")
    parser.add_argument("--start-focal", type=float, default=525.0)
    parser.add_argument("--start-baseline", type=float, default=-0.0256, help="x of colour_from_depth, metres")
    arguments = parser.parse_args()
    sequence = open_sequence(arguments.sequence)  # the folder's own camera: the depth camera, colour raw
    depth_camera = sequence.camera
    frames = [(sequence.read_rgb(sequence.rgb_paths[i]), sequence.read_depth_m(sequence.depth_paths[i]))
              for i in range(0, len(sequence), arguments.every)]
    colour_from_depth = np.eye(4)
    colour_from_depth[0, 3] = arguments.start_baseline
    start = ColourToDepth(depth_camera, dataclasses.replace(depth_camera, fx=arguments.start_focal,
                                                            fy=arguments.start_focal), colour_from_depth)
    margin = max(4, depth_camera.width // 32)
    unregistered = float(np.mean([edge_alignment(colour, depth_m, margin) for colour, depth_m in frames]))
    fitted, score = fit_colour_to_depth(frames, start)
    camera: Camera = fitted.colour_camera
    result = {
        "sequence": str(arguments.sequence), "frames": len(frames),
        "score_unregistered": unregistered,
        "score_start": float(np.mean([edge_alignment(start.colour_in_depth_camera(c, d), d, margin) for c, d in frames])),
        "score_fitted": score,
        "colour_fx": camera.fx, "colour_fy": camera.fy, "colour_cx": camera.cx, "colour_cy": camera.cy,
        "colour_from_depth": fitted.colour_from_depth.tolist(),
    }
    for key, value in result.items():
        print(f"{key:>20}: {value}")
    output = ROOT / "benchmarks" / "results" / "fit_colour_registration.json"
    output.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
