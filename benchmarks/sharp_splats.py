"""Sharp splats: the sharpening pass after tracking (``mapper.sharp_*``) on vs off, per sequence and preset.

    python benchmarks/sharp_splats.py                                   # 7-Scenes 0-299 and fr1/xyz 0-199, both presets
    python benchmarks/sharp_splats.py --cases 7scenes:default:700       # one case: sequence:preset:frames (0: all)
    python benchmarks/sharp_splats.py --fit 7scenes:300:0.25 --fit 7scenes:300:1.0   # upper bounds (below)
    python benchmarks/sharp_splats.py --cases 7scenes:default:700 --pass-variant "l1:mapper.sharp_w_colour_squared=0"

Every case is one ``reconstruct`` run in its own process (peak memory its own). On and off come from that same run:
the sharpening pass is the last step of the mapping stage and nothing before it depends on it, so the run keeps a
copy of the map and of the views' exposures as they are before the pass, and scores both maps at the same novel
views (every 5th frame that is not a mapping view). "off" seconds are the run's end-to-end seconds less those of
its ``sharpening`` stage, its frames/s the frames over those.

Scores, all renders at the camera's full resolution from the run's rendering poses:
- ``psnr``/``ssim``: the run's own (metrics.json: through each view's exposure, inside the valid region; "on":
  the exposures refitted to the final map, "off": as they were before the pass);
- ``psnr_exp``/``ssim_exp``: as exported: the map's own colours with no per-view exposure (what a viewer of
  splats.ply shows at those poses), inside the valid region;
- ``ssim_low``: the run's SSIM of the same renders and frames area-resized to the mapping resolution (what the map
  was optimised at): the gap to ``ssim`` is the detail lost between the resolutions.

``--fit`` is the upper bound of what the map representation and the data give, with tracking out of the picture:
the map built at ground-truth poses (7-Scenes: KinectFusion's, a pseudo ground truth) is fitted for many steps to
a handful of the views (sequence:frames:resolution_scale, the sharpening pass's resolution) and scored on those
views and on held-out frames between them; where the folder has lossless PNGs of some frames beside its JPEGs
(7-Scenes' rgb_png_lossless), the JPEGs' PSNR against them is the ceiling compression alone sets.

``--pass-variant NAME:SETTING[;SETTING...]`` (repeatable; each SETTING ``mapper.key=value``) runs the pass again
on the same map before it, once per variant with those settings, after the run: the same trajectory, the same map
and the same random order of the views and frames, so the variants and the run's own pass differ by their settings
alone; each is pruned and its exposures refitted as ``finish`` does, and scored like "on" (``variants``: the
run's PSNR/SSIM through exposures, as exported, the error shares, the pass's seconds and Gaussians).

``--ceiling ROUNDS[:DENSIFY]`` adds an oracle to each case: after the run, its final map is fitted to the scored
novel views themselves (the test frames: no run can do this), with no exposure, at full resolution, ROUNDS Adam
steps per view in a new random order each round (first densified on the worst DENSIFY share of each view's pixels,
colour error over 0.05, as the sharpening pass densifies), and scored again as exported (``ceiling``). What a single
static map of these Gaussians, at these poses, can show at those frames when it is fitted to them: where it stays
under a target, no schedule, number of views or step count can reach that target; what separates it from the target
is then the views' disagreement (poses, exposure, colour registration) and the representation, not the mapping.

``--limits`` adds two more oracles at the scored frames, on the run's final map as exported, each scored as
``psnr_exp`` is (and where the ceiling's gap to the run comes from):
- ``psnr_affine``: every render mapped by the gain and bias per channel that fit that frame best (least squares
  against the frame itself): what the frames' own exposures (auto exposure, per frame) cost a map of fixed colours,
  which is all a .ply holds;
- ``psnr_pose``: every frame's pose first refined against the map by the bridge's refinement
  (:func:`tambridge.bridge.refinement.refine_render_pose`) with its colour term alone, at the mapping resolution:
  what the frames' tracked poses cost; ``pose_moved_mm`` the median move.

Prints a table and writes benchmarks/results/sharp_splats.json.
"""

