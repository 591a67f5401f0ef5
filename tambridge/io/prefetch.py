"""Read (and prepare) the next frame of a sequence in a worker thread while the caller works on the current one.

Decoding the images of a 640x480 frame (and resampling unregistered colour) and extracting its ORB features take
about as long as tracking it, and run mostly in cv2 and numba, which release the GIL: reading two frames ahead in
one worker thread and preparing one frame ahead in another, they overlap tracking where a core is free. Frames come
out in order and each one exactly as ``sequence[index]`` gives it, so results do not change; an error reading or
preparing a frame is raised when the caller reaches that frame. The reader also scores each frame's sharpness
(:func:`tambridge.images.sharpness`, on a thumbnail) for the Fusion Bridge's view selection.
"""

from __future__ import annotations

import collections
import concurrent.futures
from typing import Callable, Generic, Iterator, Sequence, TypeVar

from tambridge.images import sharpness
from tambridge.io.tum import Frame, RgbdSequence

Prepared = TypeVar("Prepared")
Item = TypeVar("Item")
Read = TypeVar("Read")


class FramePrefetcher(Generic[Prepared]):
    """Iterate ``(frame, prepare(frame))`` over frames ``start..len(sequence)-1``: while the caller has frame i, a
    reader thread reads frame i+2 and a preparer thread prepares frame i+1; ``prepare=None`` only reads ahead (the
    second item is None, and there is no preparer thread).

    Use it as a context manager: leaving it (also on an error) cancels the read-ahead and waits for the workers,
    so nothing runs in the background afterwards. ``prepare`` runs in the preparer thread, one frame at a time, in
    order; it must not touch state the caller changes meanwhile (a frontend's ``extract``). ``read_ahead=False``
    reads and prepares each frame in the caller's thread when it is asked for (no worker). ``sharpness[i]`` holds
    frame i's :func:`tambridge.images.sharpness` once the iterator has yielded it.
    """

    def __init__(self, sequence: RgbdSequence, start: int = 0, prepare: Callable[[Frame], Prepared] | None = None,
                 read_ahead: bool = True) -> None:
        self.sequence = sequence
        self.start = start
        self.prepare = prepare
        self._reader = _worker("read") if read_ahead else None
        self._preparer = _worker("prepare") if read_ahead and prepare is not None else None
        self.sharpness: dict[int, float] = {}

    def _read(self, index: int) -> Frame:
        """The reader's task: frame ``index`` as the sequence gives it, its sharpness noted on the way."""
        frame = self.sequence[index]
        self.sharpness[index] = sharpness(frame.rgb)
        return frame

    def _prepared(self, frame: Frame) -> tuple[Frame, Prepared | None]:
        return frame, None if self.prepare is None else self.prepare(frame)

    def _prepared_read(self, read: concurrent.futures.Future) -> tuple[Frame, Prepared | None]:
        """The preparer thread's task: wait for the reader's frame, then prepare it."""
        return self._prepared(read.result())

    def _prepare_later(self, read: concurrent.futures.Future) -> concurrent.futures.Future:
        """The future of ``(frame, prepared)`` once ``read`` has the frame; without a preparer, ``read`` itself."""
        return read if self._preparer is None else self._preparer.submit(self._prepared_read, read)

    def __iter__(self) -> Iterator[tuple[Frame, Prepared | None]]:
        indices = range(self.start, len(self.sequence))
        reader = self._reader
        if reader is None:
            yield from (self._prepared(self._read(index)) for index in indices)
            return
        reads = {index: reader.submit(self._read, index) for index in indices[:2]}
        pending = self._prepare_later(reads.pop(indices[0])) if indices else None
        for index in indices:
            current = pending
            # Queued before the caller gets frame i: i+2 is read and i+1 prepared while the caller tracks i.
            if index + 2 < len(self.sequence):
                reads[index + 2] = reader.submit(self._read, index + 2)
            if index + 1 < len(self.sequence):
                pending = self._prepare_later(reads.pop(index + 1))
            yield self._prepared(current.result()) if self._preparer is None else current.result()

    def close(self) -> None:
        """Drop the frames read ahead and wait for the worker threads to end (idempotent)."""
        for executor in (self._reader, self._preparer):
            if executor is not None:
                executor.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> "FramePrefetcher[Prepared]":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


class ReadAhead(Generic[Item, Read]):
    """Iterate ``read(item)`` over ``items`` in their order, while the caller has one result the next ``ahead``
    items being read in a worker thread (``ahead=0``: each read in the caller's thread when it is asked for). Each
    result is exactly what ``read(item)`` gives; an error reading an item is raised when the caller reaches it.
    Use it as a context manager, as :class:`FramePrefetcher`: leaving it cancels what was read ahead and waits for
    the worker. At most ``ahead + 1`` results are held at a time, the caller's included."""

    def __init__(self, items: Sequence[Item], read: Callable[[Item], Read], ahead: int = 2) -> None:
        self.items = list(items)
        self.read = read
        self.ahead = ahead
        self._reader = _worker("read-ahead") if ahead > 0 else None

    def __iter__(self) -> Iterator[Read]:
        if self._reader is None:
            yield from (self.read(item) for item in self.items)
            return
        reads = collections.deque(self._reader.submit(self.read, item) for item in self.items[:self.ahead])
        for index in range(len(self.items)):
            # Queued before the caller gets item i: items i+1..i+ahead are read while the caller works on it.
            if index + self.ahead < len(self.items):
                reads.append(self._reader.submit(self.read, self.items[index + self.ahead]))
            yield reads.popleft().result()

    def close(self) -> None:
        """Drop what was read ahead and wait for the worker to end (idempotent)."""
        if self._reader is not None:
            self._reader.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> "ReadAhead[Item, Read]":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def _worker(role: str) -> concurrent.futures.ThreadPoolExecutor:
    return concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"tambridge-prefetch-{role}")
