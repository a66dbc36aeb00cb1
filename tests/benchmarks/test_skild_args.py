"""The SkiLD benchmarks' shared learner flags."""
from __future__ import annotations

import argparse

import pytest

from benchmarks.skild_args import add_learner_arguments, learner_configs


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    add_learner_arguments(parser)
    return parser


def test_defaults_are_the_configs_defaults_and_flags_reach_them():
    parser = _parser()
    learner, cfg = learner_configs(parser.parse_args([]), parser)
    assert (learner.hidden, learner.n_step, cfg.relabel_horizon, cfg.relabel_random) == (128, 1, 1, 0.0)
    args = parser.parse_args(["--skill-hidden", "512", "--relabel-random", "0.5", "--relabel-horizon", "20",
                              "--n-step", "3", "--eps-decay-steps", "1000", "--diversity-weight", "0"])
    learner, cfg = learner_configs(args, parser)
    assert (learner.hidden, learner.n_step, learner.eps_decay_steps) == (512, 3, 1000)
    assert (cfg.relabel_random, cfg.relabel_horizon, cfg.diversity_weight) == (0.5, 20, 0.0)


def test_a_refused_value_is_a_usage_error(capsys):
    parser = _parser()
    with pytest.raises(SystemExit) as exit_:
        learner_configs(parser.parse_args(["--relabel-random", "1.5"]), parser)
    assert exit_.value.code == 2 and "relabel_random must be in [0, 1]" in capsys.readouterr().err
