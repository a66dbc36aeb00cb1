"""The SkiLD benchmarks' shared flags: the skill learner's settings (``SkillLearnerConfig``) and SkiLD's
reward and relabelling settings (``SkiLDConfig``), parsed the same way by each benchmark."""
from __future__ import annotations

import argparse

from causal.skild import SkiLDConfig
from causal.skild_agent import SkillLearnerConfig


def add_learner_arguments(parser: argparse.ArgumentParser) -> None:
    """``--eps-decay-steps --diversity-weight --skill-hidden --relabel-random --n-step --relabel-horizon``."""
    learner, cfg = SkillLearnerConfig(), SkiLDConfig()
    parser.add_argument("--eps-decay-steps", type=int, default=learner.eps_decay_steps,
                        help="env steps of epsilon's linear decay")
    parser.add_argument("--diversity-weight", type=float, default=cfg.diversity_weight,
                        help="lambda_b of SkiLD's diversity reward (0: Fig. 6.6's 'without diversity')")
    parser.add_argument("--skill-hidden", type=int, default=learner.hidden,
                        help="hidden width of the skill Q-network's trunk (SkiLD's and DIAYN's)")
    parser.add_argument("--relabel-random", type=float, default=cfg.relabel_random,
                        help="share of replayed samples given a target drawn uniformly from the history's targets")
    parser.add_argument("--n-step", type=int, default=learner.n_step,
                        help="steps of reward the skill Q-learner sums before bootstrapping (the authors: 3)")
    parser.add_argument("--relabel-horizon", type=int, default=cfg.relabel_horizon,
                        help="hindsight targets from the replayed step or up to this many steps minus one later "
                             "in its episode (1, the default: the replayed step's own graph only; 20 = L: HER's "
                             "future strategy)")


def learner_configs(args: argparse.Namespace, parser: argparse.ArgumentParser) -> tuple[SkillLearnerConfig, SkiLDConfig]:
    """The two configurations from :func:`add_learner_arguments`' flags; a value either refuses ends
    the command with the parser's usage error, before anything runs."""
    try:
        return (SkillLearnerConfig(eps_decay_steps=args.eps_decay_steps, n_step=args.n_step, hidden=args.skill_hidden),
                SkiLDConfig(diversity_weight=args.diversity_weight, relabel_horizon=args.relabel_horizon,
                            relabel_random=args.relabel_random))
    except ValueError as exc:
        parser.error(str(exc))
        raise  # parser.error exits; this keeps the type checker's view of the return honest
