"""A small Docker Engine (API 1.43) on 127.0.0.1 that answers from recorded JSON and records requests.

The fixtures under ``fixtures/`` are Engine 24.0.7 responses for a compose project ``causeway``
(two env-worker replicas, the learner, a one-off ``compose run`` container) and a second project
``staging``. The engine keeps state, so a create is listed and inspected afterwards, and a stop
changes the state; it serves only the endpoints the Docker SDK calls for ``compose_scale``.
"""
from __future__ import annotations

import copy
import json
import re
import threading
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

FIXTURES = Path(__file__).parent / "fixtures"
_VERSIONED = re.compile(r"^/v\d+\.\d+(/.*)$")


def fixture(name: str) -> Any:
    return json.loads((FIXTURES / name).read_text())


@dataclass(frozen=True)
class Request:
    """One request as the engine saw it (path without the ``/v1.xx`` prefix)."""

    method: str
    path: str
    query: dict[str, str]
    body: Any = None


@dataclass
class EngineState:
    """Containers by id (inspect documents), the image store, and every request received."""

    containers: dict[str, dict[str, Any]] = field(default_factory=dict)
    images: dict[str, str] = field(default_factory=dict)
    requests: list[Request] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    @classmethod
    def recorded(cls) -> EngineState:
        containers = [json.loads(p.read_text()) for p in sorted((FIXTURES / "containers").glob("*.json"))]
        return cls({c["Id"]: c for c in containers}, fixture("images.json"))

    def find(self, ref: str) -> dict[str, Any] | None:
        """By id, id prefix or name, as the engine resolves references."""
        for c in self.containers.values():
            if c["Id"].startswith(ref) or c["Name"] == "/" + ref:
                return c
        return None

    def by_name(self, name: str) -> list[dict[str, Any]]:
        """Inspect documents of the containers named ``name``."""
        return [c for c in self.containers.values() if c["Name"] == "/" + name]


def _matches(container: dict[str, Any], labels: list[str]) -> bool:
    have = container["Config"]["Labels"] or {}
    return all(have.get(k) == v if sep else k in have for k, sep, v in (f.partition("=") for f in labels))


def summary(container: dict[str, Any]) -> dict[str, Any]:
    """The /containers/json entry of a container: the recorded one if there is one, else derived."""
    for entry in fixture("containers_json.json"):
        if entry["Id"] == container["Id"] and entry["State"] == container["State"]["Status"]:
            return entry
    cfg = container["Config"]
    return {"Id": container["Id"], "Names": [container["Name"]], "Image": cfg["Image"], "ImageID": container["Image"],
            "Command": " ".join(cfg.get("Cmd") or []), "Created": 1795170000, "Ports": [], "Labels": cfg["Labels"],
            "State": container["State"]["Status"], "Status": container["State"]["Status"].capitalize(),
            "HostConfig": {"NetworkMode": container["HostConfig"].get("NetworkMode", "default")},
            "NetworkSettings": {"Networks": container["NetworkSettings"]["Networks"]}, "Mounts": container["Mounts"]}


def created_container(state: EngineState, name: str, body: dict[str, Any]) -> dict[str, Any]:
    """The inspect document the engine would hold after ``POST /containers/create?name=<name>``."""
    cid = f"{len(state.containers):02d}" + name.encode().hex()[:62].ljust(62, "0")
    config = {k: copy.deepcopy(v) for k, v in body.items() if k not in ("HostConfig", "NetworkingConfig")}
    config["Hostname"] = config.get("Hostname") or cid[:12]
    endpoints = (body.get("NetworkingConfig") or {}).get("EndpointsConfig") or {}
    networks = {n: {"IPAMConfig": None, "Links": None, "Aliases": list(e.get("Aliases") or []) + [cid[:12]],
                    "NetworkID": "", "EndpointID": "", "Gateway": "", "IPAddress": "", "IPPrefixLen": 0,
                    "IPv6Gateway": "", "GlobalIPv6Address": "", "GlobalIPv6PrefixLen": 0, "MacAddress": "",
                    "DriverOpts": None} for n, e in endpoints.items()}
    return {"Id": cid, "Name": "/" + name, "Image": state.images[body["Image"]], "Config": config,
            "HostConfig": copy.deepcopy(body.get("HostConfig") or {}), "Mounts": [],
            "State": {"Status": "created", "Running": False, "ExitCode": 0},
            "NetworkSettings": {"Networks": networks}}


