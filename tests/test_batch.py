"""``tambridge batch``: sequences named on the command line, the summary, and real Ray batches (a local Ray, a killed
driver and its rerun, a two-node cluster made with ``ray start``)."""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import json
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import yaml

from pipelines.batch import Attempt, error_line, worth_retrying
from tambridge.batch.sequences import resolve_sequences
from tambridge.batch.summary import SUMMARY_VERSION, SequenceRow, Status, check_batch_folder, write_summary
from tambridge.checkpoint import checkpoint_path
from tambridge.config import load_config
from tambridge.errors import TambridgeError
from tambridge.evaluation.metrics import read_metrics
from tambridge.io.synthetic import SynthOptions, write_synthetic_sequence

ROOT = Path(__file__).resolve().parents[1]
# Tracking only, inline: the batch is about scheduling, skipping and resuming runs, not their quality.
RUN_OPTIONS = ("mapper.enabled=false", "mesh.enabled=false", "frontend.orb.mapping_thread=false")
SHORT_FRAMES, LONG_FRAMES = 6, 150


def _batch_command(sequences, out_dir, *extra) -> list[str]:
    options = [argument for option in RUN_OPTIONS for argument in ("--set", option)]
    return [sys.executable, str(ROOT / "cli.py"), "batch", *map(str, sequences), "-o", str(out_dir), "--quiet",
            *options, *extra]


def _environment(**extra) -> dict:
    return dict(os.environ, PYTHONPATH=str(ROOT), RAY_USAGE_STATS_ENABLED="0", **extra)


def _summary(out_dir: Path) -> dict:
    document = json.loads((out_dir / "summary.json").read_text())
    assert document["summary_version"] == SUMMARY_VERSION
    return {row["name"]: row for row in document["sequences"]}


def _sequence(folder: Path, frames: int) -> Path:
    write_synthetic_sequence(folder, SynthOptions(frame_count=frames, width=160, height=120))
    return folder


@pytest.fixture(scope="module")
def sequences(tmp_path_factory) -> dict[str, Path]:
    """Two short synthetic sequences, a long one, and a corrupt one (its first colour image is not an image)."""
    root = tmp_path_factory.mktemp("batch_sequences")
    folders = {name: _sequence(root / name, SHORT_FRAMES) for name in ("first", "second")}
    folders["long"] = _sequence(root / "long", LONG_FRAMES)
    folders["corrupt"] = _sequence(root / "corrupt", SHORT_FRAMES)
    sorted((folders["corrupt"] / "rgb").iterdir())[0].write_bytes(b"not a png")
    return folders


# ---- without Ray ----------------------------------------------------------------------------------------------------


def test_sequences_come_from_folders_patterns_and_list_files(tmp_path):
    for folder in ("data/a", "data/b", "data/c", "other/a"):
        (tmp_path / folder).mkdir(parents=True)
        (tmp_path / folder / "rgb.txt").write_text("")
    (tmp_path / "data" / "notes.txt").write_text("x")
    listing = tmp_path / "list.txt"
    listing.write_text("# tonight\ndata/c\n\ndata/a  # again\n")
    found = resolve_sequences([str(tmp_path / "data" / "b"), str(tmp_path / "data" / "*"), str(listing)])
    assert [(sequence.name, sequence.folder) for sequence in found] == [
        (name, (tmp_path / "data" / name).resolve()) for name in ("b", "a", "c")]

    with pytest.raises(TambridgeError, match="two sequences named 'a'"):
        resolve_sequences([str(tmp_path / "data" / "a"), str(tmp_path / "other" / "a")])
    with pytest.raises(TambridgeError, match="no such folder"):
        resolve_sequences([str(tmp_path / "missing")])
    with pytest.raises(TambridgeError, match="matches no folder"):
        resolve_sequences([str(tmp_path / "nothing*")])
    listing.write_text("data/z\n")
    with pytest.raises(TambridgeError, match=r"list.txt:1: 'data/z' is not a folder"):
        resolve_sequences([str(listing)])


