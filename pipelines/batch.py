"""``tambridge batch``: many sequences reconstructed on Ray, one task per sequence, each writing ``OUT/<name>/``.

Ray schedules the tasks: ``ray.init()`` without an address starts a Ray on this machine, ``--address`` joins a
cluster made with ``ray start`` (by hand, KubeRay or Slurm). A task is given paths, never frames: every worker reads
the sequence and writes its outputs on a file system that the driver and all workers see (a shared or mounted
one); Ray's object store only carries each task's small report. The driver skips sequences whose run finished
(metrics.json), lets a killed one resume from its checkpoint, retries failures and writes the summary
(:mod:`tambridge.batch.summary`).

Each task runs ``tambridge reconstruct`` in a child process rather than the pipeline in the Ray worker, because:
a crash (a segfault in a native library, memory exhausted) then ends one attempt with an error line instead of the
worker; thread pools (numba's is sized once per process, torch's and OpenMP's from the environment) are bounded by
``--cpus-per-run`` from the start; metrics.json's peak memory is that process's (``ru_maxrss`` of a reused worker
would carry an earlier sequence's peak); and the run is exactly the one ``tambridge reconstruct`` makes (same config
resolution, outputs, checkpoints). Its cost, the start-up and imports of one process per sequence, is seconds
against a run of minutes (benchmarks/batch.py measures it).
"""

from __future__ import annotations

import collections
import dataclasses
import datetime
import logging
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Sequence

from tqdm import tqdm

import tambridge
from tambridge.batch.sequences import BatchSequence
from tambridge.batch.summary import (SequenceRow, Status, check_batch_folder, is_finished, read_rows, with_metrics,
                                     write_summary)
from tambridge.checkpoint import checkpoint_path
from tambridge.errors import INPUT_ERROR_STATUS, TambridgeError
from tambridge.files import find_config_file

logger = logging.getLogger("tambridge.pipelines.batch")

THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")
"""Environment variables that size a process's thread pools (OpenMP, BLAS, numba; torch follows OpenMP's)."""
LOCAL_OBJECT_STORE_BYTES = 100 * 1024 * 1024
"""Object store of a local Ray: tasks exchange paths and small reports only, so Ray's default (30 % of the memory)
would only reserve shared memory the runs need."""
STOP_TIMEOUT_S = 20.0
"""After Ctrl-C: how long the driver waits for the running tasks to stop their runs."""
CHILD_STOP_TIMEOUT_S = 10.0
"""How long a task waits for its run to stop after SIGINT (it notes the stop in run.log) before killing it."""
SUMMARY_INTERVAL_S = 10.0
"""How often the driver rewrites the summary while the batch runs (and once at the end)."""
PR_SET_PDEATHSIG = 1


@dataclasses.dataclass(frozen=True)
class BatchOptions:
    """How a batch runs. ``preset`` and ``overrides`` as ``tambridge reconstruct``'s ``--config`` and ``--set``;
    ``address``: a Ray cluster (``auto`` or ``HOST:PORT``; None: ``$RAY_ADDRESS``, else a Ray started on this machine);
    ``cpus_per_run``: the CPUs Ray reserves for one sequence, and its run's thread count; ``retries``: attempts after
    the first for a sequence that fails."""

    preset: Path | None = None
    overrides: tuple[str, ...] = ()
    address: str | None = None
    cpus_per_run: int = 1
    retries: int = 2


@dataclasses.dataclass(frozen=True)
class Attempt:
    """What one task reports: the run's error line (None: it finished), whether it resumed from a checkpoint, its
    wall seconds, the host name and Ray node id of the node that ran it, and whether the run refused its input
    (``tambridge``'s exit status 2: a frame that cannot be decoded, a camera file that does not fit, a folder it may not
    write), which another attempt would refuse again."""

    error: str | None
    resumed: bool
    wall_s: float
    node: str
    node_id: str
    refused_input: bool = False


@dataclasses.dataclass
class BatchResult:
    """The summary's rows, in the order the sequences were given, and whether Ctrl-C stopped the batch."""

    rows: list[SequenceRow]
    interrupted: bool

    @property
    def failed(self) -> list[SequenceRow]:
        return [row for row in self.rows if row.status == Status.failed]


# ---- the task (on a worker) ---------------------------------------------------------------------------------------


def reconstruct_command(sequence_dir: Path, run_dir: Path, preset: Path | None, overrides: Sequence[str],
                        resume: bool) -> list[str]:
    """The child's command line: ``tambridge reconstruct`` through :func:`child_main`, which ties the child's life
    to this process's."""
    command = [sys.executable, "-m", "pipelines.batch", str(os.getpid()), "reconstruct", str(sequence_dir),
               "-o", str(run_dir), "--quiet"]
    if preset is not None:
        command += ["--config", str(preset)]
    for override in overrides:
        command += ["--set", override]
    return command + (["--resume"] if resume else [])


