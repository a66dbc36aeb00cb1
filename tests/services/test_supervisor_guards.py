"""What the local supervisor refuses before it starts, and what it leaves behind when killed."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from services.bus.router import free_tcp_port
from services.cli import main as cli_main
from services.runtime.config import build_config
from services.supervisor.config import RunConfig
from services.supervisor.processes import leftovers
from services.supervisor.wiring import check_ports_free, ports, resolve

REPO = Path(__file__).resolve().parents[2]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}").exists() and "Z" not in Path(f"/proc/{pid}/stat").read_text().split()[2]


def test_a_port_in_use_is_refused_with_what_needs_it(tmp_path, capsys) -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        taken = holder.getsockname()[1]
        cfg = resolve(build_config(RunConfig, router_port=taken, run_dir=str(tmp_path)))
        with pytest.raises(ValueError, match=f"router \\(--router-port\\): port {taken} on 127.0.0.1 is in use"):
            check_ports_free(cfg)
        code = cli_main(["run", "--router-port", str(taken), "--run-dir", str(tmp_path / "r"), "--progress", "false"])
        assert code == 2 and f"port {taken}" in capsys.readouterr().err
    free = resolve(build_config(RunConfig, router_port=free_tcp_port(), metrics_base_port=0, dashboard_port=0))
    check_ports_free(free)
    assert list(ports(free)) == ["router (--router-port)"]


def test_a_port_whose_old_connections_linger_is_not_refused(tmp_path) -> None:
    """A killed run started again at once: its router's port holds connections in TIME_WAIT (the server
    closed first), which the router's own bind (SO_REUSEADDR) ignores; only a listener makes it taken."""
    with socket.socket() as listener:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the router's (and HTTP servers') listeners
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        client = socket.create_connection(("127.0.0.1", port))
        served, _ = listener.accept()
        served.close()  # the server's side closes first: its end of the connection enters TIME_WAIT
        client.close()
    with socket.socket() as plain:  # what a probe without SO_REUSEADDR sees
        with pytest.raises(OSError):
            plain.bind(("127.0.0.1", port))
    check_ports_free(resolve(build_config(RunConfig, router_port=port, metrics_base_port=0, dashboard_port=0,
                                          run_dir=str(tmp_path))))


def test_every_listening_port_of_the_run_is_checked() -> None:
    cfg = resolve(build_config(RunConfig, router_port=7447, metrics_base_port=9100, workers=2, collector="ppo"))
    assert sorted(ports(cfg).values()) == [7447, 8080, 9101, 9102, 9103, 9104, 9110, 9111]


def test_a_second_run_on_a_directory_still_in_use_is_refused(tmp_path) -> None:
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", "services.env_worker"])
    try:
        table = {"router": "tcp/127.0.0.1:1", "supervisor_pid": 999_999_999,
                 "processes": {"env-worker-0": {"pid": child.pid, "module": "services.env_worker"},
                               "dynamics-learner": {"pid": os.getpid(), "module": "services.dynamics_learner"}}}
        (tmp_path / "processes.json").write_text(json.dumps(table))
        # between fork and exec the child's command line is still this process's: wait for the exec
        cmdline = Path(f"/proc/{child.pid}/cmdline")
        deadline = time.monotonic() + 30
        while b"services.env_worker" not in cmdline.read_bytes() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert leftovers(tmp_path) == [f"env-worker-0 (pid {child.pid})"]
    finally:
        child.kill()
        child.wait()
    assert leftovers(tmp_path) == []


def test_services_die_with_a_killed_supervisor(tmp_path) -> None:
    parent = textwrap.dedent(f"""
        import os, signal, sys, time
        from pathlib import Path
        from services.supervisor.processes import ManagedProcess
        proc = ManagedProcess("sleeper", "tests.services.sleeper", {{}}, Path({str(tmp_path)!r}) / "sleeper.log")
        proc.start()
        print(proc.pid, flush=True)
        time.sleep(60)
    """)
    supervisor = subprocess.Popen([sys.executable, "-c", parent], cwd=REPO, stdout=subprocess.PIPE, text=True)
    child = int(supervisor.stdout.readline())
    assert _alive(child)
    supervisor.send_signal(signal.SIGKILL)
    supervisor.wait()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and _alive(child):
        time.sleep(0.05)
    assert not _alive(child), "a service outlived its supervisor"


