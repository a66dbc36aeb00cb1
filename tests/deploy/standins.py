"""Images for the compose smoke test where no registry can be reached, and the project image.

- ``python:3.11-slim`` (the base of ``deploy/Dockerfile``): a debootstrapped Debian bookworm with
  its Python 3.11 (headers included, as in the upstream image), the machine's CA certificates and
  ``PIP_CERT`` so builds on the host network reach PyPI through this machine's TLS proxy.
- ``prom/prometheus:<tag of compose.yaml>``: Debian's ``prometheus`` binary (2.42) on the same
  Debian, run the way the upstream image runs it (entrypoint, ``/prometheus`` owned by nobody,
  busybox-like ``wget`` for the healthcheck).
- ``causeway:local``: built with the real ``deploy/Dockerfile`` on the host network; torch comes from
  pip's local find-links directory, served over HTTP on loopback for the build (``TORCH_PIP_ARGS``).

Stand-ins are made once per machine and kept with ``docker save`` in the cache directory
(``$CAUSEWAY_COMPOSE_CACHE``, default ``~/.cache/causeway/compose-test``); the project image and its
build stage are kept there too and given to the next build as ``--cache-from``.
"""
from __future__ import annotations

import functools
import hashlib
import http.server
import os
import re
import shutil
import subprocess
import tempfile
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from tests.deploy import REPO
from tests.deploy.engine import Engine, run_logged

CACHE = Path(os.environ.get("CAUSEWAY_COMPOSE_CACHE") or Path.home() / ".cache" / "causeway" / "compose-test")
DEBIAN_MIRROR = "http://deb.debian.org/debian"
SUITE = "bookworm"
PACKAGES = ("python3", "python3-venv", "python3-dev", "python-is-python3", "ca-certificates", "wget")
CA_DIR = Path("/usr/local/share/ca-certificates")
DEBIAN_STANDIN = "causeway-standin/debian:bookworm"
PROJECT_IMAGE = "causeway:local"
BUILD_STAGE_IMAGE = "causeway:build-stage"


@dataclass
class BuildTimes:
    """Seconds spent on each step (0 where a cached result was used)."""

    debootstrap_s: float = 0.0
    standins_s: float = 0.0
    load_s: float = 0.0
    project_s: float = 0.0
    save_s: float = 0.0
    base_cached: bool = False
    project_cached: bool = False


def base_image_names() -> tuple[str, str]:
    """The Dockerfile's base image and compose.yaml's Prometheus image, as the files name them."""
    bases = set(re.findall(r"^FROM\s+(\S+)", (REPO / "deploy" / "Dockerfile").read_text(), re.M))
    bases = {b for b in bases if ":" in b}
    prometheus = re.search(r"image:\s*(prom/prometheus:\S+)", (REPO / "compose.yaml").read_text())
    assert len(bases) == 1 and prometheus, (bases, prometheus)
    return bases.pop(), prometheus.group(1)


def _cache_key() -> str:
    python_base, prometheus = base_image_names()
    digest = hashlib.sha256(repr((SUITE, PACKAGES, python_base, prometheus, _STANDIN_DOCKERFILES)).encode())
    for cert in sorted(CA_DIR.glob("*.crt")):
        digest.update(cert.read_bytes())
    prometheus_binary = shutil.which("prometheus")
    if prometheus_binary:
        digest.update(str(os.stat(prometheus_binary).st_size).encode())
    return digest.hexdigest()[:16]


def ensure_base_images(engine: Engine, log: Path, times: BuildTimes) -> None:
    """The stand-in base images in ``engine``: loaded from the cache, or made and then cached."""
    CACHE.mkdir(parents=True, exist_ok=True)
    saved = CACHE / f"base-images-{_cache_key()}.tar"
    if saved.exists():
        started = time.monotonic()
        engine.docker("load", "-i", str(saved), timeout=600)
        times.load_s += time.monotonic() - started
        times.base_cached = True
        return
    with tempfile.TemporaryDirectory(dir=CACHE, prefix="rootfs-") as tmp:
        rootfs = Path(tmp) / "rootfs"
        times.debootstrap_s = _debootstrap(rootfs, log)
        started = time.monotonic()
        tar = subprocess.Popen(["tar", "-C", str(rootfs), "-c", "."], stdout=subprocess.PIPE)
        engine.docker("import", "-c", "ENV LANG=C.UTF-8", "-c", "CMD [\"bash\"]", "-", DEBIAN_STANDIN,
                      input=tar.stdout.read(), timeout=600)
        tar.wait(timeout=60)
    python_base, prometheus = base_image_names()
    _build_standin(engine, "python", python_base, log)
    _build_standin(engine, "prometheus", prometheus, log, files={"prometheus": shutil.which("prometheus")})
    times.standins_s = time.monotonic() - started
    for old in CACHE.glob("base-images-*.tar"):
        old.unlink()
    _save(engine, saved, [DEBIAN_STANDIN, python_base, prometheus], log)


