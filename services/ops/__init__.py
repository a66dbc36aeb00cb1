"""Operator commands for a running stack: ``causeway status | scale | stop | checkpoint``.

They talk to a run the way services do, as Zenoh clients of its router: liveliness tokens say who
is alive, stats beats say how fast they go, Control messages ask for a change. ``compose_scale``
is the one exception: under Docker Compose the env-worker replicas are containers, so scaling them
goes through the Docker Engine API instead of the supervisor.

| module | what |
|---|---|
| ``target.py`` | which run: ``--connect``/``--run`` or ``--run-dir``; ``OpsError``; opening the bus |
| ``observe.py`` | ``RunObserver``: a run's tokens and beats over a listening window |
| ``status.py`` | ``causeway status``: the table (or ``--json``) built from an observation |
| ``control.py`` | ``causeway scale | stop | checkpoint`` over the control topics |
| ``compose_scale.py`` | ``causeway scale env-worker N --compose-project P``: clone or remove replicas |
"""