def test_sequences_must_be_sequence_folders(tmp_path):
    (tmp_path / "notes").mkdir()
    with pytest.raises(TambridgeError) as refused:
        resolve_sequences([str(tmp_path / "*")])
    assert str(refused.value) == (f"{tmp_path / 'notes'}: not a sequence folder (no rgb.txt or depth.txt); leave it "
                                  "out of the batch's folders, patterns and list files")


def test_the_batch_writes_only_into_a_new_empty_or_batch_folder(tmp_path):
    data = tmp_path / "data"
    for name in ("a", "b"):
        (data / name).mkdir(parents=True)
        (data / name / "rgb.txt").write_text("")
    sequences = resolve_sequences([str(data / "*")])
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "index.html").write_text("mine")
    (tmp_path / "file").write_text("x")
    for out_dir, message in ((tmp_path / "mine", "is not empty and holds no batch (index.html); give a new or empty "
                                                 "folder, or an earlier batch's"),
                             (tmp_path / "file", "is a file; give a folder"),
                             (data, "would write sequence a's run into the sequence folder itself")):
        with pytest.raises(TambridgeError, match=re.escape(f"-o {out_dir}: {message}")):
            check_batch_folder(out_dir, sequences)
    assert (tmp_path / "mine" / "index.html").read_text() == "mine"
    write_summary(tmp_path / "earlier", [], {})
    for out_dir in (tmp_path / "new", tmp_path / "earlier"):
        check_batch_folder(out_dir, sequences)


def test_a_failed_run_is_retried_unless_it_refused_its_input():
    failed = Attempt("killed by SIGKILL (out of memory?)", False, 1.0, "node", "id")
    refused = dataclasses.replace(failed, error="rgb/0.png: cannot decode image", refused_input=True)
    assert [worth_retrying(failed, attempts, 2) for attempts in (1, 2, 3)] == [True, True, False]
    assert [worth_retrying(None, attempts, 1) for attempts in (1, 2)] == [True, False]
    assert not worth_retrying(refused, 1, 2)


def test_error_line_is_the_runs_error_or_its_signal_or_its_last_line():
    stderr = "WARNING tambridge: frame 3 has no depth\nerror: rgb/0.png: cannot decode image\n"
    assert error_line(stderr, 2) == "rgb/0.png: cannot decode image"
    assert error_line("", -signal.SIGKILL) == "killed by SIGKILL (out of memory?)"
    assert error_line("Traceback (most recent call last):\n  File x\nRuntimeError: boom\n", 1) == "RuntimeError: boom"
    assert error_line("", 3) == "exit status 3 without a message"


def test_summary_has_one_row_per_sequence_in_json_csv_and_html(tmp_path):
    rows = [SequenceRow(name="ok", sequence="/data/ok", status=Status.finished, attempts=1, frames=30, keyframes=9,
                        ate_rmse_m=0.0125, psnr_db=21.5, ssim=0.71, fps=3.5, wall_s=40.0, node="n1", node_id="ab",
                        report="ok/report/index.html"),
            SequenceRow(name="bad <1>", sequence="/data/bad", status=Status.failed, attempts=3, error="cannot read")]
    write_summary(tmp_path, rows, {"output": str(tmp_path)})
    document = json.loads((tmp_path / "summary.json").read_text())
    assert document["counts"] == {"finished": 1, "skipped": 0, "failed": 1, "interrupted": 0, "pending": 0}
    assert document["sequences"][0]["ate_rmse_m"] == 0.0125 and document["sequences"][1]["error"] == "cannot read"
    with open(tmp_path / "summary.csv", newline="") as handle:
        table = list(csv.DictReader(handle))
    assert [(row["name"], row["status"], row["frames"], row["psnr_db"]) for row in table] == [
        ("ok", "finished", "30", "21.5"), ("bad <1>", "failed", "", "")]
    page = (tmp_path / "index.html").read_text()
    assert '<a href="ok/report/index.html">ok</a>' in page and "<td>1.25</td>" in page
    assert "bad &lt;1&gt;" in page and "1 finished, 1 failed" in page


