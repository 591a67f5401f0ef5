"""Long sessions: ``tambridge reconstruct`` on 1, 2, 3 ... laps of one real sequence, played forward one after another.

    python benchmarks/long_session.py --laps 1 2 3 --work /tmp/long            # fr1/xyz x 1, 2, 3 (792 to 2376 frames)
    python benchmarks/long_session.py --laps 2 --max-frames 1000 --set mapper.enabled=false

The sequence of N laps is built in ``--work`` (outside the repository): ``<sequence>_laps<N>/`` keeps the source's
folder name in front, so a ``freiburg1`` sequence keeps TUM's fr1 camera, rolling shutter included. Every lap plays
the recording FORWARD again (reversed time would be another camera: the tracker models the Kinect's rolling
shutter, which reads rows in time order). Lap k (from 0) is the source with every timestamp shifted by k x (duration
+ one frame interval), the duration being the span of rgb.txt's and depth.txt's stamps together (fr1/xyz: 26.594 s)
and the frame interval the median of rgb.txt's (0.032 s): lap k+1's first frame follows lap k's last one after the
recording's depth stamps have ended and one frame interval more (54 ms on fr1/xyz). Images are absolute symlinks
named by their new stamps (lap 0 by its own); groundtruth.txt and accelerometer.txt are re-stamped alike, each lap
keeping only the samples within half a frame interval of its frames (their recordings start seconds before the
camera's), so that laps never overlap in time; a camera file (camera.yaml, camera.yml, camera.txt) is copied.
The joins are real revisits, but not small ones: at fr1/xyz's last frame the camera is 21.5 cm and 11.5 degrees (motion capture) from where it was at the
first, a jump between two frames 54 ms apart (4 m/s, which no motion model predicts): each join asks the tracker to
relocalise against the earlier laps' keyframes (on 2026-12-07 it did so at the join's first frame, and no loop
closed: tracking went on in the first lap's map, whose keyframes are covisible with the new ones).

Every lap count is one ``reconstruct`` run (default preset, with ``--set``/``--max-frames`` passed through) in its
own process, its resident memory sampled every ``benchmarks.memory.RSS_SAMPLE_S`` seconds (with the frame its
progress bar had reached) and its peak read with wait4 (``benchmarks.memory.peak_rss_mb``). Per run: frames, wall
and CPU seconds (all threads, from the reaped child's rusage: less at the mercy of other work than wall time),
frames/s end to end, the seconds each lap took to track and map within the run (from the progress samples), the
seconds of each stage of metrics.json per frame (ms/frame; the run's stages and the frontend's), keyframes and
Gaussians, loops closed (and which frames they join: run.log), frames lost, ATE over the whole session and per lap
(one SE(3) alignment of the whole trajectory, then the RMSE over each lap's frames), keyframes added per lap
(keyframes.txt), PSNR through the views' exposures and as exported, peak memory. A stage whose ms/frame grows with
the laps grows faster than the frames. Prints the tables and writes benchmarks/results/long_session.json (rows of
other lap counts already there are kept).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import resource
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import describe_machine  # noqa: E402
from benchmarks.memory import peak_rss_mb  # noqa: E402
from benchmarks.sequences import FR1_XYZ, find_sequence, merge_rows  # noqa: E402
from tambridge.errors import TambridgeError  # noqa: E402
from tambridge.evaluation.metrics import read_metrics  # noqa: E402
from tambridge.evaluation.trajectory import evaluate_trajectory  # noqa: E402
from tambridge.files import atomic_write_text, check_new_or_empty_folder  # noqa: E402
from tambridge.geometry import inverse, rotation_angle_deg  # noqa: E402
from tambridge.io.tum import associate, read_file_list  # noqa: E402
from tambridge.trajectory import read_tum_trajectory  # noqa: E402

DEFAULT_LAPS = (1, 2, 3)
LAYOUT_FILE = "long_session.json"
"""Written into each built sequence: how it was made (source, laps, offsets); marks the folder as this script's."""
CAMERA_FILES = ("camera.yaml", "camera.yml", "camera.txt")
RESTAMPED = ("groundtruth.txt", "accelerometer.txt")
"""``timestamp values...`` files re-stamped per lap, each lap keeping the samples near its own frames."""
PROGRESS = re.compile(r"tracking:[^\r\n]*?\|\s*(\d+)/(\d+)")
"""The tracking progress bar (tqdm, in the run's console log): frames tracked of all."""
LOOP = re.compile(r"loop closed: keyframe (\d+) \(frame (\d+)\) revisits keyframe (\d+) \(frame (\d+)\), "
                  r"(\d+) inliers, correction ([\d.]+) m")
