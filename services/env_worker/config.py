"""env-worker configuration."""
from __future__ import annotations

from dataclasses import dataclass

from services.runtime.config import ServiceConfig, doc


@dataclass(frozen=True)
class EnvWorkerConfig(ServiceConfig):
    """env-worker: steps an environment and publishes TransitionBatches."""

    env: str = doc("chemical", "environment name (envs.make_env)")
    graph: str = doc("full", "Chemical object graph: collider, chain, full or a path to a DAG JSON file")
    num_objects: int = doc(10, "Chemical: number of objects")
    cpt_seed: int = doc(0, "Chemical: seed of the fixed conditional probability tables (same for all workers)")
    seed: int = doc(0, "run seed: worker i seeds its env and policy with seed + i")
    worker_index: int = doc(0, "index i of this worker (seed + i); -1: derive it from the hostname "
                                "(compose replicas, which share one configuration)")
    batch_steps: int = doc(256, "env steps per published TransitionBatch (64-1024)")
    max_steps_per_second: float = doc(0.0, "throttle (0: as fast as possible)")
    max_steps: int = doc(0, "stop after this many env steps (0: never)")
    local_graphs: bool = doc(False, "attach the simulator's ground-truth local graphs to each batch")
    follow_policy: bool = doc(False, "act with the newest policy weights (weights/policy); random until they arrive")
    policy_poll_s: float = doc(5.0, "follow_policy: also ask for the latest policy this often, so a missed update is caught")