def run_sequence(sequence_dir: str, run_dir: str, preset: str | None, overrides: Sequence[str],
                 cpus: int) -> Attempt:
    """The Ray task: reconstruct ``sequence_dir`` into ``run_dir`` in a child process with ``cpus`` threads,
    resuming from ``run_dir``'s checkpoint where there is one (a killed or preempted earlier attempt's)."""
    import ray

    started = time.perf_counter()
    resume = checkpoint_path(Path(run_dir)).is_file()
    command = reconstruct_command(Path(sequence_dir), Path(run_dir), None if preset is None else Path(preset),
                                  overrides, resume)
    # The child imports the tambridge this worker runs (a PYTHONPATH checkout, or the installed one).
    root = str(Path(tambridge.__file__).resolve().parents[1])
    environment = {**os.environ, **{name: str(cpus) for name in THREAD_VARIABLES},
                   "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
    with tempfile.TemporaryFile() as stderr:
        child = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=stderr,
                                 env=environment)
        try:
            code = _wait(child)
        except BaseException:
            # Cancelled (the driver's Ctrl-C): stop the run as Ctrl-C stops reconstruct, so run.log says so.
            _stop(child)
            raise
        stderr.seek(0)
        error = None if code == 0 else error_line(stderr.read().decode(errors="replace"), code)
    context = ray.get_runtime_context()
    return Attempt(error, resume, time.perf_counter() - started, socket.gethostname(), context.get_node_id(),
                   refused_input=code == INPUT_ERROR_STATUS)


def _wait(child: subprocess.Popen) -> int:
    # Short waits: a cancellation raised into this thread is seen between them, not only when the child exits.
    while True:
        try:
            return child.wait(timeout=0.5)
        except subprocess.TimeoutExpired:
            continue


