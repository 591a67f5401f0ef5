"""A batch's summary: one row per sequence in ``OUT/summary.json``, ``OUT/summary.csv`` and ``OUT/index.html``.

The figures of a finished sequence come from its ``metrics.json`` (:func:`read_metrics`); how it ran (status,
attempts, node, wall time) from the batch. Distances are metres, rotations degrees, memory MiB, times seconds.
"""

from __future__ import annotations

import csv
import dataclasses
import enum
import html
import io
import json
from pathlib import Path
from typing import Sequence

from tambridge.batch.sequences import BatchSequence
from tambridge.errors import TambridgeError
from tambridge.evaluation.metrics import read_metrics
from tambridge.files import atomic_write_text, check_new_or_empty_folder

SUMMARY_VERSION = 1
"""Bumped whenever a column of the summary is added, renamed or removed, or changes meaning."""
SUMMARY_JSON, SUMMARY_CSV, SUMMARY_HTML = "summary.json", "summary.csv", "index.html"


class Status(str, enum.Enum):
    """Where a sequence stands at the end of a batch."""

    finished = "finished"
    """Ran in this batch and finished."""
    skipped = "skipped"
    """Had finished in an earlier batch (its metrics.json was there): not run again."""
    failed = "failed"
    """Failed on every attempt; ``error`` is the last one's error line."""
    interrupted = "interrupted"
    """Running when the batch was stopped (Ctrl-C); a rerun resumes it from its checkpoint where it has one."""
    pending = "pending"
    """Queued or running: what the summary says while the batch runs (or after its driver was killed)."""


@dataclasses.dataclass(kw_only=True)
class SequenceRow:
    """One sequence of a batch. The figures are None when the run did not finish (or has no such figure: ATE and RPE
    without ground truth, PSNR and SSIM with the mapper off); ``node``, ``node_id`` and ``wall_s`` are those of the
    attempt that ran last (None when none ran, nor the earlier batch recorded them)."""

    name: str
    sequence: str
    status: Status
    error: str | None = None
    attempts: int = 0
    resumed: bool = False
    """Whether the last attempt continued a killed run from its checkpoint."""
    frames: int | None = None
    keyframes: int | None = None
    ate_rmse_m: float | None = None
    rpe_trans_rmse_m: float | None = None
    rpe_rot_rmse_deg: float | None = None
    psnr_db: float | None = None
    """At the novel (evaluation) views, as metrics.json's ``rendering.novel_views``."""
    ssim: float | None = None
    fps: float | None = None
    """Frames over the run's end-to-end seconds (metrics.json's ``fps_end_to_end``)."""
    peak_memory_mb: float | None = None
    wall_s: float | None = None
    """Seconds the last attempt took on its node, from start-up to exit."""
    node: str | None = None
    """The host name of the node that ran the last attempt."""
    node_id: str | None = None
    """Ray's id of that node."""
    report: str | None = None
    """The run's report, relative to the batch's output folder."""


COLUMNS = [field.name for field in dataclasses.fields(SequenceRow)]


def with_metrics(row: SequenceRow, run_dir: Path, out_dir: Path) -> SequenceRow:
    """``row`` with the figures of the finished run in ``run_dir`` (read from its metrics.json) and its report."""
    metrics = read_metrics(run_dir / "metrics.json")
    novel = metrics.map.rendering.novel_views if metrics.map is not None else None
    trajectory = metrics.trajectory
    report = run_dir / "report" / "index.html"
    return dataclasses.replace(
        row, frames=metrics.frames, keyframes=metrics.keyframes,
        ate_rmse_m=None if trajectory is None else trajectory.ate_rmse_m,
        rpe_trans_rmse_m=None if trajectory is None else trajectory.rpe_trans_rmse_m,
        rpe_rot_rmse_deg=None if trajectory is None else trajectory.rpe_rot_rmse_deg,
        psnr_db=None if novel is None else novel.psnr_db, ssim=None if novel is None else novel.ssim,
        fps=metrics.fps_end_to_end, peak_memory_mb=metrics.peak_memory_mb,
        report=str(report.relative_to(out_dir)) if report.is_file() else None)


def is_finished(run_dir: Path) -> bool:
    """Whether ``run_dir`` holds a finished run of this tambridge (a metrics.json that :func:`read_metrics` reads)."""
    try:
        read_metrics(run_dir / "metrics.json")
    except TambridgeError:
        return False
    return True


