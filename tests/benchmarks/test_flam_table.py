"""FLAM's Tables 8.1-8.2 benchmark end to end at a toy budget, and its slot-sharing measure."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.flam_table import (agent_slot_share, agent_slots, code_overlap, per_agent, main, parse_args,
                                   slot_sharing, token_labels, train_lam, train_two_stage)
from causal.flam import FLAM, FLAMConfig

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_flam_table_toy_budget(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "table.json"
    main(parse_args(["--episodes", "3", "--episode-steps", "5", "--eval-episodes", "4", "--horizon", "3",
                     "--ae-updates", "1", "--updates", "2", "--slot-dim", "16", "--aggregator", "broadcast",
                     "--mask-prior", "annealed", "--out", str(out)]))
    results = json.loads(out.read_text())["results"]
    assert set(results) == {"recon", "flam", "monolithic", "random", "observed moves"}
    assert all(0.0 <= results["observed moves"][f"dci_{x}"] <= 1.0 for x in "dci")  # the latent actions' ceiling
    for name in ("flam", "monolithic"):
        for suffix in ("", "_positions_latent"):
            assert all(0.0 <= results[name][f"dci_{x}{suffix}"] <= 1.0 for x in "dci")
        assert results[name]["psnr"] > 0
    # Table 8.2's reading (factor states against positions) for the slot model and the chance row alone
    assert all(0.0 <= results[key][f"dci_{x}_positions"] <= 1.0 for key in ("flam", "random") for x in "dci")
    assert "dci_d_positions" not in results["monolithic"] and "psnr" not in results["random"]
    assert len(results["flam"]["positions_importance"]) == 4 and len(results["flam"]["agent_slot_share"][0]) == 5
    assert all(0.0 <= results["flam"][f"dci_{x}{s}_matched"] <= 1.0 for x in "dci" for s in ("", "_positions"))
    assert 0.0 <= results["flam"]["every_agent_own_slot"] <= 1.0
    overlap = np.array(results["recon"]["code_overlap"])  # the autoencoder's codes, background and 4 agents
    assert overlap.shape == (5, 5) and np.allclose(overlap, overlap.T) and np.allclose(np.diag(overlap), 1.0)
    printed = capsys.readouterr().out
    assert "| flam |" in printed and "largest overlap of two agents' codes" in printed


def test_agent_slots_and_sharing_on_a_hand_built_attention() -> None:
    labels = torch.zeros(1, 1, 8, 8, dtype=torch.uint8)
    labels[0, 0, 0:4, 0:4] = 1  # agent 0 on token 0
    labels[0, 0, 0:4, 4:8] = 2  # agent 1 on token 1
    labels[0, 0, 4:8, 0:4] = 3  # agent 2 on token 2
    attention = torch.zeros(1, 1, 3, 4)
    attention[0, 0, 1, 0] = attention[0, 0, 1, 1] = attention[0, 0, 2, 2] = 1.0
    attention[0, 0, 0, 3] = 1.0
    slots = agent_slots(attention, labels, num_agents=3)
    assert slots.tolist() == [[[1, 1, 2]]]
    sharing = slot_sharing(slots)
    assert sharing == {"agents_0_1_share_slot": 1.0, "grouped_as_actions": 1.0, "every_agent_own_slot": 0.0}
    assert agent_slot_share(slots, num_slots=3) == [[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


def test_the_two_stage_baseline_trains_slots_first_then_latent_actions_on_them_frozen(tmp_path: Path) -> None:
    args = parse_args(["--episodes", "3", "--episode-steps", "5", "--eval-episodes", "4", "--horizon", "3",
                       "--ae-updates", "1", "--slot-stage-updates", "2", "--updates", "2", "--slot-dim", "16",
                       "--aggregator", "broadcast", "--mask-prior", "annealed", "--models", "two-stage"])
    features = torch.randn(3, 6, 64, 4)
    labels = torch.randint(5, (3, 6, 64))
    model = FLAM(FLAMConfig(num_slots=5, slot_dim=16, aggregator="broadcast", slot_reconstruction=1.0), 64)
    factorizer = [p.detach().clone() for p in model.factorizer.parameters()]
    idm = [p.detach().clone() for p in model.idm.parameters()]
    train_two_stage(model, features, labels, args)
    assert not any(p.requires_grad for p in [*model.factorizer.parameters(), *model.slot_decoder.parameters()])
    assert any(not torch.equal(a, b) for a, b in zip(factorizer, model.factorizer.parameters()))
    assert any(not torch.equal(a, b) for a, b in zip(idm, model.idm.parameters()))
    frozen = [p.detach().clone() for p in model.factorizer.parameters()]
    train_lam(model, features, labels, args, "two-stage", prior="none")
    assert all(torch.equal(a, b) for a, b in zip(frozen, model.factorizer.parameters()))
    results = main(replace(args, out=str(tmp_path / "table.json")))
    assert set(results) == {"recon", "two-stage", "random", "observed moves"} and results["two-stage"]["psnr"] > 0
    assert 0.0 <= results["two-stage"]["dci_d_positions"] <= 1.0
    assert 0.0 <= results["two-stage"]["every_agent_own_slot"] <= 1.0


def test_per_agent_picks_each_agents_slot_per_frame() -> None:
    values = torch.arange(2 * 3 * 2, dtype=torch.float32).view(1, 2, 3, 2)  # frame t, slot k: [6t + 2k, 6t + 2k + 1]
    slots = torch.tensor([[[2, 0], [1, 1]]])  # frame 0: agents in slots 2 and 0; frame 1: both in slot 1
    assert per_agent(values, slots).tolist() == [[[4.0, 5.0], [0.0, 1.0]], [[8.0, 9.0], [8.0, 9.0]]]


def test_token_labels_group_agents_in_index_order_when_slots_are_fewer() -> None:
    labels = np.zeros((1, 1, 8, 32), np.uint8)
    for i in range(4):  # agent i on token i of the first row
        labels[0, 0, 0:4, 4 * i:4 * i + 4] = 1 + i
    assert token_labels(labels)[0, 0, :5].tolist() == [1, 2, 3, 4, 0]
    assert token_labels(labels, num_slots=5, num_agents=4)[0, 0, :5].tolist() == [1, 2, 3, 4, 0]
    assert token_labels(labels, num_slots=9, num_agents=4)[0, 0, :5].tolist() == [1, 2, 3, 4, 0]
    # K = 2 agent slots: agents 0, 1 -> slot 1 and 2, 3 -> slot 2; K = 1: every agent in slot 1
    assert token_labels(labels, num_slots=3, num_agents=4)[0, 0, :5].tolist() == [1, 1, 2, 2, 0]
    assert token_labels(labels, num_slots=2, num_agents=4)[0, 0, :5].tolist() == [1, 1, 1, 1, 0]


def test_one_slot_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        parse_args(["--num-slots", "1"])
    assert "--num-slots must be 0" in capsys.readouterr().err


def test_the_correlated_variant_refuses_the_segment_prior(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        parse_args(["--variant", "correlated", "--mask-prior", "annealed"])
    assert "the grouping under test" in capsys.readouterr().err
    assert parse_args(["--variant", "correlated", "--mask-prior", "foreground"]).mask_prior == "foreground"


def test_the_binding_term_needs_a_mask_prior(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        parse_args(["--mask-binding", "1"])
    assert "needs a --mask-prior" in capsys.readouterr().err
    assert parse_args(["--mask-binding", "1", "--mask-prior", "annealed"]).mask_binding == 1.0


def test_code_overlap_is_one_for_the_same_codes_and_zero_for_none_in_common() -> None:
    a, b, c = [1.0, 0.0], [0.0, 1.0], [0.5, 0.5]
    features = torch.tensor([[a, a, b, c], [a, b, b, c]])  # [frames, n, d_e]
    labels = torch.tensor([[0, 1, 2, 3], [0, 1, 2, 3]])
    overlap = code_overlap(features, labels, 4)
    assert overlap[0][0] == 1.0 and overlap[3][3] == 1.0
    assert overlap[0][1] == overlap[1][0] == 0.5  # segment 1 is half code a, half b; segment 0 all a
    assert overlap[1][2] == 0.5 and overlap[2][3] == 0.0 and overlap[0][3] == 0.0
