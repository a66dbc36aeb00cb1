"""env-worker configuration."""
from __future__ import annotations

from dataclasses import dataclass

from envs.registry import EnvOptions, env_names
from proto.settings import section
from services.runtime.config import ServiceConfig, doc


@dataclass(frozen=True)
class EnvWorkerConfig(ServiceConfig):
    """env-worker: steps an environment and publishes TransitionBatches."""

    env: str = doc("chemical", "environment (envs.registry)", choices=env_names)
    env_options: EnvOptions = section(EnvOptions, prefix="", help="environment construction options")
    worker_index: int = doc(0, "index i of this worker (seed + i); -1: derive it from the hostname "
                                "(compose replicas, which share one configuration)")
    batch_steps: int = doc(256, "env steps per published TransitionBatch (64-1024)")
    max_steps_per_second: float = doc(0.0, "throttle (0: as fast as possible)")
    max_steps: int = doc(0, "stop after this many env steps (0: never)")
    local_graphs: bool = doc(False, "attach the simulator's ground-truth local graphs to each batch")
    follow_policy: bool = doc(False, "act with the newest policy weights (weights/policy); random until they arrive")
    publish_frames: bool = doc(False, "publish the steps as frames (FrameBatch on frames/<worker>, for the factor-extractor) "
                                      "instead of transitions; the env must render them (chemical-pixels)")
    frames_beside: bool = doc(False, "publish each batch's frames too (FrameBatch on frames/<worker>) beside its "
                                     "transitions, which still go on transitions/<worker>: for the factor-extractor's "
                                     "latent-action labels (a flam run with --label-latent-actions)")
    frame_stride: int = doc(1, "publish_frames: keep every n-th pixel along each side of a frame (downsampling)")
    skild: bool = doc(False, "act with SkiLD's skill/task policies (weights/skild-policy; no steps before they "
                             "arrive) and publish each batch's skill labels too (SkillBatch on skills/<worker>)")
    policy_poll_s: float = doc(5.0, "follow_policy: also ask for the latest policy this often, so a missed update is caught")

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 1 <= self.batch_steps <= 65536:
            raise ValueError(f"batch_steps must be in [1, 65536], got {self.batch_steps}")
        if self.max_steps_per_second < 0 or self.max_steps < 0:
            raise ValueError("max_steps_per_second and max_steps must be >= 0")
        if self.publish_frames and self.frames_beside:
            raise ValueError("publish_frames (frames instead of transitions) and frames_beside (frames beside "
                             "them) exclude each other")
        if self.frame_stride < 1:
            raise ValueError(f"frame_stride must be >= 1, got {self.frame_stride}")
        if self.worker_index < -1:
            raise ValueError(f"worker_index must be >= 0 (or -1: from the hostname), got {self.worker_index}")