# ---- on Ray ---------------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_a_cluster_that_cannot_be_joined_stops_the_batch_before_it_writes(sequences, tmp_path):
    out_dir = tmp_path / "out"
    batch = subprocess.run(_batch_command([sequences["first"]], out_dir, "--address", "bad addr"),
                           cwd=ROOT, env=_environment(), capture_output=True, text=True, timeout=120)
    assert batch.returncode == 2
    assert batch.stderr.strip().startswith("error: --address bad addr: cannot join the Ray cluster there")
    assert len(batch.stderr.strip().splitlines()) == 1 and not out_dir.exists()


def _processes_naming(folder: Path) -> list[int]:
    """The processes whose command line names ``folder`` (Linux: read from /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and str(folder) in (entry / "cmdline").read_bytes().decode(errors="replace"):
                found.append(int(entry.name))
        except OSError:
            continue
    return found


def _wait_for(condition, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


@pytest.mark.slow
def test_a_killed_batch_reruns_only_what_did_not_finish_and_a_corrupt_sequence_fails_alone(sequences, tmp_path):
    out_dir = tmp_path / "out"
    names = ("first", "long", "second", "corrupt")
    command = _batch_command([sequences[name] for name in names], out_dir, "--set", "checkpoint.every_keyframes=2",
                             "--set", "checkpoint.min_interval_s=0")
    driver = subprocess.Popen(command, cwd=ROOT, env=_environment(), stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    try:
        # Halfway: a short sequence finished while the long one is between checkpoints.
        _wait_for(lambda: any((out_dir / name / "metrics.json").exists() for name in ("first", "second"))
                  and checkpoint_path(out_dir / "long").exists(), 240, "a finished run and a checkpoint")
        # Stopped, the long run cannot finish in the seconds Ray takes to notice its driver's death; SIGKILL still
        # reaches a stopped process, so the kill below must end it all the same.
        for pid in _processes_naming(out_dir / "long"):
            with contextlib.suppress(ProcessLookupError):  # It finished: the assertion below says so.
                os.kill(pid, signal.SIGSTOP)
    finally:
        driver.send_signal(signal.SIGKILL)
        driver.wait()
    assert not (out_dir / "long" / "metrics.json").exists(), "the long run finished before the driver was killed"
    # The killed driver's local Ray takes its workers with it, and each worker its run.
    _wait_for(lambda: not _processes_naming(out_dir), 60, "the killed batch's runs to end")
    finished = [name for name in names if (out_dir / name / "metrics.json").exists()]
    modified = {path: path.stat().st_mtime_ns for name in finished for path in (out_dir / name).rglob("*")}

    rerun = subprocess.run(command, cwd=ROOT, env=_environment(), capture_output=True, text=True, timeout=300)

    assert rerun.returncode == 1, rerun.stderr
    assert "error: 1 of 4 sequences failed" in rerun.stderr
    assert "failed: corrupt: " in rerun.stderr and "cannot decode image" in rerun.stderr
    rows = _summary(out_dir)
    assert list(rows) == list(names)
    assert {name: row["status"] for name, row in rows.items()} == {
        name: "failed" if name == "corrupt" else "skipped" if name in finished else "finished" for name in names}
    corrupt = rows.pop("corrupt")
    # The run refused its input: another attempt (the default allows two) would refuse it again.
    assert (corrupt["attempts"], corrupt["frames"]) == (1, None)
    assert str(sequences["corrupt"] / "rgb") in corrupt["error"] and "cannot decode image" in corrupt["error"]
    assert not (out_dir / "corrupt" / "metrics.json").exists()
    assert rows["long"]["resumed"] is True and rows["long"]["frames"] == LONG_FRAMES
    assert "resuming at frame" in (out_dir / "long" / "run.log").read_text()
    assert {path: path.stat().st_mtime_ns for path in modified} == modified
    for name in rows:
        assert read_metrics(out_dir / name / "metrics.json").frames == rows[name]["frames"]


WORKER_PORTS = range(47000, 47100)
"""The ports the two nodes' workers get (47000-47049 and 47050-47099); no other component may take one of them."""


