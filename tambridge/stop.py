"""Stopping a run by a signal (SIGTERM from a scheduler, SIGINT from Ctrl-C) without losing its work.

While frames are tracked the first signal is only noted: the tracking loop finishes the frame it is on, writes a
checkpoint and raises :class:`RunStopped`, so that ``--resume`` continues exactly there. Elsewhere, or at a
second signal, :class:`RunStopped` is raised at once (the latest checkpoint stays).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from typing import Iterator

from tambridge.errors import TambridgeError

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


class RunStopped(TambridgeError):
    """A run stopped by a signal; ``exit_status`` is the shell's 128 + the signal's number (143, 130).
    ``at_once``: raised where the signal came (its message says only that), not by a run that stopped between frames
    and said where."""

    def __init__(self, signum: int, message: str, at_once: bool = True) -> None:
        super().__init__(message)
        self.signum = signum
        self.exit_status = 128 + signum
        self.at_once = at_once


def signal_name(signum: int) -> str:
    return signal.Signals(signum).name


class StopRequests:
    """Installs handlers of :data:`STOP_SIGNALS` for the duration of a ``with`` block (in the main thread only: Python
    runs signal handlers there; elsewhere nothing is installed and signals keep their handlers)."""

    def __init__(self) -> None:
        self.requested: int | None = None
        self._deferring = False
        self._previous: dict[int, object] = {}

    def __enter__(self) -> "StopRequests":
        if threading.current_thread() is threading.main_thread():
            for signum in STOP_SIGNALS:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc_info) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()

    @contextlib.contextmanager
    def deferred(self) -> Iterator[None]:
        """Inside the block a first signal is only recorded in :attr:`requested`, for the caller to honour."""
        self._deferring = True
        try:
            yield
        finally:
            self._deferring = False

    def _handle(self, signum: int, frame) -> None:
        if self._deferring and self.requested is None:
            self.requested = signum
            return
        raise RunStopped(signum, f"stopped by {signal_name(signum)}")