LOST = re.compile(r"frame (\d+) \(t=[\d.]+\): tracking lost")
WARNING = re.compile(r" WARNING (\S+): (.*)$")


def lap_layout(source: Path, laps: int) -> dict:
    """Where the laps of ``source`` lie in time: ``offset_s`` (lap k's stamps are the source's + k x offset_s,
    rounded to the microsecond), ``windows_s`` ([first, last] stamp of each lap's frames, s), ``frames_per_lap``
    (colour images paired with depth, as the reader pairs them)."""
    colour, depth = read_file_list(source / "rgb.txt"), read_file_list(source / "depth.txt")
    stamps = np.array([stamp for stamp, _ in colour + depth])
    interval_s = float(np.median(np.diff([stamp for stamp, _ in colour])))
    first_s, last_s = float(stamps.min()), float(stamps.max())
    offset_s = round(last_s - first_s + interval_s, 6)
    frames = len(associate(np.array([s for s, _ in colour]), np.array([s for s, _ in depth])))
    return {"source": str(source.resolve()), "laps": laps, "duration_s": last_s - first_s,
            "frame_interval_s": interval_s, "offset_s": offset_s, "frames_per_lap": frames,
            "windows_s": [[first_s + k * offset_s, last_s + k * offset_s] for k in range(laps)]}


def _restamped_list(source: Path, folder: Path, name: str, offsets_s: list[float]) -> str:
    """rgb.txt or depth.txt for all laps, linking each lap's images as ``<folder of the image>/<new stamp><suffix>``."""
    shift_s = offsets_s[1] if len(offsets_s) > 1 else 0.0
    lines = [f"# {name} of {len(offsets_s)} laps of {source} (lap k: stamps + k x {shift_s:.6f} s)\n"]
    for offset_s in offsets_s:
        for stamp, image in read_file_list(source / name):
            target = (source / image).resolve()
            link = Path(image).parent / f"{stamp + offset_s:.6f}{Path(image).suffix}"
            (folder / link).parent.mkdir(parents=True, exist_ok=True)
            if not (folder / link).is_symlink():
                (folder / link).symlink_to(target)
            lines.append(f"{stamp + offset_s:.6f} {link}\n")
    return "".join(lines)


def _restamped_samples(path: Path, layout: dict) -> str:
    """``path`` (``timestamp values...`` lines) once per lap, re-stamped, each lap's samples only within half a frame
    interval of that lap's frames (so laps do not overlap); comments kept once."""
    margin_s = layout["frame_interval_s"] / 2
    first_s = layout["windows_s"][0][0]
    last_s = layout["windows_s"][0][1]
    header, rows = [], []
    for line in path.read_text().splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            header.append(line + "\n")
            continue
        stamp, _, values = line.strip().partition(" ")
        if first_s - margin_s <= float(stamp) <= last_s + margin_s:
            rows.append((float(stamp), values.strip()))
    lapped = [f"{stamp + k * layout['offset_s']:.6f} {values}\n"
              for k in range(layout["laps"]) for stamp, values in rows]
    return "".join(header) + "".join(lapped)


