"""Progress on long work (a build, an encode, a benchmark), shown or not as the caller likes.

A ``Progress`` wraps an iterable and yields its items unchanged: ``progress(items, label,
total)``, with ``label`` what is being done ("tracking", "encoding") and ``total`` the number
of items when known (None otherwise). The command line passes a progress bar on stderr;
library callers and tests get ``no_progress``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")
Progress = Callable[[Iterable[T], str, "int | None"], Iterable[T]]


def no_progress(items: Iterable[T], label: str, total: int | None) -> Iterator[T]:
    """Show nothing: the items, unchanged."""
    return iter(items)
