"""Capture on its own thread, so that reading frames and processing them overlap.

``FrameThread(frames, latest)`` iterates ``frames`` (any iterable, e.g. a
``sender.capture.Source`` of ``VideoFrame``) on a daemon thread and hands the items over in
order:

- ``latest=False`` (a file): through a queue of at most ``AHEAD`` items. The reader waits
  while the queue is full, so nothing is dropped, and decoding runs up to ``AHEAD`` frames
  ahead of the tracker (PyAV and OpenCV release the GIL while they decode).
- ``latest=True`` (a camera): only the newest item is held. One that the consumer has not
  taken when the next arrives is dropped and counted (``dropped``): a camera cannot wait,
  and a slow consumer then always gets the current frame, not the oldest one a driver's
  buffer would hand out.

An exception raised by the reader reaches the consumer after the items read before it, from
``next``. ``close`` (or leaving ``with``) tells the reader to stop and waits up to
``JOIN_S`` for it (it notices after its current read), so that the source can be closed
after it; the thread is a daemon, so a reader stuck in a device read cannot keep the
process alive.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Iterable, Iterator
from typing import Generic, Self, TypeVar

AHEAD = 4
JOIN_S = 2.0

T = TypeVar("T")


class FrameThread(Generic[T]):
    """Iterate ``frames`` on a reader thread (module docstring).

    Args:
        frames: what to read, on the reader thread only.
        latest: keep only the newest item (a camera), else queue up to ``ahead`` (a file).
        ahead: the queue's size when not ``latest``, >= 1.

    Raises:
        ValueError: ``ahead`` < 1.
    """

    def __init__(self, frames: Iterable[T], latest: bool, ahead: int = AHEAD) -> None:
        if ahead < 1:
            raise ValueError(f"ahead: expected >= 1, got {ahead}")
        self._frames = frames
        self._latest = latest
        self._ahead = ahead
        self._items: deque[T] = deque()
        self._cond = threading.Condition()
        self._done = False
        self._closed = False
        self._error: BaseException | None = None
        self.dropped = 0
        self._thread = threading.Thread(target=self._read, name="facewire capture",
                                        daemon=True)
        self._thread.start()

    def _read(self) -> None:
        try:
            for item in self._frames:
                with self._cond:
                    while not self._latest and len(self._items) >= self._ahead \
                            and not self._closed:
                        self._cond.wait()
                    if self._closed:
                        return
                    if self._latest and self._items:
                        self.dropped += len(self._items)
                        self._items.clear()
                    self._items.append(item)
                    self._cond.notify_all()
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer by __next__
            with self._cond:
                self._error = exc
        finally:
            with self._cond:
                self._done = True
                self._cond.notify_all()

    def __iter__(self) -> Iterator[T]:
        return self

    def __next__(self) -> T:
        with self._cond:
            while not self._items and not self._done:
                self._cond.wait()
            if self._items:
                item = self._items.popleft()
                self._cond.notify_all()
                return item
            if self._error is not None:
                error, self._error = self._error, None
                raise error
            raise StopIteration

    def close(self) -> None:
        """Stop the reader and wait up to ``JOIN_S`` for it (again: no effect)."""
        with self._cond:
            self._closed = True
            self._items.clear()
            self._cond.notify_all()
        if self._thread is not threading.current_thread():
            self._thread.join(JOIN_S)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
