"""What both transports share: handles that close once, and the registry a transport closes on exit."""
from __future__ import annotations

import threading
from typing import Callable


class OnceHandle:
    """Closes once: runs ``undeclare`` and leaves the owning registry."""

    def __init__(self, undeclare: Callable[[], None], owner: "HandleRegistry") -> None:
        self._undeclare = undeclare
        self._owner = owner
        self._closed = False
        self._lock = threading.Lock()

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._undeclare()
        self._owner._forget(self)


class HandleRegistry:
    """The declared entities of one transport, so ``close()`` can undeclare everything it declared."""

    def __init__(self) -> None:
        self._handles: set[OnceHandle] = set()
        self._lock = threading.Lock()
        self._closed = False

    def _track(self, undeclare: Callable[[], None]) -> OnceHandle:
        handle = OnceHandle(undeclare, self)
        with self._lock:
            closed = self._closed
            if not closed:
                self._handles.add(handle)
        if closed:
            handle.close()
            raise RuntimeError("transport is closed")
        return handle

    def _forget(self, handle: OnceHandle) -> None:
        with self._lock:
            self._handles.discard(handle)

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("transport is closed")