def build_laps(source: Path, folder: Path, laps: int) -> dict:
    """Write the sequence of ``laps`` laps of ``source`` into ``folder`` (new, empty, or built here before: then
    rebuilt); returns :func:`lap_layout` with the count of frames the reader will pair (checked: laps x the
    source's)."""
    check_new_or_empty_folder(folder, holds="a lapped sequence", marks=(LAYOUT_FILE,))
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    layout = lap_layout(source, laps)
    offsets_s = [k * layout["offset_s"] for k in range(laps)]
    for name in ("rgb.txt", "depth.txt"):
        (folder / name).write_text(_restamped_list(source, folder, name, offsets_s))
    for name in RESTAMPED:
        if (source / name).is_file():
            (folder / name).write_text(_restamped_samples(source / name, layout))
    for name in CAMERA_FILES:
        if (source / name).is_file():
            shutil.copyfile(source / name, folder / name)
    colour, depth = read_file_list(folder / "rgb.txt"), read_file_list(folder / "depth.txt")
    paired = len(associate(np.array([s for s, _ in colour]), np.array([s for s, _ in depth])))
    if paired != laps * layout["frames_per_lap"]:
        raise TambridgeError(f"{folder}: the reader would pair {paired} frames, not {laps} x "
                             f"{layout['frames_per_lap']}; the laps' stamps overlap or run into each other")
    layout["frames"] = paired
    atomic_write_text(folder / LAYOUT_FILE, json.dumps(layout, indent=2) + "\n")
    return layout


def join_jump(source: Path) -> tuple[float, float]:
    """How far (m, degrees) the ground-truth pose at the source's last frame lies from the one at its first: the jump
    at every join of the laps."""
    colour = read_file_list(source / "rgb.txt")
    ends = read_tum_trajectory(source / "groundtruth.txt").nearest(np.array([colour[0][0], colour[-1][0]]))
    first, last = ends.world_from_camera
    return float(np.linalg.norm(last[:3, 3] - first[:3, 3])), rotation_angle_deg(inverse(first) @ last)


class _SamplesWithFrames(list):
    """The list :func:`peak_rss_mb` appends ``(seconds, MiB)`` samples to, each kept as ``(seconds, MiB, frames
    tracked)``: the frame the run's progress bar had reached (its console log's latest, None before the first)."""

    def __init__(self, log_path: Path) -> None:
        super().__init__()
        self.log_path = log_path

    def append(self, sample: tuple[float, float]) -> None:
        frames = None
        try:
            with open(self.log_path, "rb") as log:
                log.seek(0, 2)
                log.seek(max(0, log.tell() - 4096))
                found = PROGRESS.findall(log.read().decode(errors="replace"))
            frames = int(found[-1][0]) if found else (self[-1][2] if self else None)
        except OSError:
            pass
        super().append((*sample, frames))


def online_seconds_per_lap(samples: list[tuple[float, float, int | None]], frames_per_lap: int) -> list[float]:
    """Seconds the run took to track (and map) each whole lap, from the samples' progress (to within a sample
    interval): within one run, a lap that costs more than the first is the session's growth, whatever the load."""
    crossings = [0.0]
    for seconds, _, frames in samples:
        if frames is not None and frames >= frames_per_lap * len(crossings):
            crossings.append(seconds)
    first = next((seconds for seconds, _, frames in samples if frames), None)
    if first is None or len(crossings) < 2:
        return []
    # The first lap is timed from the first progress shown (the run's imports and checks come before it).
    crossings[0] = first
    return [round(b - a, 1) for a, b in zip(crossings, crossings[1:])]


