"""Where a benchmark's independent jobs run: a spawn pool of ``workers`` processes (one torch thread
each, set by the job), or, for one worker, this process in order (so a single run is debuggable and
its prints come straight through)."""
from __future__ import annotations

import multiprocessing
from typing import Any


class InProcess:
    """A one-worker stand-in for the pool: the jobs run here, in order."""

    def __enter__(self) -> "InProcess":
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def imap_unordered(self, fn: Any, items: list[Any]) -> Any:
        return map(fn, items)


def job_pool(workers: int) -> Any:
    """A context manager with ``imap_unordered``: a spawn pool for ``workers > 1``, else :class:`InProcess`."""
    return multiprocessing.get_context("spawn").Pool(workers) if workers > 1 else InProcess()