def _debootstrap(rootfs: Path, log: Path) -> float:
    started = time.monotonic()
    run_logged(["debootstrap", "--variant=minbase", f"--include={','.join(PACKAGES)}", SUITE, str(rootfs),
                DEBIAN_MIRROR], log, timeout=1200)
    for cert in CA_DIR.glob("*.crt"):
        shutil.copy(cert, rootfs / "usr/local/share/ca-certificates" / cert.name)
    run_logged(["chroot", str(rootfs), "update-ca-certificates"], log, timeout=120)
    run_logged(["chroot", str(rootfs), "apt-get", "clean"], log, timeout=120)
    shutil.rmtree(rootfs / "var/lib/apt/lists", ignore_errors=True)
    (rootfs / "var/lib/apt/lists/partial").mkdir(parents=True)
    return time.monotonic() - started


_STANDIN_DOCKERFILES = {
    # python:3.11-slim has no wget; PIP_CERT: pip's own CA bundle lacks this machine's proxy CA.
    "python": f"""FROM {DEBIAN_STANDIN}
RUN rm -f /usr/bin/wget
ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt PYTHONDONTWRITEBYTECODE=1
CMD ["python3"]
""",
    # As the upstream image: binary in /bin, data in /prometheus owned by nobody, same entrypoint.
    "prometheus": f"""FROM {DEBIAN_STANDIN}
COPY prometheus /bin/prometheus
RUN mkdir -p /etc/prometheus /prometheus && chown nobody:nogroup /prometheus
USER nobody
WORKDIR /prometheus
VOLUME ["/prometheus"]
EXPOSE 9090
ENTRYPOINT ["/bin/prometheus"]
CMD ["--config.file=/etc/prometheus/prometheus.yml", "--storage.tsdb.path=/prometheus"]
""",
}


def _build_standin(engine: Engine, kind: str, tag: str, log: Path, files: dict[str, str | None] | None = None) -> None:
    with tempfile.TemporaryDirectory(prefix=f"standin-{kind}-") as context:
        (Path(context) / "Dockerfile").write_text(_STANDIN_DOCKERFILES[kind])
        for name, source in (files or {}).items():
            if source is None:
                raise RuntimeError(f"{name} is not installed (make sysdeps installs it)")
            shutil.copy(source, Path(context) / name)
        run_logged(["docker", "build", "--network", "none", "-t", tag, context], log, timeout=300,
                   env=engine.environ())


SAVE_HEADROOM = 2.0
"""A cache is written only where the disk keeps this many times the images' size free (the images'
size is uncompressed and ``docker save`` writes about that much)."""


def _save(engine: Engine, target: Path, images: list[str], log: Path) -> float:
    """Keep ``images`` in ``target`` for the next run; seconds spent, 0 where nothing was kept.

    The cache only saves time, so a disk too full to hold it (a CI machine has been seen with under
    300 MB free) skips it, and a save that fails anyway is dropped, both with a line in ``log``:
    neither fails the test. The old ``target`` goes first, so its space counts as free."""
    started = time.monotonic()
    target.unlink(missing_ok=True)
    partial = target.with_suffix(".partial")
    need = SAVE_HEADROOM * sum(_image_sizes(engine, images))
    free = shutil.disk_usage(target.parent).free
    if free < need:
        _note(log, f"cache {target.name} not written: {free / 2**20:.0f} MiB free, "
                   f"{need / 2**20:.0f} MiB wanted ({SAVE_HEADROOM:g}x the images)")
        return 0.0
    try:
        engine.docker("save", "-o", str(partial), *images, timeout=900)
    except (RuntimeError, subprocess.TimeoutExpired) as exc:
        for leftover in (partial, *target.parent.glob(f".tmp-{partial.name}*")):
            leftover.unlink(missing_ok=True)
        _note(log, f"cache {target.name} not written: {exc}")
        return 0.0
    os.replace(partial, target)
    return time.monotonic() - started


