"""The Fusion Bridge on against off: what each view-selection rule did, the rendering gain overall and on the
sharper half of the frames, the bridge's share of the run's time, and the mapping views' ATE before and after the
pose refinement.

    python benchmarks/bridge.py                                  # blurred synthetic, fr1/xyz 300, 7-Scenes 300
    python benchmarks/bridge.py --sequences synthetic --refine   # also a run with bridge.refine_poses=true
    python benchmarks/bridge.py --sequences synthetic --synthetic DIR --oracle   # an existing sequence; + oracle case
    python benchmarks/bridge.py --sequences fr1_xyz --set-all seed=1 --name seed1   # a repeat at another seed

Every case is one in-process ``reconstruct`` (default preset plus ``--set`` overrides) under
benchmarks/results/runs/bridge/. Renders are scored as the run's evaluation renders them (full resolution, the
rendering poses, the views' exposures), on the frames 0, 5, 10, ... that no case of the sequence mapped (the same
frames for on and off), against the sharp ground truth ``gt_rgb/`` where the sequence has it and against the input
frames otherwise, both through the views' exposures (``psnr_db``) and as exported (``psnr_db_exported``: the
map's own colours, what splats.ply shows); "sharper half": those of the frames whose input is at least as sharp as
their median (:func:`tambridge.images.sharpness`). ``--oracle`` (synthetic only) adds a case whose blur-aware
mapping takes each view's motion over the exposure from the synthetic's true path instead of the tracked poses:
what exact blur modelling wins. The synthetic sequence is 120 frames at 320x240 with a 1/30 s exposure of
physical motion blur and two bursts of fast rotation. Results of the sequences run are merged into
benchmarks/results/bridge.json.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import pipelines.reconstruct as reconstruct_module  # noqa: E402
from benchmarks.machine import describe_machine  # noqa: E402
from benchmarks.reconstruct import SYNTHETIC_SETTINGS  # noqa: E402
from benchmarks.sequences import camera_file_for  # noqa: E402
from tambridge.bridge.view_selection import SHARPER_FRAME  # noqa: E402
from tambridge.config import load_config  # noqa: E402
from tambridge.evaluation.rendering import psnr_db  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402
from tambridge.images import sharpness  # noqa: E402
from tambridge.bridge.blur import ExposurePath  # noqa: E402
from tambridge.geometry import inverse  # noqa: E402
from tambridge.io.synthetic import RotationBursts, SynthOptions, write_synthetic_sequence  # noqa: E402
from tambridge.mapping.stage import MappingStage  # noqa: E402
from tambridge.run_folder import Start  # noqa: E402

RUNS = ROOT / "benchmarks" / "results" / "runs" / "bridge"
RESULTS = ROOT / "benchmarks" / "results" / "bridge.json"
SYNTHETIC = SynthOptions(frame_count=120, width=320, height=240, seed=0, exposure_s=0.0333, bursts=RotationBursts(count=2))
ORACLE_SAMPLES = 33
"""Poses of the true path per exposure that the oracle's exposure path interpolates between."""
SEQUENCES = {
    "synthetic": (RUNS / "synthetic_blur_120", SYNTHETIC_SETTINGS + ["--set", "mapper.resolution_scale=0.5"], None),
    "fr1_xyz": (Path("/work/data/rgbd_dataset_freiburg1_xyz"), [], 300),
    "7scenes": (Path("/work/shared/data/7scenes_redkitchen_0-699"), [], 300),
}
EVERY = 5
CASES = {"off": ["bridge.enabled=false"], "on": []}


def settings_of(words: list[str]) -> list[str]:
    """``["--set", "k=v", ...]`` -> ``["k=v", ...]``."""
    return [word for word in words if word != "--set"]


