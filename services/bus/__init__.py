"""The bus: a small ``Transport`` protocol with an in-memory and a Zenoh implementation.

``InMemoryTransport`` runs a whole pipeline in one process (tests, benchmarks); ``ZenohTransport``
is what every deployed ``service.py`` opens, as a client of the router that ``start_router`` runs
inside the local supervisor (or the eclipse/zenoh container under compose).
"""
from services.bus.base import Callback, Handle, LatestValue, LivelinessCallback, Transport
from services.bus.memory import InMemoryBus, InMemoryTransport, key_intersects
from services.bus.router import client_config, free_tcp_port, start_router, wait_for_router
from services.bus.zenoh_transport import ZenohTransport

__all__ = [
    "Callback",
    "Handle",
    "InMemoryBus",
    "InMemoryTransport",
    "LatestValue",
    "LivelinessCallback",
    "Transport",
    "ZenohTransport",
    "client_config",
    "free_tcp_port",
    "key_intersects",
    "start_router",
    "wait_for_router",
]
