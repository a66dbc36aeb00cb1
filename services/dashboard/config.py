"""dashboard configuration."""
from __future__ import annotations

from dataclasses import dataclass

from services.runtime.config import ServiceConfig, doc


@dataclass(frozen=True)
class DashboardConfig(ServiceConfig):
    """dashboard: serves the live causal-graph page of every run on the bus over HTTP."""

    http_host: str = doc("0.0.0.0", "address the HTTP server binds to")
    http_port: int = doc(8080, "port of the page, its JSON API and its event stream (0: any free port)")
    watch_run: str = doc("*", "run id to show, or * for every run on the bus")
    history_points: int = doc(1_000, "learning-curve points kept per run (older points are thinned, not cut)")
    local_examples: int = doc(8, "example transitions of a local-graph report sent to the page (the rest are not)")
    max_runs: int = doc(64, "runs kept; the one updated longest ago is forgotten first")
    max_services: int = doc(256, "service instances kept per run; the one heard from longest ago goes first")
    max_sse_clients: int = doc(32, "concurrent /events streams; more are answered 503")
    heartbeat_s: float = doc(15.0, "seconds between keep-alive comments on an idle event stream")
    services_push_s: float = doc(2.0, "minimum seconds between pushes of a run's service list")
    stale_after_s: float = doc(10.0, "a service not heard from for this long is shown as stale")