def _stop(child: subprocess.Popen) -> None:
    child.send_signal(signal.SIGINT)
    try:
        child.wait(timeout=CHILD_STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        child.kill()
        child.wait()


def error_line(stderr: str, code: int) -> str:
    """One line saying why a run with exit status ``code`` and ``stderr`` failed: tambridge's ``error:`` line, else
    the signal that killed it, else the last line it wrote (a traceback's exception)."""
    lines = [line.strip() for line in stderr.splitlines() if line.strip()]
    errors = [line.removeprefix("error:").strip() for line in lines if line.startswith("error:")]
    if errors:
        return errors[-1]
    if code < 0:
        name = signal.Signals(-code).name
        return f"killed by {name}" + (" (out of memory?)" if -code == signal.SIGKILL else "")
    return lines[-1] if lines else f"exit status {code} without a message"


def child_main(arguments: Sequence[str]) -> None:
    """``python -m pipelines.batch PARENT_PID COMMAND...``: the ``tambridge`` command line, killed when its parent
    (the Ray worker) dies, so no run outlives a killed batch and writes into a folder its rerun is using."""
    parent, command = int(arguments[0]), list(arguments[1:])
    # Ray's workers block SIGINT and a child inherits the mask: unblocked, SIGINT stops the run as Ctrl-C would.
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
        if os.getppid() != parent:
            sys.exit(f"error: the batch task (process {parent}) ended before its run started")
    from cli import main

    main(command, prog_name="tambridge")


# ---- the driver -----------------------------------------------------------------------------------------------------


def run_batch(sequences: Sequence[BatchSequence], out_dir: Path, options: BatchOptions,
              progress: bool = True) -> BatchResult:
    """Reconstruct each of ``sequences`` into ``out_dir/<name>/`` on Ray and write the summary into ``out_dir``.

    Sequences finished by an earlier batch are skipped. A failed attempt (the run's error, a lost worker or node) is
    retried up to ``options.retries`` times, then the sequence is failed with its last error line; the others go on.
    Ctrl-C stops the running runs (a rerun resumes those with a checkpoint) and returns with ``interrupted``.
    """
    # Here, not at the top: Ray workers import this module for run_sequence, and the config layer imports torch.
    from tambridge.config import check_config, load_config

    # A bad preset or --set, or an output folder that is not the batch's, stops it here, not in every task.
    config = load_config(options.preset, options.overrides)
    check_config(config)
    check_batch_folder(out_dir, sequences)
    out_dir = Path(out_dir).resolve()
    preset = None if options.preset is None else str(find_config_file(options.preset).resolve())
    batch = {"output": str(out_dir), "started": _now(), "finished": None, "address": options.address,
             "config": preset, "overrides": list(options.overrides), "cpus_per_run": options.cpus_per_run,
             "retries": options.retries}
    earlier = read_rows(out_dir)
    rows: dict[str, SequenceRow] = {}
    to_run = []
    for sequence in sequences:
        run_dir = out_dir / sequence.name
        if is_finished(run_dir):
            check_finished_run_is_this(run_dir, sequence, config)
            before = earlier.get(sequence.name)
            ran = {} if before is None else {"attempts": before.attempts, "resumed": before.resumed,
                                             "wall_s": before.wall_s, "node": before.node, "node_id": before.node_id}
            rows[sequence.name] = with_metrics(
                SequenceRow(name=sequence.name, sequence=str(sequence.folder), status=Status.skipped, **ran),
                run_dir, out_dir)
        else:
            rows[sequence.name] = SequenceRow(name=sequence.name, sequence=str(sequence.folder), status=Status.pending)
            to_run.append(sequence)
    # Ray first: a cluster that cannot be joined stops the batch before it writes anything.
    ray = connect(options.address) if to_run else None
    interrupted = False
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        write_summary(out_dir, list(rows.values()), batch)
        if to_run:
            interrupted = _run_tasks(ray, to_run, out_dir, preset, options, rows, batch, progress)
    finally:
        if ray is not None:
            ray.shutdown()
    batch["finished"] = _now()
    write_summary(out_dir, list(rows.values()), batch)
    return BatchResult(list(rows.values()), interrupted)


def check_finished_run_is_this(run_dir: Path, sequence: BatchSequence, config) -> None:
    """Raise :class:`TambridgeError` (one line naming ``run_dir``) unless the finished run in it is of ``sequence``
    with ``config`` as a run of it would record it (config.yaml: the ORB values adapted to its camera; the checkpoint
    section aside): a batch skips that run as this sequence's, so another folder of the same name, or other
    settings, would be reported as done."""
    from tambridge.camera import find_sensor
    from tambridge.checkpoint import IGNORED_CONFIG_SECTIONS
    from tambridge.config import config_for_camera, load_config, to_dict
    from tambridge.evaluation.metrics import read_metrics
    from tambridge.state import dotted_items

    ran = read_metrics(run_dir / "metrics.json").sequence
    if Path(ran).resolve() != Path(sequence.folder).resolve():
        raise TambridgeError(f"{run_dir}: holds a finished run of {ran}, not of {sequence.folder}; give another -o, or "
                             "remove that run to make this one")
    camera = find_sensor(sequence.folder, config.input.camera_file).camera
    wanted, had = (dotted_items({section: values for section, values in to_dict(settings).items()
                                 if section not in IGNORED_CONFIG_SECTIONS})
                   for settings in (config_for_camera(config, camera), load_config(run_dir / "config.yaml")))
    differing = sorted(key for key in wanted.keys() | had.keys() if wanted.get(key) != had.get(key))
    if differing:
        key = differing[0]
        raise TambridgeError(f"{run_dir}: holds a finished run with other settings ({key}: {had.get(key)!r} there, "
                             f"{wanted.get(key)!r} now); give another -o, or remove that run to make it again")


def connect(address: str | None):
    """Ray, connected to the cluster at ``address`` (or ``$RAY_ADDRESS``), else to a Ray it starts on this machine."""
    try:
        import ray
    except ImportError:
        raise TambridgeError("tambridge batch needs Ray: pip install 'tambridge[batch]' (or pip install 'ray>=2.9')") from None
    # Ray reports usage to its developers unless told otherwise; a batch does not opt its users in.
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    common = {"log_to_driver": False, "logging_level": logging.WARNING}
    try:
        if address is None and not os.environ.get("RAY_ADDRESS"):
            ray.init(include_dashboard=False, object_store_memory=LOCAL_OBJECT_STORE_BYTES, **common)
        else:
            ray.init(address=address, **common)
    except (ConnectionError, RuntimeError, ValueError) as error:
        where = address or os.environ.get("RAY_ADDRESS")
        raise TambridgeError(f"--address {where}: cannot join the Ray cluster there ({_first_line(error)}); start one "
                             f"with `ray start --head`, or leave --address out to run on this machine") from None
    return ray


def _run_tasks(ray, sequences: Sequence[BatchSequence], out_dir: Path, preset: str | None, options: BatchOptions,
               rows: dict[str, SequenceRow], batch: dict, progress: bool) -> bool:
    """Submit one task per sequence, retry and record them in ``rows`` as they end; True when Ctrl-C stopped it."""
    task = ray.remote(run_sequence).options(num_cpus=options.cpus_per_run, max_retries=0)
    in_flight: dict = {}
    attempts: collections.Counter[str] = collections.Counter()

    def submit(sequence: BatchSequence) -> None:
        reference = task.remote(str(sequence.folder), str(out_dir / sequence.name), preset, list(options.overrides),
                                options.cpus_per_run)
        in_flight[reference] = sequence
        attempts[sequence.name] += 1

    for sequence in sequences:
        submit(sequence)
    settled = len(rows) - len(sequences)
    bar = tqdm(total=len(rows), initial=settled, desc="batch", unit="seq", disable=not progress, dynamic_ncols=True)
    written, shown = time.monotonic(), ""
    try:
        while in_flight:
            ready, _ = ray.wait(list(in_flight), num_returns=len(in_flight), timeout=1.0)
            for reference in ready:
                sequence = in_flight.pop(reference)
                attempt, error = _outcome(ray, reference)
                if error is not None and worth_retrying(attempt, attempts[sequence.name], options.retries):
                    logger.warning("%s: attempt %d failed (%s); retrying", sequence.name, attempts[sequence.name], error)
                    submit(sequence)
                    continue
                rows[sequence.name] = _row(sequence, out_dir, attempt, error, attempts[sequence.name])
                bar.update()
            failed = sum(row.status == Status.failed for row in rows.values())
            # Ray does not say which tasks in flight have started: those the cluster's CPUs hold are counted running.
            capacity = int(ray.cluster_resources().get("CPU", 0) // options.cpus_per_run)
            running = min(len(in_flight), capacity)
            state = f"done {bar.n - failed}, running {running}, queued {len(in_flight) - running}, failed {failed}"
            if state != shown:
                bar.set_postfix_str(state)
                shown = state
            if time.monotonic() - written > SUMMARY_INTERVAL_S:
                write_summary(out_dir, list(rows.values()), batch)
                written = time.monotonic()
        return False
    except KeyboardInterrupt:
        _cancel(ray, in_flight)
        for sequence in in_flight.values():
            # A run may have finished while its task was being cancelled.
            finished = is_finished(out_dir / sequence.name)
            row = dataclasses.replace(rows[sequence.name], status=Status.finished if finished else Status.interrupted,
                                      attempts=attempts[sequence.name])
            rows[sequence.name] = with_metrics(row, out_dir / sequence.name, out_dir) if finished else row
        return True
    finally:
        bar.close()


def worth_retrying(attempt: Attempt | None, attempts: int, retries: int) -> bool:
    """Whether a failed sequence gets another attempt after ``attempts``: while ``retries`` allow, unless its run
    refused its input (another attempt would refuse it again); a task that failed without a report (``attempt``
    None: a lost worker or node) is retried."""
    return attempts <= retries and (attempt is None or not attempt.refused_input)


def _outcome(ray, reference) -> tuple[Attempt | None, str | None]:
    """The attempt a finished task reports and its error line; (None, why) when the task itself failed (its
    worker or node lost, or an exception in the task)."""
    try:
        attempt = ray.get(reference)
    except ray.exceptions.RayTaskError as error:
        return None, _first_line(error, last=True)
    except ray.exceptions.RayError as error:
        return None, _first_line(error)
    return attempt, attempt.error


def _row(sequence: BatchSequence, out_dir: Path, attempt: Attempt | None, error: str | None,
         attempts: int) -> SequenceRow:
    ran = {} if attempt is None else {"resumed": attempt.resumed, "wall_s": attempt.wall_s, "node": attempt.node,
                                      "node_id": attempt.node_id}
    row = SequenceRow(name=sequence.name, sequence=str(sequence.folder), attempts=attempts,
                      status=Status.failed if error is not None else Status.finished, error=error, **ran)
    if error is None:
        try:
            return with_metrics(row, out_dir / sequence.name, out_dir)
        except TambridgeError as unreadable:
            return dataclasses.replace(row, status=Status.failed, error=str(unreadable))
    return row


def _cancel(ray, in_flight: dict) -> None:
    """Stop the tasks in flight: each stops its run (:func:`run_sequence`); those that do not within
    :data:`STOP_TIMEOUT_S` are killed with their workers."""
    for reference in in_flight:
        ray.cancel(reference)
    _, stuck = ray.wait(list(in_flight), num_returns=len(in_flight), timeout=STOP_TIMEOUT_S)
    for reference in stuck:
        ray.cancel(reference, force=True)


def _first_line(error: BaseException, last: bool = False) -> str:
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    if not lines:
        return type(error).__name__
    return lines[-1] if last else lines[0]


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


if __name__ == "__main__":
    child_main(sys.argv[1:])