class Capture:
    """Wraps the pipeline's ``evaluate_run`` to render every ``EVERY``-th frame from the finished map (PSNR per
    frame) before the run's own evaluation."""

    def __init__(self, targets: dict[int, np.ndarray]):
        self.targets = targets
        self.original = reconstruct_module.evaluate_run
        self.psnr_db: dict[int, float] = {}
        self.psnr_db_exported: dict[int, float] = {}
        self.view_frames: list[int] = []

    def __call__(self, sequence, config, tracking, mapping, *args, **kwargs):
        if mapping is not None:
            poses = mapping.rendering_poses(tracking.trajectory)
            camera = sequence.camera
            top, bottom, left, right = sequence.valid_region
            self.view_frames = sorted(view.frame_index for view in mapping.views)
            with mapping.threads():
                for index, target in self.targets.items():
                    rendered = mapping.map.render(camera, poses[index]).rgb
                    exposure = mapping.anchor_view(index).exposure if mapping.views else None
                    for scores, image in ((self.psnr_db, rendered if exposure is None else exposure.apply(rendered)),
                                          (self.psnr_db_exported, rendered)):
                        image = image.detach().clamp(0.0, 1.0).cpu().numpy()[top:bottom, left:right]
                        scores[index] = psnr_db(image, target[top:bottom, left:right])
        return self.original(sequence, config, tracking, mapping, *args, **kwargs)


class TruePaths:
    """Replaces :meth:`MappingStage.exposure_path_of` while a case runs: each view's exposure path from the
    synthetic sequence's true camera path (``options``), relative to its true pose at the frame, instead of from
    the tracked neighbours."""

    def __init__(self, options: SynthOptions):
        self.options = options
        self.original = MappingStage.exposure_path_of

    def __enter__(self):
        options = self.options

        def true_path(stage: MappingStage, frame_index: int, world_from_frame):
            if not stage.blur_exposure_s:
                return None
            offsets_s = np.linspace(-0.5, 0.5, ORACLE_SAMPLES) * stage.blur_exposure_s
            poses = options.path.poses(np.concatenate([[frame_index], frame_index + offsets_s * options.fps]))
            return ExposurePath(offsets_s, np.stack([inverse(poses[0]) @ pose for pose in poses[1:]]),
                                stage.blur_exposure_s)

        MappingStage.exposure_path_of = true_path
        return self

    def __exit__(self, *exc):
        MappingStage.exposure_path_of = self.original


def targets_of(folder: Path, config) -> tuple[dict[int, np.ndarray], dict[int, float], bool]:
    """Every ``EVERY``-th frame's scoring target ((H, W, 3) in [0, 1]: ``gt_rgb/`` where present, else the input),
    its input's sharpness, and whether ground-truth images were used."""
    sequence = reconstruct_module.open_sequence(
        folder, camera_file=None if config.input.camera_file is None else Path(config.input.camera_file),
        max_frames=config.input.max_frames)
    targets, scores = {}, {}
    has_gt = (folder / "gt_rgb").is_dir()
    for index in range(0, len(sequence), EVERY):
        frame = sequence[index]
        scores[index] = sharpness(frame.rgb)
        rgb = frame.rgb
        if has_gt:
            gt = cv2.imread(str(folder / "gt_rgb" / sequence.rgb_paths[index].name), cv2.IMREAD_COLOR)
            rgb = cv2.cvtColor(gt, cv2.COLOR_BGR2RGB)
        targets[index] = rgb.astype(np.float32) / 255.0
    return targets, scores, has_gt


def run_case(name: str, folder: Path, settings: list[str], max_frames: int | None, camera: Path | None,
             targets: dict[int, np.ndarray], true_paths: SynthOptions | None = None) -> dict:
    overrides = list(settings)
    if max_frames:
        overrides.append(f"input.max_frames={max_frames}")
    if camera is not None:
        overrides.append(f"input.camera_file={camera}")
    config = load_config(ROOT / "configs" / "default.yaml", overrides)
    capture = Capture(targets)
    reconstruct_module.evaluate_run = capture
    try:
        with TruePaths(true_paths) if true_paths is not None else contextlib.nullcontext():
            result = reconstruct_module.reconstruct(folder, RUNS / name, config, progress=False, start=Start.OVERWRITE)
    finally:
        reconstruct_module.evaluate_run = capture.original
    metrics = json.loads((RUNS / name / "metrics.json").read_text())
    stages = metrics["seconds_per_stage"]
    bridge = metrics["bridge"]
    return {
        "settings": overrides,
        "psnr_db": {str(index): value for index, value in capture.psnr_db.items()},
        "psnr_db_exported": {str(index): value for index, value in capture.psnr_db_exported.items()},
        "view_frames": capture.view_frames,
        "view_selection": bridge["view_selection"],
        "views_ate_rmse_m": bridge.get("views_ate_rmse_m"),
        "ate_rmse_m": (metrics.get("trajectory") or {}).get("ate_rmse_m"),
        "novel_psnr_db_as_run": metrics["rendering"]["novel_views"]["psnr_db"],
        "bridge_s": stages.get("bridge", 0.0),
        "seconds_total": metrics["seconds_total"],
        "bridge_share": stages.get("bridge", 0.0) / result.metrics.seconds_total,
        "frames_per_s": metrics.get("fps_end_to_end"),
        "blur": {key: bridge.get(key) for key in ("blur_exposure_s", "blurred_views", "mean_subposes_blurred")},
    }