from __future__ import annotations

import argparse
import copy
import datetime
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe_machine  # noqa: E402
from benchmarks.sequences import camera_file_for  # noqa: E402
from tambridge.files import atomic_write_text  # noqa: E402

SEQUENCES = {
    "7scenes": ROOT.parent / "shared" / "data" / "7scenes_redkitchen_0-699",
    "fr1xyz": ROOT.parent / "data" / "rgbd_dataset_freiburg1_xyz",
}
CASES = ("7scenes:default:300", "7scenes:quality:300", "fr1xyz:default:200", "fr1xyz:quality:200")
RESULTS = ROOT / "benchmarks" / "results"


def as_exported_scores(mapping, poses: np.ndarray, frames: list[int]) -> dict:
    """PSNR/SSIM of the map rendered with no exposure at full resolution, and the run's SSIM at the mapping
    resolution (renders through the exposures, area-resized as the mapper resizes frames); inside the valid region.
    ``error_shares``: where the squared error as exported lies, summed over the frames, by the map's silhouette
    (``covered`` at least 0.95, ``uncovered`` at most 0.05, ``partial`` between) and by the frame's depth
    (``unmeasured``: pixels without); ``pixel_shares`` the same classes' share of the pixels."""
    import cv2
    import torch

    from tambridge.evaluation.exported import COVERED_SILHOUETTE
    from tambridge.evaluation.rendering import psnr_db, ssim_value

    camera = mapping.sequence.camera
    top, bottom, left, right = mapping.sequence.valid_region
    size = (mapping.camera.width, mapping.camera.height)
    psnr, ssim, ssim_low = [], [], []
    errors = {"covered": 0.0, "partial": 0.0, "uncovered": 0.0, "unmeasured": 0.0, "all": 0.0}
    pixels = dict.fromkeys(errors, 0)
    with mapping.threads():
        for index in frames:
            output = mapping.map.render(camera, poses[index])
            rendered = output.rgb
            frame = mapping.sequence[index]
            observed = frame.rgb[top:bottom, left:right].astype(np.float32) / 255.0
            own = rendered.clamp(0.0, 1.0).cpu().numpy()[top:bottom, left:right]
            psnr.append(psnr_db(own, observed))
            ssim.append(ssim_value(own, observed))
            squared_error = ((own.astype(np.float64) - observed) ** 2).mean(axis=2)
            silhouette = output.silhouette.cpu().numpy()[top:bottom, left:right]
            classes = {"covered": silhouette >= COVERED_SILHOUETTE, "uncovered": silhouette <= 1 - COVERED_SILHOUETTE,
                       "unmeasured": frame.depth_m[top:bottom, left:right] <= 0, "all": np.ones_like(silhouette, bool)}
            classes["partial"] = ~classes["covered"] & ~classes["uncovered"]
            for name, mask in classes.items():
                errors[name] += float(squared_error[mask].sum())
                pixels[name] += int(mask.sum())
            exposure = mapping.anchor_view(index).exposure
            with torch.no_grad():
                compensated = (rendered if exposure is None else exposure.apply(rendered)).clamp(0.0, 1.0).cpu().numpy()[top:bottom, left:right]
            low = [cv2.resize(np.ascontiguousarray(image), size, interpolation=cv2.INTER_AREA)
                   for image in (compensated, observed)]
            ssim_low.append(ssim_value(*low))
    return {"psnr_exp": float(np.mean(psnr)), "ssim_exp": float(np.mean(ssim)), "ssim_low": float(np.mean(ssim_low)),
            "error_shares": {name: errors[name] / max(errors["all"], 1e-12) for name in errors if name != "all"},
            "pixel_shares": {name: pixels[name] / max(pixels["all"], 1) for name in pixels if name != "all"}}