def test_an_inbox_is_bounded_in_bytes_as_well_as_messages() -> None:
    from proto.codec import encode
    from proto.messages import Control
    from services.runtime.metrics import ServiceMetrics
    from services.runtime.shell import Inbox

    metrics = ServiceMetrics("test", "0")
    inbox = Inbox("control", Control, maxsize=100, metrics=metrics, max_bytes=3 * len(encode(Control("stop", "x" * 500))))
    for i in range(5):
        inbox.on_payload("k", encode(Control("stop", f"{i}" * 500)))
    kept = [message.argument[0] for _, message in inbox.drain()]
    assert kept == ["2", "3", "4"] and inbox.bytes == 0
    assert metrics.dropped.labels(reason="control_bytes_full")._value.get() == 2
    assert inbox.get(timeout=0.01) is None


def test_a_configuration_exit_stops_the_run_with_the_services_reason(tmp_path) -> None:
    from services.runtime.checkpoint import CONFIG_ERROR_EXIT
    from services.supervisor.processes import FatalServiceError, ManagedProcess

    log = tmp_path / "dynamics-learner.log"
    log.write_text("2026-12-02 05:00:00 dynamics-learner INFO x: started\n"
                   "2026-12-02 05:00:09 dynamics-learner ERROR dynamics-learner: the loss was not finite for 100 "
                   "updates in a row (no step was taken): the learning rate is likely too high for this model\n")
    proc = ManagedProcess("dynamics-learner", "services.dynamics_learner", {}, log)
    proc.process = subprocess.Popen([sys.executable, "-c", f"raise SystemExit({CONFIG_ERROR_EXIT})"])
    proc.process.wait()
    with pytest.raises(FatalServiceError, match="the learning rate is likely too high"):
        proc.check(time.monotonic())


def test_stale_forged_and_scoreless_graph_reports_cannot_break_the_finish_step(tmp_path) -> None:
    """Found by the live fuzz test: a graph report without scores (here a stale one) entered the
    history and the finish step's learning curve failed on it (KeyError 'f1'), leaving no summary."""
    import dataclasses

    import numpy as np

    from proto.codec import encode
    from proto.messages import GraphReport
    from services.supervisor.report import plot_learning_curve
    from services.supervisor.supervisor import Supervisor

    sup = Supervisor(build_config(RunConfig, router_port=7447, run_dir=str(tmp_path), progress=False))
    n = 3
    real = GraphReport(kind="cdl", weights_version=5, env_steps=100, updates=10, factor_names=("a", "b", "c"),
                       cmi=np.zeros((n, n + 1), np.float32), adjacency=np.zeros((n, n + 1), np.uint8), threshold=0.02,
                       controllable=(), action_relevant=(), action_irrelevant=(), metrics={"f1": 0.5, "accuracy": 0.9},
                       timestamp=0.0)
    key = "causeway/run/graph/cdl"
    (tmp_path / "checkpoints").mkdir()  # the learner's record: it published up to version 6
    (tmp_path / "checkpoints" / "dynamics-learner-0.version.json").write_text('{"version": 6}')
    sup._on_graph(key, encode(real))
    sup._on_graph(key, encode(dataclasses.replace(real, weights_version=1, metrics={})))  # stale: ignored
    sup._on_graph(key, encode(dataclasses.replace(real, weights_version=2**62, metrics={"f1": 1.0})))  # refused
    assert len(sup.history) == 1 and sup.last_report.weights_version == 5
    sup._on_graph(key, encode(dataclasses.replace(real, weights_version=6, env_steps=200, metrics={})))  # no scores
    assert len(sup.history) == 2
    plot_learning_curve(sup.history, tmp_path / "learning_curve.png")
    assert (tmp_path / "learning_curve.png").stat().st_size > 1000