class _Handler(BaseHTTPRequestHandler):
    server: FakeDockerEngine

    def log_message(self, *_args: object) -> None:
        pass

    def _reply(self, status: int, document: Any = None, text: str | None = None) -> None:
        body = text.encode() if text is not None else b"" if document is None else json.dumps(document).encode()
        self.send_response(status)
        self.send_header("Api-Version", "1.43")
        self.send_header("Content-Type", "text/plain; charset=utf-8" if text is not None else "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def _error(self, status: int, kind: str, **fields: str) -> None:
        self._reply(status, {"message": fixture("errors.json")[kind]["message"].format(**fields)})

    def _handle(self, method: str) -> None:
        url = urlsplit(self.path)
        match = _VERSIONED.match(url.path)
        path = match.group(1) if match else url.path
        query = {k: v[-1] for k, v in parse_qs(url.query).items()}
        length = int(self.headers.get("Content-Length") or 0)
        body = json.loads(self.rfile.read(length)) if length else None
        state = self.server.state
        with state.lock:
            state.requests.append(Request(method, path, query, body))
            self.server.route(self, method, path, query, body)

    def do_GET(self) -> None:
        self._handle("GET")

    def do_POST(self) -> None:
        self._handle("POST")

    def do_DELETE(self) -> None:
        self._handle("DELETE")


class FakeDockerEngine(ThreadingHTTPServer):
    """``with FakeDockerEngine() as engine:`` serves on ``engine.base_url`` until the block ends."""

    daemon_threads = True

    def __init__(self) -> None:
        super().__init__(("127.0.0.1", 0), _Handler)
        self.state = EngineState.recorded()
        self._thread = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True)

    @property
    def base_url(self) -> str:
        return f"tcp://127.0.0.1:{self.server_address[1]}"

    def __enter__(self) -> FakeDockerEngine:
        self._thread.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.shutdown()
        self.server_close()

    def requests(self, method: str | None = None, pattern: str = "") -> list[Request]:
        """Recorded requests, optionally of one method and with a path matching ``pattern``."""
        return [r for r in self.state.requests
                if (method is None or r.method == method) and re.search(pattern, r.path)]

    def route(self, h: _Handler, method: str, path: str, query: dict[str, str], body: Any) -> None:
        if (method, path) == ("GET", "/_ping"):
            return h._reply(200, text="OK")
        if (method, path) == ("GET", "/version"):
            return h._reply(200, fixture("version.json"))
        if (method, path) == ("GET", "/containers/json"):
            return h._reply(200, self._list(query))
        if (method, path) == ("POST", "/containers/create"):
            return self._create(h, query["name"], body)
        if m := re.fullmatch(r"/networks/([^/]+)/connect", path):
            return self._connect(h, m.group(1), body)
        m = re.fullmatch(r"/containers/([^/]+)(/[a-z]+)?", path)
        container = self.state.find(m.group(1)) if m else None
        if container is None:
            return h._error(404, "no_such_container", id=m.group(1) if m else path)
        self._container(h, method, m.group(2) or "", container)

    def _list(self, query: dict[str, str]) -> list[dict[str, Any]]:
        labels = json.loads(query.get("filters", "{}")).get("label", [])
        every = query.get("all") in ("1", "true", "True")
        return [summary(c) for c in self.state.containers.values()
                if _matches(c, labels) and (every or c["State"]["Running"])]

    def _create(self, h: _Handler, name: str, body: dict[str, Any]) -> None:
        if existing := self.state.by_name(name):
            return h._error(409, "name_conflict", name=name, id=existing[0]["Id"])
        if body.get("Image") not in self.state.images:
            return h._error(404, "no_such_image", image=body.get("Image"))
        container = created_container(self.state, name, body)
        self.state.containers[container["Id"]] = container
        h._reply(201, {**fixture("create_response.json"), "Id": container["Id"]})

    def _connect(self, h: _Handler, network: str, body: dict[str, Any]) -> None:
        container = self.state.find(body["Container"])
        if container is None:
            return h._error(404, "no_such_container", id=body["Container"])
        aliases = (body.get("EndpointConfig") or {}).get("Aliases") or []
        container["NetworkSettings"]["Networks"][network] = {"Aliases": aliases + [container["Id"][:12]]}
        h._reply(200)

    def _container(self, h: _Handler, method: str, action: str, c: dict[str, Any]) -> None:
        if (method, action) == ("GET", "/json"):
            return h._reply(200, c)
        if (method, action) == ("POST", "/start"):
            c["State"].update(Status="running", Running=True)
            return h._reply(204)
        if (method, action) == ("POST", "/stop"):
            if not c["State"]["Running"]:
                return h._reply(304)
            c["State"].update(Status="exited", Running=False, ExitCode=0)
            return h._reply(204)
        if (method, action) == ("DELETE", ""):
            if c["State"]["Running"]:
                return h._error(409, "remove_running", id=c["Id"])
            del self.state.containers[c["Id"]]
            return h._reply(204)
        h._error(404, "no_such_container", id=c["Id"])
