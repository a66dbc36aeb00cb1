"""The learner's live-score history: a row each time its beats carry new ``live_*`` scores, kept in
``summary.json``'s ``live_history`` and drawn in ``live_scores.png``."""
from __future__ import annotations

from pathlib import Path

from proto.codec import encode
from proto.messages import ServiceStats
from services.bus.router import free_tcp_port
from services.runtime.config import build_config
from services.supervisor.config import RunConfig
from services.runtime.live_scores import live_row
from services.supervisor.report import plot_live_scores
from services.supervisor.supervisor import Supervisor


def test_a_row_comes_only_when_the_live_scores_change() -> None:
    assert live_row({"updates": 5.0, "loss": 1.0}, None, 1.0) is None  # no live scores in the beat
    first = live_row({"updates": 10.0, "env_steps": 640.0, "live_psnr": 30.5, "live_dci_d": 0.25}, None, 2.0)
    assert first == {"time": 2.0, "updates": 10.0, "env_steps": 640.0, "psnr": 30.5, "dci_d": 0.25}
    # the next beats repeat them until the trainer scores again
    assert live_row({"updates": 12.0, "live_psnr": 30.5, "live_dci_d": 0.25}, first, 3.0) is None
    again = live_row({"updates": 20.0, "live_psnr": 31.0, "live_dci_d": 0.25}, first, 4.0)
    assert again is not None and again["updates"] == 20.0 and again["psnr"] == 31.0


def test_the_plot_has_a_panel_for_scores_and_one_for_the_rest(tmp_path: Path) -> None:
    history = [{"time": float(t), "updates": 100.0 * t, "env_steps": 0.0, "psnr": 20.0 + t, "dci_d": 0.1 * t,
                "slot0_kl": 3.0} for t in range(1, 5)]
    plot_live_scores(history, tmp_path / "live.png")
    assert (tmp_path / "live.png").stat().st_size > 1000
    plot_live_scores([], tmp_path / "none.png")
    assert not (tmp_path / "none.png").exists()


def test_the_supervisor_keeps_the_learners_live_scores_and_no_one_elses(tmp_path: Path) -> None:
    sup = Supervisor(build_config(RunConfig, method="flam", env="multigrid-agents", run_dir=str(tmp_path / "run"),
                                  router_port=free_tcp_port(), metrics_base_port=0, dashboard_port=0))
    sup.started.update({"dynamics-learner", "env-worker-0"})
    key = "causeway/run/stats/{}/{}"
    beats = [("dynamics-learner", {"updates": 100.0, "live_psnr": 25.0}),
             ("dynamics-learner", {"updates": 130.0, "live_psnr": 25.0}),  # a repeat: no row
             ("env-worker", {"env_steps": 5.0, "live_psnr": 99.0}),  # not the learner's
             ("dynamics-learner", {"updates": 300.0, "live_psnr": 27.5})]
    for service, values in beats:
        sup._on_stats(key.format(service, "0"), encode(ServiceStats(service=service, instance="0", values=values)))
    forged = ServiceStats(service="dynamics-learner", instance="0", values={"live_psnr": 1.0})
    sup._on_stats(key.format("env-worker", "0"), encode(forged))  # under another process's key: refused
    assert [(row["updates"], row["psnr"]) for row in sup.live_history] == [(100.0, 25.0), (300.0, 27.5)]