def check_batch_folder(out_dir: Path, sequences: Sequence[BatchSequence]) -> None:
    """Raise :class:`TambridgeError` unless a batch may write into ``out_dir``: new, empty, or an earlier batch's
    (with its summary.json), and no sequence's folder its own output folder ``out_dir/<name>``."""
    out_dir = Path(out_dir)
    for sequence in sequences:
        if (out_dir / sequence.name).resolve() == Path(sequence.folder).resolve():
            raise TambridgeError(f"-o {out_dir}: would write sequence {sequence.name}'s run into the sequence folder "
                                 "itself; give another -o")
    check_new_or_empty_folder(out_dir, "-o", "batch", [SUMMARY_JSON])


def read_rows(out_dir: Path) -> dict[str, SequenceRow]:
    """The rows of ``out_dir/summary.json`` by name (none when it is missing or of another summary version): an
    earlier batch's record of how its sequences ran."""
    path = Path(out_dir) / SUMMARY_JSON
    try:
        data = json.loads(path.read_text())
        if data.get("summary_version") != SUMMARY_VERSION:
            return {}
        return {row["name"]: SequenceRow(**{**row, "status": Status(row["status"])}) for row in data["sequences"]}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def counts(rows: Sequence[SequenceRow]) -> dict[str, int]:
    """How many rows have each status (every status named, zeros too)."""
    return {status.value: sum(row.status == status for row in rows) for status in Status}


def write_summary(out_dir: Path, rows: Sequence[SequenceRow], batch: dict) -> None:
    """Write summary.json (``batch``'s keys, the counts by status and the rows), summary.csv and index.html into
    ``out_dir``, each atomically."""
    out_dir = Path(out_dir)
    records = [_record(row) for row in rows]
    document = {"summary_version": SUMMARY_VERSION, **batch, "counts": counts(rows), "sequences": records}
    atomic_write_text(out_dir / SUMMARY_JSON, json.dumps(document, indent=2) + "\n")
    table = io.StringIO()
    writer = csv.DictWriter(table, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows({key: "" if value is None else value for key, value in record.items()} for record in records)
    atomic_write_text(out_dir / SUMMARY_CSV, table.getvalue())
    atomic_write_text(out_dir / SUMMARY_HTML, summary_html(rows, batch))


def _record(row: SequenceRow) -> dict:
    return {**dataclasses.asdict(row), "status": row.status.value}


HTML_COLUMNS = {
    "name": "sequence", "status": "status", "error": "error", "attempts": "attempts", "frames": "frames",
    "keyframes": "keyframes", "ate_rmse_m": "ATE RMSE (cm)", "rpe_trans_rmse_m": "RPE (cm/frame)",
    "psnr_db": "PSNR (dB)", "ssim": "SSIM", "fps": "frames/s", "peak_memory_mb": "peak MiB", "wall_s": "wall (s)",
    "node": "node",
}
"""The columns of index.html and their headings."""


def _cell(row: SequenceRow, column: str) -> str:
    value = getattr(row, column)
    if value is None:
        return ""
    if column in ("ate_rmse_m", "rpe_trans_rmse_m"):
        return f"{value * 100:.2f}"
    if column == "status":
        return value.value
    if column == "name" and row.report is not None:
        return f'<a href="{html.escape(row.report)}">{html.escape(value)}</a>'
    if isinstance(value, float):
        return f"{value:.3f}" if column == "ssim" else f"{value:.1f}"
    return html.escape(str(value))


def summary_html(rows: Sequence[SequenceRow], batch: dict) -> str:
    """index.html: the counts by status and one table row per sequence, its name linking to the run's report."""
    tally = ", ".join(f"{count} {status}" for status, count in counts(rows).items() if count)
    head = "".join(f"<th>{html.escape(title)}</th>" for title in HTML_COLUMNS.values())
    body = "\n".join(
        f'<tr class="{row.status.value.replace(" ", "-")}">' + "".join(f"<td>{_cell(row, column)}</td>"
                                                                          for column in HTML_COLUMNS) + "</tr>"
        for row in rows)
    return f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>tambridge batch: {html.escape(str(batch.get("output", "")))}</title>
<style>body{{font-family:sans-serif}} table{{border-collapse:collapse}} td,th{{border:1px solid #ccc;padding:2px 6px}}
tr.failed{{background:#fdd}} tr.interrupted,tr.pending{{background:#ffd}}</style></head>
<body><h1>tambridge batch</h1><p>{html.escape(tally)}</p>
<table><tr>{head}</tr>
{body}
</table></body></html>
"""