def per_lap_errors(run: Path, folder: Path, layout: dict) -> dict:
    """ATE over the whole session and per lap (cm): trajectory.txt aligned to groundtruth.txt once (SE(3)), then the
    RMSE of the per-pose errors whose stamps fall in each lap; with the keyframes (keyframes.txt) each lap added."""
    errors = evaluate_trajectory(read_tum_trajectory(run / "trajectory.txt"),
                                 read_tum_trajectory(folder / "groundtruth.txt"))
    keyframes = read_tum_trajectory(run / "keyframes.txt").timestamps_s
    margin_s = layout["frame_interval_s"] / 2
    laps = []
    for first_s, last_s in layout["windows_s"]:
        inside = (errors.timestamps_s >= first_s - margin_s) & (errors.timestamps_s <= last_s + margin_s)
        lap_errors = errors.ate_errors_m[inside]
        laps.append({"poses": int(inside.sum()),
                     "ate_rmse_cm": float(np.sqrt(np.mean(lap_errors**2)) * 100) if inside.any() else None,
                     "ate_max_cm": float(lap_errors.max() * 100) if inside.any() else None,
                     "keyframes": int(((keyframes >= first_s - margin_s) & (keyframes <= last_s + margin_s)).sum())})
    return {"ate_rmse_cm": errors.ate_rmse_m * 100, "poses": errors.pose_count, "laps": laps}


