"""Read (and prepare) the next frame of a sequence in a worker thread while the caller works on the current one.

Decoding the PNGs of a 640x480 frame and extracting its ORB features take about as long as tracking it, and
both run mostly in cv2, which releases the GIL: done one frame ahead in a single worker thread, they overlap
tracking on a second core, where one is free. Frames come out in order and each one exactly as ``sequence[index]`` gives it, so results
do not change; an error reading or preparing a frame is raised when the caller reaches that frame.
"""

from __future__ import annotations

import concurrent.futures
from typing import Callable, Generic, Iterator, TypeVar

from tambridge.io.tum import Frame, RgbdSequence

Prepared = TypeVar("Prepared")


class FramePrefetcher(Generic[Prepared]):
    """Iterate ``(frame, prepare(frame))`` over frames ``start..len(sequence)-1`` with frame i+1 read and prepared
    in a worker thread while the caller has frame i; ``prepare=None`` only reads ahead (the second item is None).

    Use it as a context manager: leaving it (also on an error) cancels the read-ahead and waits for the worker,
    so nothing runs in the background afterwards. ``prepare`` runs in the worker thread, one frame at a time, in
    order; it must not touch state the caller changes meanwhile. ``read_ahead=False`` reads and prepares each
    frame in the caller's thread when it is asked for (no worker).
    """

    def __init__(self, sequence: RgbdSequence, start: int = 0, prepare: Callable[[Frame], Prepared] | None = None,
                 read_ahead: bool = True) -> None:
        self.sequence = sequence
        self.start = start
        self.prepare = prepare
        self._executor = None
        if read_ahead:
            self._executor = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="tambridge-prefetch")

    def _load(self, index: int) -> tuple[Frame, Prepared | None]:
        frame = self.sequence[index]
        return frame, None if self.prepare is None else self.prepare(frame)

    def __iter__(self) -> Iterator[tuple[Frame, Prepared | None]]:
        indices = range(self.start, len(self.sequence))
        if self._executor is None:
            yield from (self._load(index) for index in indices)
            return
        pending = self._executor.submit(self._load, indices[0]) if indices else None
        for index in indices:
            current = pending
            # Queued before the caller gets frame i: the worker reads i+1 while the caller tracks i.
            pending = self._executor.submit(self._load, index + 1) if index + 1 < len(self.sequence) else None
            yield current.result()

    def close(self) -> None:
        """Drop the frame read ahead and wait for the worker thread to end (idempotent)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> "FramePrefetcher[Prepared]":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()
