"""The Markov check (issue 19): a hidden velocity shows as the previous action's gain; a Markov state
shows none; constant factors and bad input are reported, not scored."""
import numpy as np
import pytest

from benchmarks.markov_check import predictability, table

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _rollout(observe_velocity: bool, steps: int = 1500, episode: int = 50, seed: int = 0):
    rng = np.random.default_rng(seed)
    states, actions, nexts, first = [], [], [], []
    x = v = 0.0
    for t in range(steps):
        if t % episode == 0:
            x, v = rng.uniform(-1, 1), 0.0
        a = rng.uniform(-1, 1)
        x_next = x + 0.1 * (v + a)  # the residual motion v carries on
        v_next = 0.3 * v + a
        obs = [x, v] if observe_velocity else [x]
        obs_next = [x_next, v_next] if observe_velocity else [x_next]
        states.append(obs + [0.5])  # a constant factor beside
        nexts.append(obs_next + [0.5])
        actions.append([a])
        first.append(t % episode == 0)
        x, v = x_next, v_next
    return np.array(states), np.array(actions), np.array(nexts), np.array(first)


def test_a_hidden_velocity_shows_as_the_previous_actions_gain():
    result = predictability(*_rollout(observe_velocity=False), updates=600, hidden=64, seed=0)
    # dx = 0.1 (v + a): (x, a) leave v unexplained (about half the variance), and v = 0.3 v' + a_{t-1}
    # is nine tenths a_{t-1}
    assert result["r2"][0] < 0.7
    assert result["gain"][0] > 0.7
    assert result["constant"] == [False, True]
    assert result["r2"][1] is None and result["gain"][1] is None
    # in nats: 0.5 ln((1 - R^2) / (1 - R^2_prev)) of the standardised change, i.e. -0.5 ln(1 - gain)
    assert result["nats"][0] == pytest.approx(-0.5 * np.log(1.0 - result["gain"][0]), rel=1e-3)
    assert result["nats"][0] > 0.6 and result["nats"][1] is None


def test_a_markov_state_shows_no_gain():
    result = predictability(*_rollout(observe_velocity=True), updates=600, hidden=64, seed=0)
    assert result["r2"][0] > 0.97 and result["r2"][1] > 0.97
    assert abs(result["r2_prev"][0] - result["r2"][0]) < 0.02 and abs(result["r2_prev"][1] - result["r2"][1]) < 0.02
    assert result["gain"][0] is None or abs(result["gain"][0]) < 0.5
    assert all(n is not None and abs(n) < 0.5 for n in result["nats"][:2])
    lines = table(("x", "v", "c"), result).splitlines()
    assert lines[-1] == "| c | constant | constant | - | - |"
    assert lines[2].endswith(f"| {result['nats'][0]:+.3f} |")
    del result["nats"]  # a file written before the column: the table still prints
    assert table(("x", "v", "c"), result).splitlines()[2].endswith("| - |")


def test_progress_reports_each_tenth_of_each_fit_and_changes_nothing():
    data = _rollout(observe_velocity=True, steps=300)
    lines: list[str] = []
    quiet = predictability(*data, updates=50, hidden=16, seed=0)
    loud = predictability(*data, updates=50, hidden=16, seed=0, progress=lines.append)
    assert lines == [f"fit {name}: {done}/50 updates" for name in ("r2", "r2_prev") for done in range(5, 51, 5)]
    assert loud == quiet


def test_bad_input_is_refused():
    s, a, n, f = _rollout(observe_velocity=True, steps=200)
    with pytest.raises(ValueError, match="same number of rows"):
        predictability(s, a[:-1], n, f)
    with pytest.raises(ValueError, match="at least 10 steps"):
        predictability(s[:5], a[:5], n[:5], f[:5])


def test_the_command_writes_its_table_json_and_picture(tmp_path, capsys):
    import json

    from benchmarks.markov_check import main

    main(["--env", "chemical-distractors", "--steps", "300", "--updates", "50", "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "markov.json").read_text())
    assert len(saved["factor_names"]) == len(saved["r2"]) == len(saved["constant"])
    assert saved["fitted_rows"] + saved["heldout_rows"] < 300  # first steps of episodes are left out
    assert (tmp_path / "markov.png").stat().st_size > 0
    assert capsys.readouterr().out.splitlines()[0].startswith("| factor |")
    with pytest.raises(SystemExit):
        main(["--env", "chemical-distractors", "--control-freq", "5", "--out", str(tmp_path)])