def read_run_log(path: Path, frames_per_lap: int) -> dict:
    """From run.log: the loops closed (keyframes and frames they join, the lap of each frame, correction m), the
    frames lost per lap, and the warnings by their logger with the first message of each."""
    loops, lost, warnings = [], {}, {}
    if not path.is_file():
        return {"loops": loops, "lost_per_lap": lost, "warnings": warnings}
    for line in path.read_text(errors="replace").splitlines():
        if (match := LOOP.search(line)) is not None:
            keyframe, frame, earlier_keyframe, earlier_frame, inliers, shift = match.groups()
            loops.append({"keyframe": int(keyframe), "frame": int(frame), "lap": int(frame) // frames_per_lap,
                          "revisits_keyframe": int(earlier_keyframe), "revisits_frame": int(earlier_frame),
                          "revisits_lap": int(earlier_frame) // frames_per_lap, "inliers": int(inliers),
                          "correction_m": float(shift)})
        if (match := LOST.search(line)) is not None:
            lap = str(int(match.group(1)) // frames_per_lap)
            lost[lap] = lost.get(lap, 0) + 1
        if (match := WARNING.search(line)) is not None:
            entry = warnings.setdefault(match.group(1), {"count": 0, "first": match.group(2)})
            entry["count"] += 1
    return {"loops": loops, "lost_per_lap": lost, "warnings": warnings}


def run_laps(source: Path, work: Path, laps: int, options: list[str]) -> dict:
    """Build the sequence of ``laps`` laps and run ``reconstruct`` on it (``options`` passed through); returns its
    row."""
    folder = work / f"{source.name}_laps{laps}"
    layout = build_laps(source, folder, laps)
    out = work / "runs" / f"laps{laps}"
    command = [sys.executable, str(ROOT / "cli.py"), "reconstruct", str(folder), "-o", str(out), *options]
    if out.exists():
        command.append("--overwrite")
    out.parent.mkdir(parents=True, exist_ok=True)
    console = out.parent / f"laps{laps}.console.log"
    samples = _SamplesWithFrames(console)
    load_before, children_before = os.getloadavg()[0], resource.getrusage(resource.RUSAGE_CHILDREN)
    status, peak_mb, seconds = peak_rss_mb(command, console, samples)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    row = {"laps": laps, "options": " ".join(options), "date": datetime.datetime.now().isoformat(timespec="seconds"),
           "sequence": str(folder), "output": str(out), "exit_status": status,
           "wall_seconds": seconds, "cpu_seconds": (children.ru_utime - children_before.ru_utime
                                                     + children.ru_stime - children_before.ru_stime),
           "load_average_1min": [load_before, os.getloadavg()[0]],
           "peak_memory_mb_wait4": peak_mb, "layout": layout,
           "online_seconds_per_lap": online_seconds_per_lap(list(samples), layout["frames_per_lap"]),
           "rss_samples_s_mb_frames": list(samples)}
    metrics_path = out / "metrics.json"
    if status != 0 or not metrics_path.is_file():
        row["console_tail"] = console.read_text(errors="replace")[-2000:]
        return row
    metrics = read_metrics(metrics_path)
    frames = metrics.frames
    rendering = metrics.map.rendering if metrics.map is not None else None
    row.update(
        frames=frames, keyframes=metrics.keyframes, keyframes_culled=metrics.keyframes_culled,
        gaussians=metrics.map.gaussians if metrics.map is not None else None,
        mapping_views=metrics.map.mapping_views if metrics.map is not None else None,
        loops_closed=metrics.loops_closed, frames_lost=metrics.frames_lost,
        frames_relocalised=metrics.frames_relocalised,
        frames_tracked_by_depth=metrics.frames_tracked_by_depth, warnings=metrics.warnings,
        fps_end_to_end=metrics.fps_end_to_end, seconds_total=metrics.seconds_total, wall_fps=frames / seconds,
        seconds_per_stage=metrics.seconds_per_stage, frontend_seconds_per_stage=metrics.frontend_seconds_per_stage,
        ms_per_frame_per_stage={k: 1000 * v / frames for k, v in metrics.seconds_per_stage.items()},
        frontend_ms_per_frame_per_stage={k: 1000 * v / frames for k, v in metrics.frontend_seconds_per_stage.items()},
        peak_memory_mb=metrics.peak_memory_mb, peak_memory_mb_tracking=metrics.peak_memory_mb_tracking,
        ate_rmse_cm_metrics=None if metrics.trajectory is None else metrics.trajectory.ate_rmse_m * 100,
        trajectory_unavailable=metrics.trajectory_unavailable,
        psnr_novel_db=None if rendering is None else rendering.novel_views.psnr_db,
        psnr_mapping_views_db=None if rendering is None else rendering.mapping_views.psnr_db,
        psnr_exported_db=None if rendering is None else rendering.novel_views_exported.psnr_db,
        ssim_exported=None if rendering is None else rendering.novel_views_exported.ssim,
    )
    if metrics.trajectory is not None:
        row["per_lap"] = per_lap_errors(out, folder, layout)
    row["run_log"] = read_run_log(out / "run.log", layout["frames_per_lap"])
    return row


def _number(value, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _settings(row: dict) -> str:
    return row["options"].replace("--set ", "") or "default"


def format_tables(rows: list[dict]) -> str:
    """Markdown: one row per run (frames, time, map, loops, errors, memory), then ms/frame per stage against laps,
    one table per settings."""
    done = [row for row in rows if row["exit_status"] == 0 and "frames" in row]
    lines = ["| settings | laps | frames | wall s (CPU s) | frames/s | online s per lap | keyframes (per lap) | Gaussians | "
             "loops closed | lost | ATE cm | ATE cm per lap | PSNR dB novel / exported | peak MB (tracking) |",
             "|---|" + "---|" * 13]
    for row in rows:
        if row not in done:
            lines.append(f"| {_settings(row)} | {row['laps']} | failed (exit {row['exit_status']}) | "
                         f"{row['wall_seconds']:.0f} |" + " |" * 10)
            continue
        per_lap = row.get("per_lap", {}).get("laps", [])
        lines.append(
            f"| {_settings(row)} | {row['laps']} | {row['frames']} | {row['wall_seconds']:.0f} "
            f"({_number(row.get('cpu_seconds'), 0)}) | "
            f"{row['fps_end_to_end']:.2f} | {' / '.join(f'{s:.0f}' for s in row['online_seconds_per_lap']) or '-'} | "
            f"{row['keyframes']} ({' / '.join(str(lap['keyframes']) for lap in per_lap) or '-'}) | "
            f"{row['gaussians'] or '-'} | {row['loops_closed']} | {row['frames_lost']} | "
            f"{_number(row['per_lap']['ate_rmse_cm'] if 'per_lap' in row else None, 2)} | "
            f"{' / '.join(_number(lap['ate_rmse_cm'], 2) for lap in per_lap) or '-'} | "
            f"{_number(row['psnr_novel_db'], 2)} / {_number(row['psnr_exported_db'], 2)} | "
            f"{row['peak_memory_mb']:.0f} ({row['peak_memory_mb_tracking']:.0f}) |")
    for settings in dict.fromkeys(_settings(row) for row in done):
        group = [row for row in done if _settings(row) == settings]
        for title, key in (("stage", "ms_per_frame_per_stage"), ("frontend stage", "frontend_ms_per_frame_per_stage")):
            stages = list(dict.fromkeys(stage for row in group for stage in row[key]))
            header = " | ".join(f"{row['laps']} lap{'s' if row['laps'] > 1 else ''} ({row['frames']} fr)" for row in group)
            lines += ["", f"| {title}, ms/frame ({settings}) | {header} | last / first |", "|---|" + "---|" * (len(group) + 1)]
            for stage in stages:
                values = [row[key].get(stage) for row in group]
                ratio = (values[-1] / values[0]) if values[0] and values[-1] is not None and len(group) > 1 else None
                lines.append(f"| {stage} | {' | '.join(_number(value) for value in values)} | "
                             f"{'-' if ratio is None else f'{ratio:.2f}x'} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", default=FR1_XYZ,
                        help=f"the sequence to lap: a folder or a name (default {FR1_XYZ})")
    parser.add_argument("--data", type=Path, nargs="+", help="folders to look for --sequence in")
    parser.add_argument("--laps", type=int, nargs="+", default=list(DEFAULT_LAPS), help="lap counts, one run each")
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "tambridge_long_session",
                        help="where the lapped sequences and the runs go (outside the repository)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="passed to reconstruct as --set KEY=VALUE (repeatable)")
    parser.add_argument("--max-frames", type=int, help="passed to reconstruct: at most this many frames of the laps")
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "long_session.json")
    arguments = parser.parse_args()
    source = find_sequence(arguments.sequence, *([arguments.data] if arguments.data else []))
    if any(laps < 1 for laps in arguments.laps):
        parser.error(f"--laps {arguments.laps}: give counts of 1 or more")
    if ROOT in arguments.work.resolve().parents or arguments.work.resolve() == ROOT:
        parser.error(f"--work {arguments.work}: inside the repository; give a folder outside it (e.g. /tmp/long)")
    options = [item for override in arguments.overrides for item in ("--set", override)]
    if arguments.max_frames is not None:
        options += ["--max-frames", str(arguments.max_frames)]
    jump_m, jump_deg = join_jump(source) if (source / "groundtruth.txt").is_file() else (None, None)
    if jump_m is not None:
        print(f"{source.name}: last frame {jump_m * 100:.1f} cm, {jump_deg:.1f} deg from the first (ground truth)")
    command = " ".join(["python", "benchmarks/long_session.py", *sys.argv[1:]])
    rows = []
    for laps in arguments.laps:
        print(f"reconstruct, {laps} lap(s) of {source.name} ...", flush=True)
        try:
            rows.append({"command": command, **run_laps(source, arguments.work, laps, options)})
        except TambridgeError as error:
            raise SystemExit(f"error: {error}") from None
        row = rows[-1]
        print(f"  exit {row['exit_status']}, {row.get('frames', '-')} frames in {row['wall_seconds']:.0f} s, "
              f"peak {row['peak_memory_mb_wait4']:.0f} MB", flush=True)
    old = json.loads(arguments.output.read_text()).get("rows", []) if arguments.output.is_file() else []
    rows = sorted(merge_rows(old, rows, ("laps", "options")), key=lambda row: (row["options"], row["laps"]))
    for row in rows:
        if "online_seconds_per_lap" not in row:
            row["online_seconds_per_lap"] = online_seconds_per_lap(row["rss_samples_s_mb_frames"],
                                                                   row["layout"]["frames_per_lap"])
    print(format_tables(rows))
    result = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": describe_machine(),
              "command": command, "sequence": str(source),
              "join_jump_m": jump_m, "join_jump_deg": jump_deg, "rows": rows}
    atomic_write_text(arguments.output, json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