def limit_scores(mapping, poses: np.ndarray, frames: list[int], pose_iterations: int = 10) -> dict:
    """The oracles of ``--limits`` at ``frames`` (their rendering ``poses``) on ``mapping.map`` as it is: mean PSNR
    as exported with the best affine colour of each frame (``psnr_affine``) and at poses refined against the map
    by colour alone (``psnr_pose``, ``pose_moved_mm``); with the plain ``psnr_exp`` they are compared with."""
    import dataclasses

    import torch

    from tambridge.bridge.refinement import refine_render_pose
    from tambridge.evaluation.rendering import psnr_db
    from tambridge.gaussians.mapper import affine_colour_fit
    from tambridge.mapping.stage import resize_frame

    camera = mapping.sequence.camera
    top, bottom, left, right = mapping.sequence.valid_region
    bridge = dataclasses.replace(mapping.bridge_config, w_reprojection=0.0, w_depth=0.0, w_colour=1.0,
                                 iterations=pose_iterations)
    with torch.no_grad():
        gaussians = mapping.map.gaussians()
    plain, affine, refined, moved = [], [], [], []

    def cropped_render(pose) -> np.ndarray:
        with torch.no_grad():
            return mapping.map.render(camera, pose).rgb.clamp(0.0, 1.0).cpu().numpy()[top:bottom, left:right]

    with mapping.threads():
        for index in frames:
            frame = mapping.sequence[index]
            observed = frame.rgb[top:bottom, left:right].astype(np.float32) / 255.0
            rendered = cropped_render(poses[index])
            plain.append(psnr_db(rendered, observed))
            gain, bias = affine_colour_fit(torch.from_numpy(rendered.reshape(-1, 3)), torch.from_numpy(observed.reshape(-1, 3)))
            fitted = np.clip(rendered * gain.numpy() + bias.numpy(), 0.0, 1.0).astype(rendered.dtype)
            affine.append(psnr_db(fitted, observed))
            low = resize_frame(frame, mapping.mapper_config.resolution_scale, mapping.device)
            refinement = refine_render_pose(gaussians, mapping.camera, poses[index], low.rgb, low.depth_m,
                                            np.zeros((0, 3)), np.zeros((0, 2)), bridge,
                                            backend=mapping.mapper_config.backend)
            refined.append(psnr_db(cropped_render(refinement.world_from_camera), observed))
            moved.append(1e3 * float(np.linalg.norm(refinement.world_from_camera[:3, 3] - poses[index][:3, 3])))
    return {"psnr_exp": float(np.mean(plain)), "psnr_affine": float(np.mean(affine)), "psnr_pose": float(np.mean(refined)),
            "pose_moved_mm": float(np.median(moved)), "pose_iterations": pose_iterations}


# Anchor ids of the ceiling's Gaussians, one per scored frame, above any keyframe id of a run.
CEILING_ANCHOR_BASE = 10**7


