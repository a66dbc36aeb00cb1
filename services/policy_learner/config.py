"""policy-learner configuration."""
from __future__ import annotations

from dataclasses import dataclass

from causal.methods import method_configs_class
from causal.rl import PPOConfig, SACConfig
from causal.skild_agent import SkillLearnerConfig
from proto.settings import section
from services.runtime.config import ServiceConfig, doc

ALGOS = ("ppo", "sac")
SKILD_GRAPHS = ("evaluator", "true")
MethodConfigs = method_configs_class()


@dataclass(frozen=True)
class PolicyLearnerConfig(ServiceConfig):
    """policy-learner: PPO (discrete or continuous actions) or SAC (continuous) behind one interface."""

    algo: str = doc("ppo", "policy learning algorithm", choices=ALGOS)
    skills: bool = doc(False, "PPO over the env's skill options (envs.skills.OPTIONS; manipulation) instead of raw "
                              "actions: one decision per skill, its return the sum of the skill's step rewards")
    skill_rollout: int = doc(8, "skills: consecutive decisions of one worker per PPO column (and the PPO "
                                "minibatch size, if smaller than minibatch_size)")
    scored: bool = doc(False, "learn from ScoredBatches (scored/*, with intrinsic rewards) instead of transitions/*")
    extrinsic_coef: float = doc(1.0, "weight of the environment reward")
    intrinsic_coef: float = doc(1.0, "weight of the intrinsic reward (scored batches only)")
    max_policy_lag: int = doc(4, "drop batches produced by a policy more than this many versions old")
    abstraction: bool = doc(True, "mask the policy input to the graph's abstraction (controllable + action-relevant)")
    hide: str = doc("", "comma-separated factor-name prefixes the policy never sees, whatever the graph says "
                        "(e.g. 'mk' hides the manipulation markers; '' none)")
    always_keep: str = doc(".goal_color", "factors whose name ends with this are never masked (provided task factors; '' none)")
    hidden: int = doc(64, "width of the two hidden layers of every policy/value network")
    lr: float = doc(3e-4, "Adam learning rate")
    gamma: float = doc(0.99, "discount")
    rollout_batches: int = doc(4, "PPO: transition batches (one per column) per update")
    epochs: int = doc(4, "PPO: passes over each rollout")
    minibatch_size: int = doc(64, "PPO: steps per minibatch")
    clip: float = doc(0.2, "PPO: clip range of the surrogate ratio")
    entropy_coef: float = doc(0.01, "PPO: entropy bonus")
    replay_capacity: int = doc(100_000, "SAC: replay size")
    warmup_steps: int = doc(1_000, "SAC: transitions before the first update")
    batch_size: int = doc(256, "SAC: rows per update")
    action_low: float = doc(-1.0, "continuous actions: lower bound of every dimension")
    action_high: float = doc(1.0, "continuous actions: upper bound of every dimension")
    publish_every_updates: int = doc(0, "updates between weight publications (0: PPO 1, SAC 100)")
    max_updates: int = doc(0, "stop after this many updates (0: never)")
    skild: bool = doc(False, "SkiLD (ch. 6): learn skills from SkillBatches (skills/*), then a task policy over them")
    skild_pretrain_steps: int = doc(20_000, "SkiLD: env steps of reward-free skill pre-training before task learning "
                                            "starts (the low level then frozen)")
    skild_graphs: str = doc("evaluator", "SkiLD: induced graphs from the graph-evaluator's estimator (InducedGraphs, "
                                         "pCMI) or the env's true local graphs (true: the chapter's ablation)",
                            choices=SKILD_GRAPHS)
    skild_updates_per_env_step: float = doc(0.0625, "SkiLD: skill Q-network updates per pre-training env step "
                                                    "(benchmarks/skild_coverage: one per step of 16 envs)")
    skill: SkillLearnerConfig = section(SkillLearnerConfig, prefix="skill",
                                        help="SkiLD's skill learner (low-level DQN, graph selector)")
    models: MethodConfigs = section(MethodConfigs, prefix="", help="every method's hyper-parameters")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.algo not in ALGOS:
            raise ValueError(f"algo must be one of {ALGOS}, got {self.algo!r}")
        if self.skills and self.algo != "ppo":
            raise ValueError("a policy over skills is learned with PPO (algo=ppo)")
        if self.skild and self.algo != "ppo":
            raise ValueError("SkiLD's task policy is learned with PPO (algo=ppo)")
        if self.skild_pretrain_steps < 0 or not self.skild_updates_per_env_step >= 0:
            raise ValueError("skild_pretrain_steps and skild_updates_per_env_step must be >= 0")
        if self.max_policy_lag < 0:
            raise ValueError("max_policy_lag must be >= 0")

    def ppo(self) -> PPOConfig:
        """PPO's settings. Over skills a rollout holds ``rollout_batches x skill_rollout`` decisions
        (32 by default, ~1,000 motor steps) instead of ``rollout_batches x 256`` steps, so minibatches
        shrink to ``skill_rollout`` to keep several gradient steps per update (measured: with 64
        decisions per update in minibatches of 64 the policy stayed near uniform (entropy 1.94 of
        ln 7 = 1.95) over the 71 updates of a 30-minute run)."""
        minibatch = min(self.minibatch_size, self.skill_rollout) if self.skills else self.minibatch_size
        return PPOConfig(lr=self.lr, gamma=self.gamma, clip=self.clip, epochs=self.epochs,
                         minibatch_size=minibatch, entropy_coef=self.entropy_coef,
                         hidden=(self.hidden, self.hidden))

    def sac(self) -> SACConfig:
        return SACConfig(hidden=(self.hidden, self.hidden), lr=self.lr, gamma=self.gamma, batch_size=self.batch_size)

    @property
    def publish_every(self) -> int:
        return self.publish_every_updates or (1 if self.algo == "ppo" else 100)
