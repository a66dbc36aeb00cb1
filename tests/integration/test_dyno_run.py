"""``causeway run --method dyno --env chemical-pixels`` end to end: the real supervisor, router and
service processes on loopback; the learner goes through Dyn-O's three phases on frames rendered from
the run's transitions, and ``summary.json`` carries the final model's ``slots.fg_ari``."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from causal.methods import model_from_config_json
from services.runtime.checkpoint import load_checkpoint

pytestmark = pytest.mark.integration
REPO = Path(__file__).resolve().parents[2]
PHASES = {"ae_updates": 5, "slot_updates": 10}


def test_a_dyno_run_trains_slots_and_writes_their_fg_ari(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "services.cli", "run", "--env", "chemical-pixels", "--method", "dyno",
           "--graph", "chain", "--num-objects", "2", "--max-seconds", "40", "--router-port", "0",
           "--metrics-base-port", "0", "--dashboard-port", "0", "--progress", "false", "--run-dir", str(run_dir),
           "--dyno-frame-size", "16", "--dyno-ae-updates", str(PHASES["ae_updates"]),
           "--dyno-slot-updates", str(PHASES["slot_updates"]), "--dyno-batch-size", "8",
           "--learner-warmup-steps", "100", "--worker-max-steps-per-second", "500"]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["method"] == "dyno" and summary["graph_report"] is None
    slots = summary["slots"]
    assert "error" not in slots, slots
    assert math.isfinite(slots["fg_ari"]) and -1.0 <= slots["fg_ari"] <= 1.0
    assert slots["num_slots"] == 3 and slots["frame_size"] == 16
    assert slots["updates"] > sum(PHASES.values()), "the learner never reached the world-model phase"
    saved = load_checkpoint(run_dir / "checkpoints" / "dynamics-learner-0.pt")
    model = model_from_config_json(saved["model_config"])
    model.load_state_dict(saved["trainer"]["model"])


def test_dyno_refuses_an_environment_it_cannot_render(tmp_path: Path) -> None:
    cmd = [sys.executable, "-m", "services.cli", "run", "--env", "chemical", "--method", "dyno",
           "--run-dir", str(tmp_path / "run"), "--progress", "false"]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120)
    out = done.stdout + done.stderr
    assert done.returncode == 2 and "runs on chemical-pixels, chemical-pixels-two-tone only" in out