def test_stats_beats_of_processes_the_run_did_not_start_do_not_count(tmp_path) -> None:
    """A beat forged on stats/env-worker/<any> (the env-worker role may publish there) would otherwise
    add its env steps to the run's total and end the run on its env-step budget."""
    from proto.codec import encode
    from proto.messages import ServiceStats
    from services.supervisor.supervisor import Supervisor
    from services.supervisor.wiring import service_configs, worker_config

    sup = Supervisor(build_config(RunConfig, router_port=7447, run_dir=str(tmp_path), progress=False, max_env_steps=10_000))
    sup.process("env-worker-0", "services.env_worker", worker_config(sup.cfg, "", 0))
    sup.process("dynamics-learner", "services.dynamics_learner", service_configs(sup.cfg, "")["dynamics-learner"])
    for service, instance, values in (("env-worker", "0", {"env_steps": 300.0}), ("env-worker", "fuzz", {"env_steps": 1e12}),
                                      ("env-worker", "7", {"env_steps": 1e12}), ("dynamics-learner", "0", {"updates": 5.0}),
                                      ("dynamics-learner", "1", {"updates": 1e9}), ("graph-evaluator", "0", {"reports": 1.0})):
        sup._on_stats(f"causeway/{sup.cfg.run_id}/stats/{service}/{instance}", encode(ServiceStats(service, instance, values)))
    assert sup.progress.env_steps() == 300 and sup.progress.updates() == 5
    assert set(sup.progress.stats) == {("env-worker", "0"), ("dynamics-learner", "0")}


def test_the_summary_keeps_the_report_the_stop_rule_judged(tmp_path) -> None:
    """Seen in a stop-rule run: the rule stopped on a stable graph with nothing undecided, one more
    report (a changed graph, 2 entries undecided) came in before the summary, and the summary showed
    it beside "no undecided entry". Reports arriving while the rule decides, or after, are dropped."""
    import dataclasses

    import numpy as np

    from proto.codec import encode
    from proto.messages import GraphReport
    from services.supervisor.supervisor import Supervisor

    sup = Supervisor(build_config(RunConfig, router_port=7447, run_dir=str(tmp_path), progress=False, stable_reports=2,
                                  evaluator_edge_rule="fdr"))
    n = 3
    settled = GraphReport(kind="cdl", weights_version=1, env_steps=100, updates=10, factor_names=("a", "b", "c"),
                          cmi=np.zeros((n, n + 1), np.float32), adjacency=np.eye(n, n + 1, dtype=np.uint8),
                          threshold=0.02, controllable=(), action_relevant=(), action_irrelevant=(),
                          metrics={"f1": 1.0}, timestamp=1.0, undecided=np.zeros((n, n + 1), np.uint8),
                          cmi_stderr=np.full((n, n + 1), 1e-3, np.float32), edge_rule="fdr", fdr=0.05, min_cmi=5e-3)
    changed = dataclasses.replace(settled, weights_version=3, timestamp=3.0, adjacency=np.ones((n, n + 1), np.uint8),
                                  metrics={"f1": 0.5}, undecided=np.ones((n, n + 1), np.uint8))
    key = "causeway/run/graph/cdl"
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "dynamics-learner-0.version.json").write_text('{"version": 10}')
    sup._on_graph(key, encode(settled))
    sup._check_budget(1.0)
    assert not sup.stop_reason
    sup._on_graph(key, encode(dataclasses.replace(settled, weights_version=2, timestamp=2.0)))
    judge = sup.stop_rules.check

    def arrives_meanwhile(*args):  # the real rule; the newer report lands while it decides
        reason = judge(*args)
        sup._on_graph(key, encode(changed))
        return reason

    sup.stop_rules.check = arrives_meanwhile
    sup._check_budget(2.0)
    assert sup.stop_reason.startswith("graph stable")
    assert sup.last_report.weights_version == 2 and [h["f1"] for h in sup.history] == [1.0, 1.0]
    sup._on_graph(key, encode(dataclasses.replace(changed, weights_version=4, timestamp=4.0)))  # after the stop
    assert sup.last_report.weights_version == 2 and len(sup.history) == 2


def test_the_summary_names_the_commit_the_run_started_at(tmp_path, monkeypatch) -> None:
    """Seen after a long run: a commit made while it ran was the summary's ``git_revision``, not the
    code that ran (the run directory's ``git_revision`` file, written at the start, was right)."""
    import services.supervisor.supervisor as module

    sup = module.Supervisor(build_config(RunConfig, router_port=7447, run_dir=str(tmp_path), progress=False))
    monkeypatch.setattr(module, "git_revision", lambda: "a" * 40)
    sup._write_run_config()
    monkeypatch.setattr(module, "git_revision", lambda: "b" * 40)
    seen = {}
    monkeypatch.setattr(module, "analyse", lambda cfg, run_dir, record, stream: seen.update(record.facts) or {})
    sup.finish(1.0)
    assert seen["git_revision"] == "a" * 40
    assert (tmp_path / "git_revision").read_text() == "a" * 40 + "\n"