def _free_ports(count: int) -> list[int]:
    """``count`` ports free now, none in :data:`WORKER_PORTS` (the kernel hands out ports from a range that holds
    them, and Ray refuses a component port inside a worker range)."""
    sockets = []
    while len([handle for handle in sockets if handle.getsockname()[1] not in WORKER_PORTS]) < count:
        handle = socket.socket()
        handle.bind(("127.0.0.1", 0))
        sockets.append(handle)
    ports = [handle.getsockname()[1] for handle in sockets if handle.getsockname()[1] not in WORKER_PORTS][:count]
    for handle in sockets:
        handle.close()
    return ports


def _ray_start(arguments: list[str], log: Path, environment: dict) -> subprocess.Popen:
    """``ray start --block`` (it stops the node's processes when terminated), once its node is up."""
    with open(log, "w") as handle:
        node = subprocess.Popen([sys.executable, "-m", "ray.scripts.scripts", "start", "--block", "--disable-usage-stats",
                                 "--num-cpus=1", "--object-store-memory=100000000",
                                 *arguments], stdout=handle, stderr=subprocess.STDOUT, env=environment)
    _wait_for(lambda: "Ray runtime started" in log.read_text() or node.poll() is not None, 120, f"ray start ({log})")
    assert node.poll() is None, log.read_text()
    return node


def _stop(node: subprocess.Popen) -> None:
    node.terminate()
    try:
        node.wait(timeout=30)
    except subprocess.TimeoutExpired:
        node.kill()
        node.wait()


