"""Prometheus metrics every service shares, on a per-process registry with its own HTTP port."""
from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, start_http_server

from proto.codec import REJECT_REASONS


class ServiceMetrics:
    """Common metrics; a service adds its own on ``self.registry``."""

    def __init__(self, service: str, instance: str) -> None:
        self.registry = CollectorRegistry()
        self.service, self.instance = service, instance
        self.rejected = Counter("causeway_messages_rejected", "Messages that failed validation, by reason",
                                ["reason"], registry=self.registry)
        for reason in REJECT_REASONS:
            self.rejected.labels(reason=reason)
        self.received = Counter("causeway_messages_received", "Valid messages received, by message type",
                                ["type"], registry=self.registry)
        self.dropped = Counter("causeway_messages_dropped", "Valid messages dropped, by reason",
                               ["reason"], registry=self.registry)
        self.queue_depth = Gauge("causeway_queue_depth", "Messages waiting in a bounded inbound queue",
                                 ["queue"], registry=self.registry)
        self.up = Gauge("causeway_service_info", "Constant 1, labelled with the service and instance",
                        ["service", "instance"], registry=self.registry)
        self.up.labels(service=service, instance=instance).set(1)
        self.started = Gauge("causeway_process_start_time_seconds", "Unix time this service started",
                             registry=self.registry)
        self.started.set_to_current_time()

        self.rejected_count = 0

    def reject(self, reason: str) -> None:
        """Count one rejected message (also reported in the service's stats beats)."""
        self.rejected.labels(reason=reason).inc()
        self.rejected_count += 1

    def serve(self, port: int, host: str = "0.0.0.0") -> None:
        """Expose /metrics on ``host:port`` (port 0: do not serve)."""
        if port:
            start_http_server(port, addr=host, registry=self.registry)

    def counter(self, name: str, doc: str, labels: tuple[str, ...] = ()) -> Counter:
        return Counter(name, doc, list(labels), registry=self.registry)

    def gauge(self, name: str, doc: str, labels: tuple[str, ...] = ()) -> Gauge:
        return Gauge(name, doc, list(labels), registry=self.registry)

    def histogram(self, name: str, doc: str, buckets: tuple[float, ...]) -> Histogram:
        return Histogram(name, doc, buckets=buckets, registry=self.registry)