def ceiling_scores(mapping, poses: np.ndarray, frames: list[int], rounds: int, densify: float) -> dict:
    """The oracle of ``--ceiling``: ``mapping.map`` fitted to ``frames`` (their rendering ``poses``) with no
    exposure, ``rounds`` steps per frame at full resolution after densifying the worst ``densify`` share of each
    frame's pixels; then :func:`as_exported_scores` at the same frames, with the Gaussians added and the seconds."""
    from tambridge.mapping.stage import resize_frame, shuffled_chunks

    camera = mapping.sequence.camera
    rng = np.random.default_rng(0)

    def chunk_views(chunk):
        return [(poses[index], resize_frame(mapping.sequence[index], 1.0, mapping.device, mapping.sequence.valid_region))
                for index in chunk]

    started, before = time.perf_counter(), len(mapping.map)
    with mapping.threads():
        if densify > 0:
            for index in frames:
                (pose, images), = chunk_views([index])
                anchor_id = CEILING_ANCHOR_BASE + index
                mapping.map.set_anchor_pose(anchor_id, pose)
                mapping.map.densify_colour_error(anchor_id, camera, images, None, 0.05, densify)
        for _ in range(rounds):
            # A new order every round: in a fixed one the map follows the exposure of the frames it saw last (7-Scenes'
            # last frames are the brightest), and the fit scores under the map it started from.
            for chunk in shuffled_chunks(frames, mapping.mapper_config.window_size, rng):
                mapping.map.optimise(camera, chunk_views(chunk), list(range(len(chunk))))
    scores = as_exported_scores(mapping, poses, frames)
    return {"psnr_exp": scores["psnr_exp"], "ssim_exp": scores["ssim_exp"], "rounds": rounds, "densify": densify,
            "gaussians_added": len(mapping.map) - before, "gaussians": len(mapping.map),
            "seconds": time.perf_counter() - started}


def child_case(sequence: Path, preset: str, frames: int, out: Path, extra: list[str],
               ceiling: tuple[int, float] | None = None, limits: bool = False,
               pass_variants: list[tuple[str, list[str]]] = ()) -> dict:
    """One run in this process, the map before the sharpening pass kept for the "off" scores; with ``ceiling``
    (rounds, densify share), :func:`ceiling_scores` of the final map too; with ``limits``, :func:`limit_scores`;
    each of ``pass_variants`` (name, mapper settings) a pass again from that map (:func:`variant_scores`)."""
    import pipelines.reconstruct as pipeline
    from tambridge.config import load_config
    from tambridge.evaluation.mapping import evaluation_frames, score_views
    from tambridge.mapping.stage import MappingStage
    from tambridge.run_folder import Start

    overrides = list(extra)
    if frames:
        overrides.append(f"input.max_frames={frames}")
    camera_file = camera_file_for(sequence)
    if camera_file is not None:
        overrides.append(f"input.camera_file={camera_file}")
    config = load_config(ROOT / "configs" / f"{preset}.yaml", overrides + ["mesh.enabled=false"])
    # Each variant's settings are checked here, before the run.
    variant_configs = {name: load_config(ROOT / "configs" / f"{preset}.yaml",
                                         overrides + ["mesh.enabled=false"] + settings).mapper
                       for name, settings in pass_variants}
    before: dict = {}
    rows: dict = {}
    sharpen = MappingStage.sharpen

    def keeping_the_map(stage: MappingStage, frames_between=()) -> None:
        before["stage"] = copy.deepcopy(stage.state_dict())
        before["frames_between"] = list(frames_between)
        sharpen(stage, frames_between)

    mapping_metrics = pipeline.mapping_metrics

    def scoring_both(mapping, tracking, sequence, evaluation, run_log, exported):
        metrics = mapping_metrics(mapping, tracking, sequence, evaluation, run_log, exported)
        poses = mapping.rendering_poses(tracking.trajectory)
        novel = evaluation_frames(len(sequence), evaluation.novel_view_every, {v.frame_index for v in mapping.views})
        on = {"psnr": metrics.rendering.novel_views.psnr_db, "ssim": metrics.rendering.novel_views.ssim,
              "gaussians": len(mapping.map)}
        rows["on"] = on | as_exported_scores(mapping, poses, novel)
        if limits:
            rows["limits"] = limit_scores(mapping, poses, novel)
        final_map = copy.deepcopy(mapping.map.state_dict()) if ceiling else None
        if variant_configs:
            rows["variants"] = {name: variant_scores(mapping, before, mapper_config, poses, novel)
                                for name, mapper_config in variant_configs.items()}
        if before:
            restore_before_the_pass(mapping, before)
            # As a run without the pass: the final refinement's prune follows the pass.
            mapping.final_prune()
            scores = score_views(mapping, poses, novel).summary()
            off = {"psnr": scores["psnr_db"], "ssim": scores["ssim"], "gaussians": len(mapping.map)}
            rows["off"] = off | as_exported_scores(mapping, poses, novel)
        if ceiling:
            mapping.map.load_state_dict(final_map)
            rows["ceiling"] = ceiling_scores(mapping, poses, novel, *ceiling)
        return metrics

    MappingStage.sharpen = keeping_the_map
    pipeline.mapping_metrics = scoring_both
    started = time.perf_counter()
    result = pipeline.reconstruct(sequence, out, config, progress=False, start=Start.OVERWRITE)
    wall = time.perf_counter() - started
    metrics = result.metrics
    sharpening_s = metrics.seconds_per_stage.get("sharpening", 0.0)
    rows["on"].update(seconds=metrics.seconds_total, fps=metrics.fps_end_to_end)
    if "off" in rows:
        rows["off"].update(seconds=metrics.seconds_total - sharpening_s,
                           fps=metrics.frames / (metrics.seconds_total - sharpening_s))
    return {"sequence": sequence.name, "preset": preset, "frames": metrics.frames, "mapping_views": len(before["stage"]["views"]) if before else None,
            "frames_between": len(before["frames_between"]) if before else None,
            "wall_seconds_process": wall, "sharpening_seconds": sharpening_s,
            "seconds_per_stage": metrics.seconds_per_stage, "peak_memory_mb": metrics.peak_memory_mb,
            "ate_cm": None if metrics.trajectory is None else metrics.trajectory.ate_rmse_m * 100, "extra": extra, **rows}