def summarise(cases: dict[str, dict], sharpness_by_frame: dict[int, float]) -> dict:
    """Gains on the frames no case mapped, overall and on the sharper half of them."""
    mapped = set().union(*(case["view_frames"] for case in cases.values()))
    frames = [index for index in sharpness_by_frame if index not in mapped]
    median = float(np.median([sharpness_by_frame[index] for index in frames]))
    sharper = [index for index in frames if sharpness_by_frame[index] >= median]
    summary = {"frames_scored": len(frames), "sharper_half": len(sharper)}
    for name, case in cases.items():
        summary[name] = {}
        for key in ("psnr_db", "psnr_db_exported"):
            if key not in case:  # a case from before the as-exported scores
                continue
            scores = {int(index): value for index, value in case[key].items()}
            summary[name][key] = float(np.mean([scores[i] for i in frames]))
            summary[name][key + "_sharper_half"] = float(np.mean([scores[i] for i in sharper]))
    for name in cases:
        for suffix in ("", "_exported"):
            key = "psnr_db" + suffix
            if name != "off" and "off" in summary and key in summary[name] and key in summary["off"]:
                summary[f"gain_db{suffix}_{name}"] = summary[name][key] - summary["off"][key]
                summary[f"gain_db{suffix}_{name}_sharper_half"] = (summary[name][key + "_sharper_half"]
                                                                   - summary["off"][key + "_sharper_half"])
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequences", default=",".join(SEQUENCES), help="comma-separated: " + ", ".join(SEQUENCES))
    parser.add_argument("--max-frames", type=int, default=None, help="instead of each sequence's own count")
    parser.add_argument("--refine", action="store_true", help="add a case with bridge.refine_poses=true")
    parser.add_argument("--set", action="append", default=[], help="a config override for every case but off")
    parser.add_argument("--set-all", action="append", default=[],
                        help="a config override for every case, off included (a repeat at another seed: seed=1)")
    parser.add_argument("--reuse-off", action="store_true", help="take the off case from bridge.json instead of running it")
    parser.add_argument("--name", default="", help="store the sequence's results under KEY_NAME (a variant)")
    parser.add_argument("--synthetic", type=Path, default=None,
                        help="an existing synthetic sequence written with SYNTHETIC's options (instead of writing one)")
    parser.add_argument("--oracle", action="store_true",
                        help="synthetic: add a case whose exposure paths come from the true camera path")
    parser.add_argument("--cases", default=None, help="comma-separated subset of the cases to run (default: all)")
    parser.add_argument("--label", default=None,
                        help="with one case in --cases: store it under this name beside the entry's other cases (a "
                             "variant of it, with --set, scored against the same off case)")
    args = parser.parse_args()
    if args.reuse_off and args.set_all:
        parser.error("--reuse-off takes the off case run without --set-all's overrides; run it again instead")
    if args.label and (not args.cases or "," in args.cases):
        parser.error("--label needs exactly one case in --cases")
    results = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {"sequences": {}}
    cases_to_run = dict(CASES) | ({"refine": ["bridge.refine_poses=true"]} if args.refine else {}) \
        | ({"oracle": []} if args.oracle else {})
    for key in args.sequences.split(","):
        folder, sequence_settings, max_frames = SEQUENCES[key]
        if key == "synthetic" and args.synthetic is not None:
            folder = args.synthetic
        if key == "synthetic" and not (folder / "rgb.txt").is_file():
            write_synthetic_sequence(folder, SYNTHETIC)
        max_frames = args.max_frames or max_frames
        camera = camera_file_for(folder)
        config = load_config(ROOT / "configs" / "default.yaml",
                             ([f"input.max_frames={max_frames}"] if max_frames else [])
                             + ([f"input.camera_file={camera}"] if camera else []))
        targets, sharpness_by_frame, has_gt = targets_of(folder, config)
        result_key = key + (f"_{args.name}" if args.name else "")
        cases = {}
        for name, case_settings in cases_to_run.items():
            if name == "off" and args.reuse_off:
                cases[name] = results["sequences"][key]["cases"]["off"]
                continue
            if args.cases and name not in args.cases.split(","):
                continue
            stored = args.label or name
            print(f"{key}: bridge {stored}", flush=True)
            cases[stored] = run_case(f"{result_key}_{stored}", folder,
                                   settings_of(sequence_settings) + args.set_all + case_settings
                                   + (args.set if name != "off" else []),
                                   max_frames, camera, targets, SYNTHETIC if name == "oracle" else None)
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
        # Read again: another run of this benchmark may have written meanwhile. Cases not run this time keep the
        # entry's results.
        results = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {"sequences": {}}
        cases = results["sequences"].get(result_key, {}).get("cases", {}) | cases
        results["sequences"][result_key] = {"folder": str(folder), "max_frames": max_frames, "commit": commit,
                                            "scored_against": "gt_rgb" if has_gt else "inputs",
                                            "cases": cases, "summary": summarise(cases, sharpness_by_frame)}
        results["date"] = datetime.date.today().isoformat()
        results["machine"] = describe_machine()
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(RESULTS, json.dumps(results, indent=1) + "\n")
    print_table(results)