@pytest.mark.slow
def test_a_batch_runs_on_a_ray_cluster_made_with_ray_start(sequences, tmp_path):
    # Loopback only: Ray turns 127.0.0.1 into the machine's network address, other 127.x addresses it keeps.
    head_ip, worker_ip = "127.0.0.2", "127.0.0.3"
    ports = iter(_free_ports(12))
    environment = _environment(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=secrets.token_hex(16))
    temp_dir = Path(tempfile.mkdtemp(prefix="tbray", dir="/tmp"))  # short: Ray's socket paths live under it

    def node_ports(worker_ports: str) -> list[str]:
        return [f"--node-manager-port={next(ports)}", f"--object-manager-port={next(ports)}",
                f"--runtime-env-agent-port={next(ports)}", f"--metrics-export-port={next(ports)}",
                f"--dashboard-agent-listen-port={next(ports)}", f"--dashboard-agent-grpc-port={next(ports)}",
                f"--min-worker-port={worker_ports.split('-')[0]}", f"--max-worker-port={worker_ports.split('-')[1]}",
                f"--temp-dir={temp_dir}"]

    gcs_port = _free_ports(1)[0]
    nodes = []
    try:
        nodes.append(_ray_start(["--head", "--include-dashboard=false", f"--node-ip-address={head_ip}", f"--port={gcs_port}",
                                 *node_ports(f"{WORKER_PORTS[0]}-{WORKER_PORTS[49]}")], tmp_path / "head.log", environment))
        address = f"{head_ip}:{gcs_port}"
        nodes.append(_ray_start([f"--address={address}", f"--node-ip-address={worker_ip}",
                                 *node_ports(f"{WORKER_PORTS[50]}-{WORKER_PORTS[-1]}")], tmp_path / "worker.log", environment))
        out_dir = tmp_path / "out"
        # A preset by name, from a folder outside the checkout: the batch gives each run the checkout's file.
        batch = subprocess.run(_batch_command([sequences["first"], sequences["second"]], out_dir, "--address", address,
                                              "--cpus-per-run", "1", "--config", "fast"),
                               cwd=tmp_path, env=environment, capture_output=True, text=True, timeout=300)
        listing = subprocess.run(
            [sys.executable, "-c", "import json, ray; ray.init(address=%r, log_to_driver=False); "
             "print(json.dumps({n['NodeID']: n['NodeManagerAddress'] for n in ray.nodes() if n['Alive']}))" % address],
            env=environment, capture_output=True, text=True, timeout=120)
    finally:
        for node in reversed(nodes):
            _stop(node)
        shutil.rmtree(temp_dir, ignore_errors=True)

    assert batch.returncode == 0, batch.stderr
    cluster = json.loads(listing.stdout.strip().splitlines()[-1])
    assert sorted(cluster.values()) == [head_ip, worker_ip]
    rows = _summary(out_dir)
    assert [row["status"] for row in rows.values()] == ["finished", "finished"]
    # One CPU a node and one a run: the two runs ran at once, one on each node.
    assert sorted(cluster[row["node_id"]] for row in rows.values()) == [head_ip, worker_ip]
    assert json.loads((out_dir / "summary.json").read_text())["config"] == str((ROOT / "configs" / "fast.yaml").resolve())
    fast = yaml.safe_load((ROOT / "configs" / "fast.yaml").read_text())
    assert fast["mapper"]["iterations"] != load_config(None, []).mapper.iterations  # the preset is seen in the runs
    for name, row in rows.items():
        metrics = read_metrics(out_dir / name / "metrics.json")
        config = yaml.safe_load((out_dir / name / "config.yaml").read_text())
        assert all(config[section][key] == value for section, settings in fast.items() for key, value in settings.items())
        assert (row["attempts"], row["error"]) == (1, None)
        assert (row["frames"], row["keyframes"]) == (SHORT_FRAMES, metrics.keyframes)
        assert row["ate_rmse_m"] == metrics.trajectory.ate_rmse_m
        assert row["rpe_trans_rmse_m"] == metrics.trajectory.rpe_trans_rmse_m
        assert row["psnr_db"] is None and row["ssim"] is None  # the mapper is off
        assert row["fps"] == metrics.fps_end_to_end and row["peak_memory_mb"] == metrics.peak_memory_mb
        assert row["node"] == socket.gethostname() and row["wall_s"] > metrics.seconds_total
        assert row["report"] == f"{name}/report/index.html"
        assert f'<a href="{name}/report/index.html">{name}</a>' in (out_dir / "index.html").read_text()


def test_a_finished_run_is_skipped_only_as_the_same_sequence_with_the_same_settings(synthetic_sequence_dir, tmp_path):
    """A batch skips OUT/<name> when it holds a finished run: of that very folder, with the settings asked for (as
    the run records them, ORB values adapted to the camera); else it says which differs, before anything runs."""
    from pipelines.batch import check_finished_run_is_this
    from pipelines.reconstruct import reconstruct
    from tambridge.batch.sequences import BatchSequence

    options = ["mapper.enabled=false", "mesh.enabled=false", "input.max_frames=4", "frontend.orb.mapping_thread=false"]
    run = tmp_path / "out" / "room"
    reconstruct(synthetic_sequence_dir, run, load_config(None, options), progress=False)
    sequence = BatchSequence("room", synthetic_sequence_dir.resolve())
    check_finished_run_is_this(run, sequence, load_config(None, options))
    with pytest.raises(TambridgeError, match=rf"^{run}: holds a finished run with other settings \(input\.max_frames: 4 "
                                             r"there, 5 now\); give another -o"):
        check_finished_run_is_this(run, sequence, load_config(None, [*options, "input.max_frames=5"]))
    elsewhere = tmp_path / "elsewhere" / "room"
    shutil.copytree(synthetic_sequence_dir, elsewhere)
    with pytest.raises(TambridgeError, match=rf"^{run}: holds a finished run of {synthetic_sequence_dir.resolve()}, not "
                                             rf"of {elsewhere}; give another -o"):
        check_finished_run_is_this(run, BatchSequence("room", elsewhere), load_config(None, options))