def _image_sizes(engine: Engine, images: list[str]) -> list[int]:
    sizes = []
    for image in images:
        out = engine.docker("image", "inspect", "-f", "{{.Size}}", image, check=False).stdout.decode().strip()
        sizes.append(int(out) if out.isdigit() else 0)
    return sizes


def _note(log: Path, line: str) -> None:
    with open(log, "a") as out:
        out.write(f"\n# {line}\n")


def find_links_dir() -> Path:
    """pip's local find-links directory (``pip config list``), where the CPU torch wheel lies."""
    result = subprocess.run([str(REPO / ".venv" / "bin" / "python"), "-m", "pip", "config", "list"],
                            capture_output=True, text=True, timeout=60)
    for line in result.stdout.splitlines():
        key, _, value = line.partition("=")
        if key.endswith(".find-links"):
            for candidate in value.strip("'\"").split():
                if list(Path(candidate).glob("torch-*.whl")):
                    return Path(candidate)
    raise RuntimeError(f"no find-links directory with a torch wheel in `pip config list`:\n{result.stdout}")


WHEELS_PORT = 47391
"""The find-links URL is a build argument, part of the torch layer's cache key: a fixed port keeps
it the same from run to run (a random one rebuilt torch and everything after it every time)."""


@contextmanager
def serve_directory(directory: Path) -> Iterator[str]:
    """An HTTP listing of ``directory`` on 127.0.0.1 (a pip find-links page) while the block runs."""
    handler = functools.partial(_QuietHandler, directory=str(directory))
    try:
        server = http.server.ThreadingHTTPServer(("127.0.0.1", WHEELS_PORT), handler)
    except OSError:  # taken: any port works, only the build cache is lost
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args: object) -> None:
        pass


def build_project_image(engine: Engine, log: Path, times: BuildTimes) -> None:
    """``causeway:local`` from ``deploy/Dockerfile`` (host network, torch from the local wheel directory)."""
    saved = CACHE / "project-images.tar"
    cache_from: list[str] = []
    if saved.exists():
        started = time.monotonic()
        if engine.docker("load", "-i", str(saved), timeout=900, check=False).returncode == 0:
            cache_from = ["--cache-from", BUILD_STAGE_IMAGE, "--cache-from", PROJECT_IMAGE]
        times.load_s += time.monotonic() - started
    before = _image_ids(engine, [BUILD_STAGE_IMAGE, PROJECT_IMAGE])
    started = time.monotonic()
    with serve_directory(find_links_dir()) as wheels, tempfile.TemporaryDirectory(prefix="causeway-context-") as tmp:
        context = snapshot_worktree(Path(tmp))
        common = ["docker", "build", "--network", "host", "-f", str(context / "deploy" / "Dockerfile"), *cache_from,
                  "--build-arg", f"TORCH_PIP_ARGS=--find-links {wheels}"]
        run_logged([*common, "--target", "build", "-t", BUILD_STAGE_IMAGE, str(context)], log, timeout=2400,
                   env=engine.environ())
        run_logged([*common, "-t", PROJECT_IMAGE, str(context)], log, timeout=1200, env=engine.environ())
    times.project_s = time.monotonic() - started
    after = _image_ids(engine, [BUILD_STAGE_IMAGE, PROJECT_IMAGE])
    times.project_cached = bool(cache_from) and after == before
    if after != before:
        times.save_s = _save(engine, saved, [BUILD_STAGE_IMAGE, PROJECT_IMAGE], log)


def snapshot_worktree(target: Path) -> Path:
    """A copy of the files git would see (tracked and untracked, ignored left out) under ``target``.

    Both builds read this one copy: the working tree may change between them (others edit it)."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                            capture_output=True, check=True, timeout=60).stdout.decode().split("\0")
    for name in filter(None, listed):
        source = REPO / name
        if source.is_file():
            (target / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target / name)
    return target


def _image_ids(engine: Engine, images: list[str]) -> list[str]:
    return [engine.docker("image", "inspect", "-f", "{{.Id}}", image, check=False).stdout.decode().strip()
            for image in images]