def print_table(results: dict) -> None:
    print(f"{'sequence':<10} {'against':<7} {'case':<7} {'selected':>8} {'sharper':>7} {'too sim':>7} {'few':>4} "
          f"{'blurred':>7} {'uncov':>5} {'PSNR':>6} {'gain':>6} {'sharp½':>6} {'gain½':>6} {'exp':>6} {'gain':>6} "
          f"{'exp½':>6} {'gain½':>6} {'bridge%':>7} {'fps':>5} {'K>1':>4} {'ATE views before/after (cm)':>27}")
    for key, entry in results["sequences"].items():
        summary = entry["summary"]
        for name, case in entry["cases"].items():
            selection = case["view_selection"]
            ate = case["views_ate_rmse_m"]
            ate_text = f"{100 * ate['frontend']:.2f} / {100 * ate['rendering']:.2f}" if ate else "-"
            gain = summary.get(f"gain_db_{name}")
            gain_half = summary.get(f"gain_db_{name}_sharper_half")
            exported = [summary[name].get(key) for key in ("psnr_db_exported", "psnr_db_exported_sharper_half")]
            exported_gains = [summary.get(f"gain_db_exported_{name}{half}") for half in ("", "_sharper_half")]
            extra = " ".join(f"{'' if value is None else format(value, form):>6}" for value, form in
                             zip([exported[0], exported_gains[0], exported[1], exported_gains[1]], [".2f", "+.2f"] * 2))
            fps = case.get("frames_per_s")
            blurred = (case.get("blur") or {}).get("blurred_views")
            print(f"{key:<10} {entry['scored_against']:<7} {name:<7} "
                  f"{selection.get('SELECTED', 0) + selection.get('NO_SPARSE_MAP', 0) + selection.get('BRIDGE_OFF', 0):>8} "
                  f"{selection.get(SHARPER_FRAME, 0):>7} {selection.get('TOO_SIMILAR', 0):>7} "
                  f"{selection.get('TOO_FEW_SHARED', 0):>4} {selection.get('TOO_BLURRED', 0):>7} "
                  f"{selection.get('UNCOVERED', 0):>5} {summary[name]['psnr_db']:>6.2f} "
                  f"{'' if gain is None else f'{gain:+.2f}':>6} {summary[name]['psnr_db_sharper_half']:>6.2f} "
                  f"{'' if gain_half is None else f'{gain_half:+.2f}':>6} {extra} {100 * case['bridge_share']:>6.1f}% "
                  f"{'' if fps is None else f'{fps:.2f}':>5} {'' if blurred is None else blurred:>4} {ate_text:>27}")


if __name__ == "__main__":
    main()
