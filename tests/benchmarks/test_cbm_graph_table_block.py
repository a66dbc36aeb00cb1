"""Table 4.1's benchmark on the block scene: its collection data (4-D actions, the scripted grasp that
makes the cubes move) and the truth it scores against."""
from __future__ import annotations

from benchmarks.cbm_graph_table import collect
from envs.block import PICK_HEIGHT
from envs.manipulation_layout import MOV_HALF, TABLE_TOP


def test_block_collection_opens_with_a_grasp_of_mov1() -> None:
    spec, data = collect(dict(distractors="2,1", task="pick", episode_length=40), 45, 0, "block")
    assert spec.env_id == "block" and spec.num_factors == 17 + 3 and spec.reward_parents is not None
    assert data["state"].shape == (45, 20) and data["action"].shape == (45, 4) and not data["heldout"].any()
    first = data["next_state"][:40, 7]
    assert first.max() >= TABLE_TOP[2] + MOV_HALF + PICK_HEIGHT  # the opening grasp lifted mov1 (success)
    assert data["reward"][:40].max() == 1.0
