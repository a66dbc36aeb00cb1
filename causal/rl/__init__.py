"""Policy learning: the agent interface, PPO, SAC, replay and in-process collection (no bus)."""
from causal.rl.base import ActionSpec, Agent, ReplayBatch, RolloutBatch, abstraction_input_mask
from causal.rl.ppo import PPOAgent, PPOConfig
from causal.rl.replay import UniformReplay
from causal.rl.sac import SACAgent, SACConfig

__all__ = [
    "ActionSpec", "Agent", "PPOAgent", "PPOConfig", "ReplayBatch", "RolloutBatch", "SACAgent", "SACConfig",
    "UniformReplay", "abstraction_input_mask",
]
