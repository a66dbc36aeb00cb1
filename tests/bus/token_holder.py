"""Holds a liveliness token through the Zenoh router: the far end of the process-death tests.

Run as ``python -m tests.bus.token_holder CONNECT KEY`` from the repository root; prints ``ready``
once the token is declared, then waits to be killed. With ``--crash`` it also subscribes and
watches liveliness, then dies of an uncaught exception without closing anything: the process
must still exit (Zenoh's callback threads would otherwise keep it alive).
"""
from __future__ import annotations

import argparse
import threading

from services.bus.zenoh_transport import ZenohTransport


def main(connect: str, key: str, crash: bool) -> None:
    """Declare ``key`` on the router at ``connect``; block until killed, or crash if asked."""
    transport = ZenohTransport(connect)
    transport.declare_token(key)
    transport.subscribe("**", lambda k, p: None)
    transport.watch_liveliness("**", lambda k, alive: None)
    transport.serve_latest(f"{key}/latest").set(b"x")
    print("ready", flush=True)
    if crash:
        raise RuntimeError("token holder crashed on purpose")
    threading.Event().wait()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("connect")
    parser.add_argument("key")
    parser.add_argument("--crash", action="store_true")
    args = parser.parse_args()
    main(args.connect, args.key, args.crash)
