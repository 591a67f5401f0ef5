"""Read (and prepare) the next frame of a sequence in a worker thread while the caller works on the current one.

Decoding the images of a 640x480 frame (and resampling unregistered colour) and extracting its ORB features take
about as long as tracking it, and run mostly in cv2 and numba, which release the GIL: reading :data:`FRAMES_AHEAD`
frames ahead in one worker thread and preparing them in another, they overlap tracking where a core is free. Frames
come out in order and each one exactly as ``sequence[index]`` gives it, so results do not change; an error reading or
preparing a frame is raised when the caller reaches that frame. The reader also scores each frame's sharpness
(:func:`tambridge.images.sharpness`, on a thumbnail) for the Fusion Bridge's view selection.
"""

from __future__ import annotations

import collections
import concurrent.futures
from typing import Any, Callable, Generic, Iterator, Sequence, TypeVar

from tambridge.images import sharpness
from tambridge.io.tum import Frame, RgbdSequence

Prepared = TypeVar("Prepared")
Item = TypeVar("Item")
Read = TypeVar("Read")


class ReadAhead(Generic[Item, Read]):
    """Iterate ``read(item)`` over ``items`` in their order, or with ``then`` ``then(read(item))``: while the caller
    has one result, the next ``ahead`` items are read in a worker thread and ``then`` runs on them in a second one,
    in order (``ahead=0``: each item read, and ``then`` run, in the caller's thread when it is asked for). Each
    result is exactly what the calls give; an error in either is raised when the caller reaches that item.

    Use it as a context manager: leaving it (also on an error) cancels what was read ahead and waits for the
    workers, so nothing runs in the background afterwards. At most ``ahead + 1`` results are held at a time, the
    caller's included. ``then`` must not touch state the caller changes meanwhile (a frontend's ``extract``).
    """

    def __init__(self, items: Sequence[Item], read: Callable[[Item], Read], ahead: int = 2,
                 then: Callable[[Read], Any] | None = None) -> None:
        self.items = list(items)
        self.read = read
        self.then = then
        self.ahead = ahead
        self._reader = _worker("read") if ahead > 0 else None
        self._preparer = _worker("prepare") if ahead > 0 and then is not None else None

    def _inline(self, item: Item) -> Any:
        value = self.read(item)
        return value if self.then is None else self.then(value)

    def _queue(self, item: Item) -> concurrent.futures.Future:
        """The future of item's result: read by the reader, then (with ``then``) passed on to the preparer."""
        read = self._reader.submit(self.read, item)
        if self._preparer is None:
            return read
        return self._preparer.submit(lambda: self.then(read.result()))

    def __iter__(self) -> Iterator[Any]:
        if self._reader is None:
            yield from map(self._inline, self.items)
            return
        queued = collections.deque(self._queue(item) for item in self.items[:self.ahead])
        for index in range(len(self.items)):
            # Queued before the caller gets item i: items i+1..i+ahead are worked on while the caller has it.
            if index + self.ahead < len(self.items):
                queued.append(self._queue(self.items[index + self.ahead]))
            yield queued.popleft().result()

    def close(self) -> None:
        """Drop what was queued and wait for the workers to end (idempotent)."""
        for executor in (self._reader, self._preparer):
            if executor is not None:
                executor.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> "ReadAhead[Item, Read]":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


FRAMES_AHEAD = 5
"""Frames :class:`FramePrefetcher` reads and prepares ahead of the one being tracked. Tracking slows at each keyframe
(it waits for the keyframe's fusion) and the two workers fall behind while the mapping thread takes a core; frames
read ahead (a few MB each) carry tracking over those bursts without waiting (docs/benchmarks.md)."""


class FramePrefetcher(Generic[Prepared]):
    """Iterate ``(frame, prepare(frame))`` over frames ``start..len(sequence)-1`` (:class:`ReadAhead`
    :data:`FRAMES_AHEAD` frames ahead: while the caller has frame i, the next ones are read in one worker thread and
    prepared in another);
    ``prepare=None`` only reads ahead (the second item is None, and there is no preparer thread);
    ``read_ahead=False`` reads and prepares each frame in the caller's thread when it is asked for. A context
    manager as :class:`ReadAhead`. ``sharpness[i]`` holds frame i's :func:`tambridge.images.sharpness` once the
    iterator has yielded it.
    """

    def __init__(self, sequence: RgbdSequence, start: int = 0, prepare: Callable[[Frame], Prepared] | None = None,
                 read_ahead: bool = True) -> None:
        self.sequence = sequence
        self.prepare = prepare
        self.sharpness: dict[int, float] = {}
        self._frames = ReadAhead(range(start, len(sequence)), self._read, FRAMES_AHEAD if read_ahead else 0,
                                 None if prepare is None else self._prepared)

    def _read(self, index: int) -> Frame:
        """The reader's task: frame ``index`` as the sequence gives it, its sharpness noted on the way."""
        frame = self.sequence[index]
        self.sharpness[index] = sharpness(frame.rgb)
        return frame

    def _prepared(self, frame: Frame) -> tuple[Frame, Prepared]:
        return frame, self.prepare(frame)

    def __iter__(self) -> Iterator[tuple[Frame, Prepared | None]]:
        if self.prepare is None:
            return ((frame, None) for frame in self._frames)
        return iter(self._frames)

    def close(self) -> None:
        """Drop the frames read ahead and wait for the worker threads to end (idempotent)."""
        self._frames.close()

    def __enter__(self) -> "FramePrefetcher[Prepared]":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def _worker(role: str) -> concurrent.futures.ThreadPoolExecutor:
    return concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"tambridge-prefetch-{role}")
