"""The run log: ``run.log`` beside the results, stage timings and peak memory of a run."""

from __future__ import annotations

import contextlib
import logging
import resource
import time
from pathlib import Path
from typing import Iterator

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def peak_memory_mb() -> float:
    """Peak resident memory of this process so far, in MiB (``ru_maxrss``; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class RunLog:
    """Routes the ``tambridge`` loggers to ``run.log`` and accumulates wall time per stage, in seconds.

    ``run.log`` is a log, not a result: it is appended as the run goes, so a killed run still says where it stopped.
    """

    def __init__(self, path: Path, append: bool = False) -> None:
        """``append``: continue an existing run.log (a resumed run) instead of starting a new one."""
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.stage_seconds: dict[str, float] = {}
        self.warnings = 0
        self._handler = logging.FileHandler(self.path, mode="a" if append else "w")
        self._handler.setFormatter(logging.Formatter(LOG_FORMAT))
        self._counter = _WarningCounter(self)
        self.logger = logging.getLogger("tambridge")
        self.logger.setLevel(logging.INFO)
        self.logger.addHandler(self._handler)
        self.logger.addHandler(self._counter)

    def __enter__(self) -> "RunLog":
        return self

    def __exit__(self, kind, error, traceback) -> None:
        if error is not None:
            self.record_stop(error)
        self.close()

    def add_seconds(self, stage: str, seconds: float) -> None:
        """Count ``seconds`` to ``stage`` (time spent before the log existed, or by the run a resumed one continues)."""
        self.stage_seconds[stage] = self.stage_seconds.get(stage, 0.0) + seconds

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time a stage; repeated entries of the same name add up."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.add_seconds(name, time.perf_counter() - start)

    def record_stop(self, error: BaseException) -> None:
        """Say in run.log (only there: the terminal gets the error itself) why and where the run stopped."""
        stages = ", ".join(self.stage_seconds) or "none"
        record = self.logger.makeRecord(
            self.logger.name, logging.ERROR, __file__, 0,
            "run stopped: %s: %s (stages entered: %s); outputs of this run are incomplete",
            (type(error).__name__, error, stages), None,
        )
        self._handler.handle(record)

    def close(self) -> None:
        self.logger.removeHandler(self._handler)
        self.logger.removeHandler(self._counter)
        self._handler.close()


class _WarningCounter(logging.Handler):
    def __init__(self, run_log: RunLog) -> None:
        super().__init__(level=logging.WARNING)
        self.run_log = run_log

    def emit(self, record: logging.LogRecord) -> None:
        self.run_log.warnings += 1
