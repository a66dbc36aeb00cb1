"""Scale requests are bounded (issue 20, item 3): the supervisor starts no more env-workers than --max-workers."""
from __future__ import annotations

import pytest

from services.runtime.config import build_config
from services.supervisor.config import RunConfig
from services.supervisor.supervisor import Supervisor


def test_a_request_above_the_limit_is_refused(tmp_path) -> None:
    sup = Supervisor(build_config(RunConfig, router_port=7447, run_dir=str(tmp_path), max_workers=4, progress=False))
    scaled: list[int] = []
    sup.scale_workers = scaled.append
    for argument in ("env-worker=5", "env-worker=1000000", "env-worker=-1", "learner=2", "env-worker=x", "env-worker=4"):
        sup.pending_scale.put(argument)
    sup._apply_scale_requests()
    assert scaled == [4]


def test_the_limit_cannot_be_below_the_workers_started() -> None:
    with pytest.raises(ValueError, match="max_workers"):
        build_config(RunConfig, workers=3, max_workers=2)
    assert RunConfig().max_workers == 64


def test_causeway_scale_refuses_above_the_runs_limit_before_sending(tmp_path, capsys) -> None:
    import json

    from services.cli import main

    (tmp_path / "config.json").write_text(json.dumps({"run_id": "r", "router_port": 1, "max_workers": 4}))
    assert main(["scale", "env-worker", "5", "--run-dir", str(tmp_path)]) == 2
    assert "at most 4" in capsys.readouterr().err
