"""Headless Chromium driven over the DevTools protocol on a pipe: no WebDriver, no websocket, no new package.

``--remote-debugging-pipe`` makes Chromium read protocol commands from fd 3 and write replies to fd 4,
each a JSON object ended by a NUL byte (what Puppeteer's ``pipe: true`` does). A ``bash -c 'exec ...'``
puts our pipe ends on fds 3 and 4, so nothing Python-level runs between fork and exec (``preexec_fn``
is unsafe here: the test process has Zenoh threads).
"""
from __future__ import annotations

import base64
import fcntl
import json
import os
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

CHROMIUM = Path("/usr/bin/chromium")
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars", "--remote-debugging-pipe")


class BrowserError(RuntimeError):
    pass


def _high_fd(fd: int) -> int:
    """``fd`` moved to a number >= 10, so the shell's 3/4 redirections never collide with it."""
    high = fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10)
    os.close(fd)
    return high


class Browser:
    """One headless Chromium with one page; ``call`` sends a DevTools command to that page."""

    def __init__(self, width: int = 1440, height: int = 1000, log_path: Path | None = None) -> None:
        self.width = width
        self.profile = tempfile.TemporaryDirectory(prefix="causeway-chromium-", ignore_cleanup_errors=True)
        child_in, self._to_browser = (_high_fd(fd) for fd in os.pipe())
        self._from_browser, child_out = (_high_fd(fd) for fd in os.pipe())
        script = f'exec "$0" "$@" 3<&{child_in} 4>&{child_out} {child_in}<&- {child_out}>&-'
        args = ["/bin/bash", "-c", script, str(CHROMIUM), *FLAGS, f"--user-data-dir={self.profile.name}",
                f"--window-size={width},{height}", "about:blank"]
        self.log_path = log_path or Path(self.profile.name) / "chromium.log"
        with open(self.log_path, "wb") as log:
            self.process = subprocess.Popen(args, pass_fds=(child_in, child_out), stdin=subprocess.DEVNULL,
                                            stdout=log, stderr=subprocess.STDOUT)
        os.close(child_in)
        os.close(child_out)
        self._next_id = 0
        self._replies: dict[int, dict] = {}
        self._arrived = threading.Condition()
        self.exceptions: list[str] = []
        self._reader = threading.Thread(target=self._read, name="cdp-reader", daemon=True)
        self._reader.start()
        target = self._call("Target.createTarget", {"url": "about:blank"})["targetId"]
        self.session = self._call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        for method in ("Page.enable", "Runtime.enable"):
            self.call(method)
        self.call("Emulation.setDeviceMetricsOverride",
                  {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False})

    # ------------------------------------------------------------------ protocol

    def _read(self) -> None:
        buffer = b""
        while chunk := os.read(self._from_browser, 1 << 20):
            buffer += chunk
            *messages, buffer = buffer.split(b"\0")
            for raw in messages:
                self._dispatch(json.loads(raw))
        with self._arrived:
            self._arrived.notify_all()

    def _dispatch(self, message: dict) -> None:
        if message.get("method") == "Runtime.exceptionThrown":
            details = message["params"]["exceptionDetails"]
            self.exceptions.append(details.get("exception", {}).get("description") or details.get("text", ""))
        if "id" in message:
            with self._arrived:
                self._replies[message["id"]] = message
                self._arrived.notify_all()

    def _call(self, method: str, params: dict | None = None, session: str | None = None,
              timeout: float = 15.0) -> dict:
        self._next_id += 1
        ident = self._next_id
        message: dict[str, Any] = {"id": ident, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = session
        data = memoryview(json.dumps(message).encode() + b"\0")
        while data:
            data = data[os.write(self._to_browser, data):]
        with self._arrived:
            if not self._arrived.wait_for(lambda: ident in self._replies or not self._reader.is_alive(), timeout):
                raise BrowserError(f"{method}: no reply in {timeout}s")
            reply = self._replies.pop(ident, None)
        if reply is None:
            raise BrowserError(f"{method}: Chromium exited; see {self.log_path}")
        if "error" in reply:
            raise BrowserError(f"{method}: {reply['error']}")
        return reply["result"]

    def call(self, method: str, params: dict | None = None, timeout: float = 15.0) -> dict:
        """A DevTools command on the page."""
        return self._call(method, params, self.session, timeout)

    # ------------------------------------------------------------------ page helpers

    def navigate(self, url: str, timeout: float = 10.0) -> None:
        """Load ``url`` and wait until its document is complete."""
        self.call("Page.navigate", {"url": url})
        self.wait_for(f"location.href === {json.dumps(url)} && document.readyState === 'complete'", timeout,
                      f"{url} to load")

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (JSON-able values only)."""
        result = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                                "awaitPromise": True})
        if "exceptionDetails" in result:
            raise BrowserError(f"{expression!r}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def wait_for(self, expression: str, timeout: float, what: str) -> Any:
        """Poll ``expression`` until it is truthy; returns its value."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                value, error = self.evaluate(expression), None
            except BrowserError as exc:  # e.g. the element is not there yet
                value, error = None, exc
            if value:
                return value
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout}s waiting for {what} ({expression}); last: {error}")
            time.sleep(0.05)

    def hover(self, selector: str) -> None:
        """Move the mouse onto the centre of the first element matching ``selector``."""
        box = self.evaluate(f"(() => {{ const e = document.querySelector({json.dumps(selector)});"
                            "e.scrollIntoView({block: 'nearest'}); const r = e.getBoundingClientRect();"
                            "return {x: r.x + r.width / 2, y: r.y + r.height / 2}; })()")
        for x, y in ((box["x"] - 3, box["y"] - 3), (box["x"], box["y"])):
            self.call("Input.dispatchMouseEvent", {"type": "mouseMoved", "x": x, "y": y})

    def fit_to_content(self) -> None:
        """Make the viewport as tall as the page, so nothing scrolls (and hover states show in screenshots)."""
        size = self.call("Page.getLayoutMetrics")["cssContentSize"]
        self.call("Emulation.setDeviceMetricsOverride", {"width": self.width, "height": int(size["height"]) + 1,
                                                         "deviceScaleFactor": 1, "mobile": False})

    def screenshot(self, path: Path) -> None:
        """A PNG of the viewport (the whole page after ``fit_to_content``)."""
        data = self.call("Page.captureScreenshot", {"format": "png"})["data"]
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(base64.b64decode(data))

    def close(self) -> None:
        try:
            self._call("Browser.close", timeout=5.0)
        except (BrowserError, OSError):
            pass
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        for fd in (self._to_browser, self._from_browser):
            try:
                os.close(fd)
            except OSError:
                pass
        self.profile.cleanup()

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
