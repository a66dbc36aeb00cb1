"""Polling for the integration tests: wait until a condition holds, or fail saying what was awaited."""
from __future__ import annotations

import time
from typing import Callable, TypeVar

T = TypeVar("T")


def wait_for(predicate: Callable[[], T], timeout: float, what: str, interval: float = 0.2,
             tolerate: tuple[type[BaseException], ...] = ()) -> T:
    """``predicate()``'s first truthy value, polled every ``interval`` s; ``AssertionError`` after
    ``timeout`` s. Exceptions of the ``tolerate`` types (say, a server not listening yet) count as
    not yet."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            value = predicate()
        except tolerate:
            value = None
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout}s waiting for {what}")