def restore_before_the_pass(mapping, before: dict) -> None:
    """The stage as it was when the pass began (its map, the views' exposures, the random generator): its own
    checkpoint state, kept then."""
    mapping.load_state_dict(copy.deepcopy(before["stage"]))


def variant_scores(mapping, before: dict, mapper_config, poses: np.ndarray, frames: list[int]) -> dict:
    """The end of ``MappingStage.finish`` (the sharpening pass, the prune, the map's colours) again from the map
    ``before`` the pass, with ``mapper_config``; scored through the exposures and as exported. The stage keeps its
    own config afterwards (its map is the variant's)."""
    from tambridge.evaluation.mapping import score_views

    own = mapping.mapper_config
    restore_before_the_pass(mapping, before)
    mapping.mapper_config = mapping.map.config = mapper_config
    started = time.perf_counter()
    mapping.sharpen_prune_and_set_colours(before["frames_between"])
    seconds = time.perf_counter() - started
    mapping.mapper_config = mapping.map.config = own
    scores = score_views(mapping, poses, frames).summary()
    return {"psnr": scores["psnr_db"], "ssim": scores["ssim"], "gaussians": len(mapping.map), "pass_seconds": seconds,
            } | as_exported_scores(mapping, poses, frames)


def fit_bound(sequence: Path, frames: int, scale: float, densify: float = 0.0, views: int = 4, steps: int = 60) -> dict:
    """A map of ``views`` frames spread over the first 60, mapped online at ground-truth poses (bridge off), then
    ``steps`` sharpening steps per view at ``scale``, first densified on the worst ``densify`` share of each view's
    pixels (colour error over 0.05); scores on those views and on the frames half-way between."""
    import dataclasses

    import cv2

    from tambridge.bridge.config import BridgeConfig
    from tambridge.config import load_config
    from tambridge.evaluation.mapping import score_views
    from tambridge.frontend.contract import KeyframeEvent
    from tambridge.io.tum import open_sequence
    from tambridge.mapping.stage import MappingStage
    from tambridge.runlog import RunLog

    config = load_config(ROOT / "configs" / "default.yaml")
    camera_file = camera_file_for(sequence)
    data = open_sequence(sequence, camera_file=camera_file, max_frames=frames or None)
    truth = data.ground_truth.nearest(data.timestamps_s).world_from_camera
    chosen = [int(i) for i in np.linspace(0, min(len(data), 60) - 1, views).round()]
    held_out = sorted({(a + b) // 2 for a, b in zip(chosen, chosen[1:])})
    mapper = dataclasses.replace(config.mapper, sharp_iterations_per_view=steps, sharp_resolution_scale=scale,
                                 window_size=views, sharp_densify_error=0.05 if densify else 0.0,
                                 sharp_densify_fraction=densify)
    run_log = RunLog(RESULTS / "runs" / "sharp_splats_fit.log")
    stage = MappingStage(data, mapper, BridgeConfig(enabled=False), run_log, seed=config.seed)
    poses = {}
    started = time.perf_counter()
    for keyframe_id, index in enumerate(chosen):
        poses[keyframe_id] = truth[index]
        event = KeyframeEvent(keyframe_id, index, 0.0, truth[index], np.zeros((0, 3)), np.zeros((0, 2)),
                              np.zeros(0, np.int64), 0, 0)
        stage.on_keyframe(event, data[index], dict(poses))
    stage.finish(poses)
    seconds = time.perf_counter() - started
    fitted, between = score_views(stage, truth, chosen).summary(), score_views(stage, truth, held_out).summary()
    # 7-Scenes ships its colour as JPEG, with a lossless PNG of some frames beside it: how far compression alone
    # lies from the recorded image.
    lossless = sorted((sequence / "rgb_png_lossless").glob("*.png"))
    jpeg = []
    for png in lossless:
        compressed = cv2.imread(str(sequence / "rgb" / f"{png.stem}.jpg")).astype(np.float32) / 255.0
        jpeg.append(float(-10 * np.log10(np.mean((compressed - cv2.imread(str(png)).astype(np.float32) / 255.0) ** 2))))
    run_log.close()
    return {"sequence": sequence.name, "frames": frames, "sharp_resolution_scale": scale, "densify": densify, "views": chosen,
            "held_out": held_out, "steps_per_view": steps, "gaussians": len(stage.map), "seconds": seconds,
            "fitted_psnr": fitted["psnr_db"], "fitted_ssim": fitted["ssim"],
            "held_out_psnr": between["psnr_db"], "held_out_ssim": between["ssim"],
            "jpeg_against_lossless_psnr": float(np.mean(jpeg)) if jpeg else None, "lossless_frames": len(jpeg)}


def parse_ceiling(text: str) -> tuple[int, float]:
    """``"10"`` -> (10, 0.0); ``"10:0.02"`` -> (10, 0.02); ValueError where the rounds or the share are out of range."""
    rounds, _, densify = text.partition(":")
    parsed = int(rounds), float(densify or 0.0)
    if parsed[0] < 1 or not 0.0 <= parsed[1] < 1.0:
        raise ValueError(text)
    return parsed


def parse_pass_variant(text: str) -> tuple[str, list[str]]:
    """``"l1:mapper.sharp_w_colour_squared=0;mapper.zeta=0.2"`` -> ("l1", [settings]); ValueError unless every
    setting is a ``mapper.key=value``."""
    name, _, settings = text.partition(":")
    parsed = [item for item in settings.split(";") if item]
    if not name or not parsed or not all(item.startswith("mapper.") and "=" in item for item in parsed):
        raise ValueError(text)
    return name, parsed


def run_child(arguments: list[str], log: Path) -> dict | None:
    """This script in a child process (its own peak memory); the row it prints last, None if it failed."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as handle:
        child = subprocess.run([sys.executable, __file__, *arguments], cwd=ROOT, stdout=subprocess.PIPE,
                               stderr=handle, text=True)
    lines = [line for line in child.stdout.splitlines() if line.startswith("{")]
    return json.loads(lines[-1]) if child.returncode == 0 and lines else None


def table(rows: list[dict], fits: list[dict]) -> str:
    lines = [f"{'sequence':28} {'preset':8} {'sharp':5} {'PSNR':>6} {'SSIM':>6} {'PSNRexp':>7} {'SSIMexp':>7} "
             f"{'SSIMlow':>7} {'fps':>6} {'seconds':>8} {'Gaussians':>9}"]
    for row in rows:
        for state in ("off", "on"):
            if state not in row:
                continue
            s = row[state]
            lines.append(f"{row['sequence'][:28]:28} {row['preset']:8} {state:5} {s['psnr']:6.2f} {s['ssim']:6.3f} "
                         f"{s['psnr_exp']:7.2f} {s['ssim_exp']:7.3f} {s['ssim_low']:7.3f} {s['fps']:6.2f} "
                         f"{s['seconds']:8.1f} {s['gaussians']:9d}")
            if "error_shares" in s:
                errors, pixels = s["error_shares"], s["pixel_shares"]
                lines.append(f"{'':28} {'':8} {state:5} squared error as exported (share of pixels): " + ", ".join(
                    f"{name} {100 * errors[name]:.1f} % ({100 * pixels[name]:.1f} %)" for name in errors))
        if "ceiling" in row:
            c = row["ceiling"]
            lines.append(f"{row['sequence'][:28]:28} {row['preset']:8} {'ceil':5} {'-':>6} {'-':>6} {c['psnr_exp']:7.2f} "
                         f"{c['ssim_exp']:7.3f} {'-':>7} {'-':>6} {c['seconds']:8.1f} {c['gaussians']:9d}  (fitted to the "
                         f"scored frames: {c['rounds']} rounds, densify {c['densify']:g})")
        for name, v in row.get("variants", {}).items():
            lines.append(f"{row['sequence'][:28]:28} {row['preset']:8} {'var':5} {v['psnr']:6.2f} {v['ssim']:6.3f} "
                         f"{v['psnr_exp']:7.2f} {v['ssim_exp']:7.3f} {v['ssim_low']:7.3f} {'-':>6} "
                         f"{v['pass_seconds']:8.1f} {v['gaussians']:9d}  ({name}: the pass again from the same map; "
                         "seconds: the pass's)")
        if "limits" in row:
            limit = row["limits"]
            lines.append(f"{row['sequence'][:28]:28} {row['preset']:8} limits: as exported {limit['psnr_exp']:.2f} dB; "
                         f"best colour gain and bias per frame {limit['psnr_affine']:.2f}; poses refined against the map "
                         f"{limit['psnr_pose']:.2f} (moved {limit['pose_moved_mm']:.1f} mm)")
    for fit in fits:
        lines.append(f"fit {fit['sequence'][:24]} scale {fit['sharp_resolution_scale']:g} densify {fit.get('densify', 0):g}: fitted {fit['fitted_psnr']:.2f} dB "
                     f"/ {fit['fitted_ssim']:.3f}, held out {fit['held_out_psnr']:.2f} dB / {fit['held_out_ssim']:.3f}, "
                     f"JPEG vs lossless {fit['jpeg_against_lossless_psnr'] or float('nan'):.1f} dB, {fit['gaussians']} Gaussians")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", nargs="*", default=list(CASES), help="sequence:preset:frames (sequence: "
                        + ", ".join(SEQUENCES) + ")")
    parser.add_argument("--fit", action="append", default=[], help="sequence:frames:resolution_scale[:densify share]")
    parser.add_argument("--set", action="append", default=[], help="section.key=value for every case")
    parser.add_argument("--ceiling", metavar="ROUNDS[:DENSIFY]", help="also fit each case's final map to its scored "
                        "frames themselves (an oracle; see above)")
    parser.add_argument("--limits", action="store_true", help="also score each case's final map with two oracles: "
                        "the best colour gain and bias per frame, and poses refined against the map (see above)")
    parser.add_argument("--pass-variant", action="append", default=[], metavar="NAME:SETTING[;SETTING...]",
                        help="also run the sharpening pass again from the same map with these mapper.* settings "
                             "(see above); repeatable")
    parser.add_argument("--child", nargs=6, metavar=("SEQUENCE", "PRESET", "FRAMES", "OUT", "CEILING", "LIMITS"),
                        help=argparse.SUPPRESS)
    parser.add_argument("--child-fit", nargs=4, metavar=("SEQUENCE", "FRAMES", "SCALE", "DENSIFY"), help=argparse.SUPPRESS)
    parser.add_argument("--output", type=Path, default=RESULTS / "sharp_splats.json")
    arguments = parser.parse_args()
    if arguments.ceiling is not None:
        try:
            parse_ceiling(arguments.ceiling)
        except ValueError:
            parser.error(f"--ceiling {arguments.ceiling}: give ROUNDS (a whole number, 1 or more) and optionally "
                         ":DENSIFY (a share of pixels in [0, 1)), for example 10 or 10:0.02")
    for variant in arguments.pass_variant:
        try:
            parse_pass_variant(variant)
        except ValueError:
            parser.error(f"--pass-variant {variant}: give NAME:SETTING[;SETTING...], each setting mapper.key=value, "
                         "for example l1:mapper.sharp_w_colour_squared=0")
    if arguments.child:
        sequence, preset, frames, out, ceiling, limits = arguments.child
        print(json.dumps(child_case(Path(sequence), preset, int(frames), Path(out), arguments.set,
                                    None if ceiling == "-" else parse_ceiling(ceiling), limits == "limits",
                                    [parse_pass_variant(variant) for variant in arguments.pass_variant])))
        return
    if arguments.child_fit:
        sequence, frames, scale, densify = arguments.child_fit
        print(json.dumps(fit_bound(Path(sequence), int(frames), float(scale), float(densify))))
        return
    # Cases and fits of an earlier run of this script stay in the JSON unless run again (one case at a time fits
    # a shared machine better).
    earlier = json.loads(arguments.output.read_text()) if arguments.output.is_file() else {"cases": [], "fits": []}
    rows, fits = [], []

    def write() -> None:
        key = lambda row: (row["sequence"], row.get("preset"), row["frames"], row.get("sharp_resolution_scale"),  # noqa: E731
                           row.get("densify"))
        done = {key(row) for row in rows + fits}
        report = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                  "machine": f"{describe_machine()} (shared: compare on/off within a row)",
                  "cases": [row for row in earlier["cases"] if key(row) not in done] + rows,
                  "fits": [row for row in earlier["fits"] if key(row) not in done] + fits}
        arguments.output.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(arguments.output, json.dumps(report, indent=2) + "\n")

    for case in arguments.cases:
        name, preset, frames = case.split(":")
        out = RESULTS / "runs" / f"sharp_splats_{name}_{preset}_{frames}"
        extra = [item for setting in arguments.set for item in ("--set", setting)]
        extra += [item for variant in arguments.pass_variant for item in ("--pass-variant", variant)]
        row = run_child(["--child", str(SEQUENCES[name]), preset, frames, str(out), arguments.ceiling or "-",
                         "limits" if arguments.limits else "-", *extra],
                        out.with_suffix(".log"))
        if row is None:
            print(f"{case}: failed, see {out.with_suffix('.log')}", file=sys.stderr)
            continue
        rows.append(row)
        write()
        print(table([row], []), flush=True)
    for fit in arguments.fit:
        name, frames, scale, densify = (fit + ":0").split(":")[:4]
        log = RESULTS / "runs" / f"sharp_splats_fit_{name}_{frames}_{scale}_{densify}.log"
        row = run_child(["--child-fit", str(SEQUENCES[name]), frames, scale, densify], log)
        if row is None:
            print(f"fit {fit}: failed, see {log}", file=sys.stderr)
            continue
        fits.append(row)
        write()
        print(table([], [row]), flush=True)
    print(table(rows, fits))


if __name__ == "__main__":
    main()
