"""The compose test's image cache is best effort: a full disk costs the next run time, never the test.

A CI run once failed all eight stack tests at ``docker save`` ("no space left on device") after the
images had built. The engine here is a stand-in for the ``docker`` CLI, because a disk that fills at
the right moment cannot be arranged; the real save is exercised by tests/deploy/test_compose_stack.py.
"""
from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from tests.deploy import standins


class _Docker:
    """Answers ``image inspect`` with fixed sizes; ``save`` writes the file or fails like a full disk."""

    def __init__(self, size: int, fail: bool) -> None:
        self.size, self.fail, self.calls = size, fail, []

    def docker(self, *args: str, check: bool = True, timeout: float = 120) -> subprocess.CompletedProcess:
        self.calls.append(args[0])
        if args[:2] == ("image", "inspect"):
            return subprocess.CompletedProcess(args, 0, stdout=f"{self.size}\n".encode(), stderr=b"")
        assert args[0] == "save"
        partial = Path(args[2])
        (partial.parent / f".tmp-{partial.name}123").write_bytes(b"half")
        if self.fail:
            raise RuntimeError(f"docker save failed (1): write {partial}: no space left on device")
        partial.write_bytes(b"images")
        return subprocess.CompletedProcess(args, 0, stdout=b"", stderr=b"")


def test_a_save_that_fails_leaves_no_partial_file_and_a_line_in_the_log(tmp_path: Path) -> None:
    target, log = tmp_path / "project-images.tar", tmp_path / "build.log"
    target.write_bytes(b"an older cache")
    assert standins._save(_Docker(size=1, fail=True), target, ["a", "b"], log) == 0.0
    assert list(tmp_path.iterdir()) == [log]
    assert "no space left on device" in log.read_text()


def test_a_disk_without_room_for_the_images_is_not_written_to(tmp_path: Path) -> None:
    target, log = tmp_path / "base-images.tar", tmp_path / "build.log"
    engine = _Docker(size=2**62, fail=False)
    assert standins._save(engine, target, ["a"], log) == 0.0
    assert "save" not in engine.calls and not target.exists()
    assert "MiB free" in log.read_text()


def test_a_save_with_room_replaces_the_cache(tmp_path: Path) -> None:
    target, log = tmp_path / "project-images.tar", tmp_path / "build.log"
    target.write_bytes(b"an older cache")
    assert standins._save(_Docker(size=1, fail=False), target, ["a"], log) >= 0.0
    assert target.read_bytes() == b"images"
    assert not target.with_suffix(".partial").exists()


@pytest.mark.parametrize("error", [RuntimeError("boom"), subprocess.TimeoutExpired(["docker"], 900)])
def test_any_failed_save_is_dropped(tmp_path: Path, error: Exception) -> None:
    class Failing(_Docker):
        def docker(self, *args: str, check: bool = True, timeout: float = 120) -> subprocess.CompletedProcess:
            if args[0] == "save":
                raise error
            return super().docker(*args, check=check, timeout=timeout)

    log = tmp_path / "build.log"
    assert standins._save(Failing(size=1, fail=False), tmp_path / "x.tar", ["a"], log) == 0.0
    assert list(tmp_path.iterdir()) == [log]
