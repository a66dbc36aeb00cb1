"""The live page in headless Chromium: a real Zenoh router, the dashboard as a process, reports over Zenoh.

Loads the page, waits for the first report to render, publishes a new one and waits for the DOM to
change without a reload, checks the heat maps, classes, scores and the hover tooltip, and leaves a
screenshot in test-artifacts/dashboard.png. Then the local-graph panel: shown with its scores and an
example transition's matrices for runs with local-graph reports (with or without a global graph),
hidden for runs without; screenshot in test-artifacts/dashboard-local.png. Then a run with a reward
graph (CBM): the reward row under the heat maps, its scores and the minimal abstraction's classes;
screenshot in test-artifacts/dashboard-reward.png; and its standard errors and undecided entries
under the fdr rule (issue 22).
"""
from __future__ import annotations

import functools
import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from proto import topics
from proto.codec import encode
from services.bus.router import free_tcp_port, start_router, wait_for_router
from services.bus.zenoh_transport import ZenohTransport
from tests.dashboard.browser import CHROMIUM, Browser
from tests.dashboard.reports import make_local_report, make_report, make_reward_report, make_stats
from tests import waiting

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]
REPO = Path(__file__).resolve().parents[2]
SCREENSHOT = REPO / "test-artifacts" / "dashboard.png"
LOCAL_SCREENSHOT = REPO / "test-artifacts" / "dashboard-local.png"
REWARD_SCREENSHOT = REPO / "test-artifacts" / "dashboard-reward.png"
RUN = "chemical-demo"


wait_for = functools.partial(waiting.wait_for, interval=0.05, tolerate=(OSError,))

def fetch_json(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=3) as reply:
        return json.loads(reply.read())


def text(browser: Browser, selector: str) -> str:
    return browser.evaluate(f"document.querySelector({json.dumps(selector)}).textContent")


@pytest.fixture
def stack(tmp_path: Path):
    """A router, a publisher on it, and the dashboard process; yields (publisher, latest graph, page URL)."""
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} missing: apt-get install --no-install-recommends chromium (make sysdeps)")
    connect = f"tcp/127.0.0.1:{free_tcp_port()}"
    router = start_router(connect)
    wait_for_router(connect)
    http_port = free_tcp_port()
    env = {**os.environ, "CAUSEWAY_RUN_ID": RUN, "CAUSEWAY_ZENOH_CONNECT": connect, "CAUSEWAY_HTTP_HOST": "127.0.0.1",
           "CAUSEWAY_HTTP_PORT": str(http_port), "CAUSEWAY_RUN_DIR": str(tmp_path / "run"), "PYTHONUNBUFFERED": "1"}
    log = open(tmp_path / "dashboard.log", "wb")
    process = subprocess.Popen([sys.executable, "-m", "services.dashboard"], cwd=REPO, env=env, stdout=log,
                               stderr=subprocess.STDOUT)
    publisher = ZenohTransport(connect)
    latest = publisher.serve_latest(topics.graph(RUN, "cdl"))
    base = f"http://127.0.0.1:{http_port}"
    try:
        wait_for(lambda: fetch_json(f"{base}/healthz")["status"] == "ok", 20, "the dashboard's /healthz")
        yield publisher, latest, base
    finally:
        latest.close()
        publisher.close()
        process.send_signal(signal.SIGTERM)
        try:
            code = process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            code = process.wait()
        log.close()
        router.close()
        assert code == 0, (tmp_path / "dashboard.log").read_text()


def publish_history(publisher: ZenohTransport, latest, base: str, versions: range) -> None:
    """Reports the dashboard sees arrive one after the other (a learning curve), ending at ``versions[-1]``."""
    for v in versions:
        latest.set(encode(make_report(3, version=v, errors=max(1, 9 - v), seed=v)))
        time.sleep(0.03)
    for service, instance, values in (("env-worker", "0", {"env_steps": 30_000.0, "episodes": 600.0}),
                                      ("env-worker", "1", {"env_steps": 29_500.0, "episodes": 590.0}),
                                      ("dynamics-learner", "0", {"updates": 1_500.0, "env_steps": 30_000.0}),
                                      ("graph-evaluator", "0", {"evaluated_version": float(versions[-1])})):
        publisher.publish(topics.stats(RUN, service, instance), encode(make_stats(service, instance, **values)))
    wait_for(lambda: fetch_json(f"{base}/api/runs/{RUN}")["graph"]["weights_version"] == versions[-1], 10,
             f"report v{versions[-1]} at the dashboard")


def test_live_page_renders_updates_without_reload_and_explains_cells(stack) -> None:
    publisher, latest, base = stack
    latest.set(encode(make_report(3, version=1, errors=8, seed=1)))
    wait_for(lambda: fetch_json(f"{base}/api/runs/{RUN}")["graph"], 10, "the first report")
    publish_history(publisher, latest, base, range(2, 7))
    with Browser(width=1440, height=1000) as browser:
        browser.navigate(f"{base}/?run={RUN}")
        browser.wait_for("document.getElementById('status').dataset.state === 'live'"
                         " && document.getElementById('weights-version').textContent === '6'", 10, "the first render")
        for heatmap in ("learned", "truth", "compare"):
            assert browser.evaluate(f"document.querySelectorAll('#heatmap-{heatmap} rect.cell').length") == 9 * 10
        browser.evaluate("window.loadedOnce = true")
        assert browser.evaluate("document.getElementById('local-panel').hidden") is True  # no local reports
        shown = make_report(3, version=6, errors=3, seed=6).metrics  # the report on the page now
        assert shown["with_self_best_threshold_f1"] != shown["best_threshold_f1"]  # the two scorings differ
        assert text(browser, "#with-self-f1") == f"{shown['with_self_best_threshold_f1']:.3f}"
        assert text(browser, "#with-self-note") == f"accuracy {shown['with_self_accuracy']:.3f}"
        assert "best F1, Table 3.1 scoring" in text(browser, "#chart-legend")
        assert browser.evaluate("document.querySelectorAll('#chart path.series-with_self_best_threshold_f1').length") == 1

        second = make_report(3, version=7, errors=0, seed=7)
        assert f"{second.metrics['f1']:.3f}" != text(browser, "#f1")
        latest.set(encode(second))
        browser.wait_for("document.getElementById('weights-version').textContent === '7'", 10, "the live update")
        assert browser.evaluate("window.loadedOnce === true"), "the page reloaded instead of updating live"
        assert text(browser, "#f1") == f"{second.metrics['f1']:.3f}"
        assert text(browser, "#env-steps") == f"{second.env_steps:,}"
        assert text(browser, "#status-text") == "live"
        chips = browser.evaluate("Object.fromEntries([...document.querySelectorAll('#classes .class-block')].map("
                                 "b => [b.dataset.class, [...b.querySelectorAll('.chip')].map(c => c.textContent)]))")
        for cls in ("controllable", "action_relevant", "action_irrelevant"):
            assert chips[cls] == [second.factor_names[i] for i in getattr(second, cls)]
        assert len(chips["controllable"]) == 3  # the three colours, set by the action
        outcomes = browser.evaluate("[...document.querySelectorAll('#heatmap-compare rect.cell')]"
                                    ".filter(r => r.classList.contains('outcome-tp')).length")
        assert outcomes == int(second.true_graph.sum()) - 9  # every true edge found, self-edges apart

        assert browser.evaluate("document.getElementById('kpi-identifiable').hidden") is True  # Chemical: = F1
        assert "identifiable F1" not in text(browser, "#chart-legend")
        third = replace(make_report(3, version=8, errors=0, seed=7),
                        metrics={**second.metrics, "identifiable_f1": 0.987})  # as on manipulation
        latest.set(encode(third))
        browser.wait_for("!document.getElementById('kpi-identifiable').hidden", 10, "the identifiable F1")
        assert text(browser, "#identifiable-f1") == "0.987"
        assert "identifiable F1" in text(browser, "#chart-legend")

        browser.fit_to_content()
        browser.hover("#heatmap-learned rect.cell[data-i='3'][data-j='0']")  # obj0.color -> obj1.color
        tip = browser.wait_for("!document.getElementById('tooltip').hidden"
                               " && document.getElementById('tooltip').innerText", 5, "the tooltip")
        assert "obj0.color → obj1.color" in tip and "true positive" in tip
        shown = float(re.search(r"CMI\s+([-0-9.e]+) nats", tip).group(1))
        assert shown == pytest.approx(float(second.cmi[3, 0]), rel=5e-3)
        browser.screenshot(SCREENSHOT)
        older = {k: v for k, v in third.metrics.items() if not k.startswith("with_self_")}  # an older evaluator
        latest.set(encode(replace(make_report(3, version=9, errors=0, seed=9), metrics=older)))
        browser.wait_for("document.getElementById('kpi-with-self').hidden", 10, "the Table 3.1 score hidden")
        assert browser.exceptions == []
    assert SCREENSHOT.stat().st_size > 30_000


def visible(browser: Browser, element_id: str) -> bool:
    return browser.evaluate(f"!document.getElementById({json.dumps(element_id)}).hidden")


def outcome_count(browser: Browser, outcome: str) -> int:
    return browser.evaluate(f"document.querySelectorAll('#local-compare rect.cell.outcome-{outcome}').length")


def check_example(browser: Browser, report, k: int) -> None:
    """The panel shows example ``k`` of ``report``: its outcomes on the comparison map, its counts."""
    predicted = report.scores[k] >= report.threshold
    off = ~np.eye(*predicted.shape, dtype=bool)
    truth = report.truth[k].astype(bool)
    for outcome, cells in (("tp", predicted & truth), ("fp", predicted & ~truth), ("fn", ~predicted & truth)):
        assert outcome_count(browser, outcome) == int((cells & off).sum()), outcome
        assert text(browser, f"#local-count-{outcome}") == str(int((cells & off).sum()))
    assert outcome_count(browser, "self") == predicted.shape[0]


def publish_local(publisher: ZenohTransport, base: str, run: str, versions: range, kind: str = "cdl") -> None:
    for v in versions:
        publisher.publish(topics.local(run, kind), encode(make_local_report(3, version=v, errors=max(0, 6 - v), seed=v,
                                                                            kind=kind)))
        time.sleep(0.03)
    wait_for(lambda: fetch_json(f"{base}/api/runs/{run}")["local_graph"]["weights_version"] == versions[-1], 10,
             f"local report v{versions[-1]} of {run}")


def select_run(browser: Browser, run: str) -> None:
    browser.evaluate(f"(() => {{ const s = document.getElementById('run'); s.value = {json.dumps(run)};"
                     "s.dispatchEvent(new Event('change')); })()")


def test_local_graph_panel_shows_for_runs_with_local_reports_only(stack) -> None:
    publisher, latest, base = stack
    latest.set(encode(make_report(3, version=2, errors=2)))  # RUN: a global graph, no local graphs
    publisher.publish(topics.graph("both", "cdl"), encode(make_report(3, version=4, errors=1, seed=4)))
    publish_local(publisher, base, "both", range(1, 5))
    publish_local(publisher, base, "local-only", range(1, 3), kind="elden")
    shown = make_local_report(3, version=4, errors=2, seed=4)  # the report "both" has now
    with Browser(width=1440, height=1000) as browser:
        browser.navigate(f"{base}/?run=both")
        browser.wait_for("document.body.dataset.localWeightsVersion === '4'"
                         " && document.body.dataset.weightsVersion === '4'", 10, "both panels")
        assert visible(browser, "local-panel") and visible(browser, "kpis") and visible(browser, "heatmap-learned")
        m = shown.metrics
        assert text(browser, "#local-roc-auc") == f"{m['roc_auc']:.3f}"
        assert text(browser, "#local-pr-auc") == f"{m['pr_auc']:.3f}"
        assert text(browser, "#local-best-f1") == f"{m['best_f1']:.3f}"
        assert text(browser, "#local-positive-rate") == f"{100 * m['positive_rate']:.1f}%"
        assert text(browser, "#local-estimator") == "point-wise CMI"
        for heatmap in ("estimated", "truth", "compare"):
            assert browser.evaluate(f"document.querySelectorAll('#local-{heatmap} rect.cell').length") == 9 * 10
        labels = browser.evaluate("[...document.querySelectorAll('#local-estimated text')].map(t => t.textContent)")
        assert set(labels) == {*shown.factor_names, "action"}
        check_example(browser, shown, 0)
        assert text(browser, "#local-example") == "transition 1 of 4"
        browser.evaluate("document.getElementById('local-next').click()")
        browser.wait_for("document.getElementById('local-example').textContent === 'transition 2 of 4'", 5, "step")
        check_example(browser, shown, 1)
        assert browser.evaluate("document.querySelectorAll('#local-chart path.series-roc_auc').length") == 1
        assert "PR AUC" in text(browser, "#local-chart-legend")

        browser.evaluate("window.loadedOnce = true")
        newer = make_local_report(3, version=5, errors=0, seed=5)
        publisher.publish(topics.local("both", "cdl"), encode(newer))
        browser.wait_for("document.body.dataset.localWeightsVersion === '5'", 10, "the live local update")
        assert browser.evaluate("window.loadedOnce === true"), "the page reloaded instead of updating live"
        assert text(browser, "#local-example") == "transition 2 of 4"  # the example stepped to stays
        check_example(browser, newer, 1)
        browser.fit_to_content()
        browser.hover("#local-estimated rect.cell[data-i='3'][data-j='0']")
        tip = browser.wait_for("!document.getElementById('tooltip').hidden"
                               " && document.getElementById('tooltip').innerText", 5, "the tooltip")
        assert "obj0.color → obj1.color" in tip and "pCMI" in tip and "estimated" in tip
        browser.screenshot(LOCAL_SCREENSHOT)

        select_run(browser, "local-only")  # a method with local graphs and no global graph
        browser.wait_for("document.body.dataset.localWeightsVersion === '2'", 10, "the local-only run")
        assert visible(browser, "local-panel") and not visible(browser, "kpis") and not visible(browser, "waiting")
        assert browser.evaluate("document.getElementById('board').classList.contains('local-only')")
        assert text(browser, "#kind") == "elden"
        select_run(browser, RUN)
        browser.wait_for("document.body.dataset.weightsVersion === '2'"
                         " && document.getElementById('local-panel').hidden", 10, "the global-only run, no local panel")
        assert visible(browser, "kpis") and visible(browser, "heatmap-learned")
        assert browser.exceptions == []
    assert LOCAL_SCREENSHOT.stat().st_size > 30_000


def test_a_reward_graph_shows_as_a_reward_row_with_the_minimal_abstraction(stack) -> None:
    publisher, latest, base = stack
    latest.set(encode(make_report(3, version=2, errors=2)))  # RUN: CDL, no reward graph
    cbm = publisher.serve_latest(topics.graph("cbm-demo", "cbm"))
    report = make_reward_report(3, version=3, errors=1, reward_errors=2)
    cbm.set(encode(report))
    try:
        wait_for(lambda: fetch_json(f"{base}/api/runs/cbm-demo")["graph"], 10, "the CBM report")
        with Browser(width=1440, height=1000) as browser:
            browser.navigate(f"{base}/?run=cbm-demo")
            browser.wait_for("document.body.dataset.weightsVersion === '3'", 10, "the CBM run")
            for heatmap in ("learned", "truth", "compare"):
                assert browser.evaluate(f"document.querySelectorAll('#heatmap-{heatmap} rect.cell').length") == 10 * 10
            assert text(browser, "#heatmap-learned text.reward-label") == "reward"
            compare = browser.evaluate("[...document.querySelectorAll('#heatmap-compare rect.cell[data-i=\\'9\\']')]"
                                       ".map(r => r.getAttribute('class').replace('cell outcome-', ''))")
            assert compare == ["tp", "fp", "fp", "tp", "tn", "tn", "tp", "tn", "tn", "tp"]
            assert text(browser, "#reward-counts") == "reward row: TP 4 · FP 2 · FN 0 · TN 4"
            assert visible(browser, "kpi-reward") and visible(browser, "kpi-abstraction")
            assert text(browser, "#reward-f1") == f"{report.metrics['reward_f1']:.3f}"
            assert text(browser, "#abstraction-accuracy") == f"{report.metrics['abstraction_accuracy']:.3f}"
            assert "Theorem 4.1" in text(browser, "#classes-sub")
            chips = browser.evaluate("Object.fromEntries([...document.querySelectorAll('#classes .class-block')].map("
                                     "b => [b.dataset.class, [...b.querySelectorAll('.chip')].map(c => c.textContent)]))")
            assert set(chips) == {"reward_parents", "reward_ancestors", "dropped"}
            assert {"obj0.x", "obj0.y"} <= set(chips["reward_parents"])
            assert "reward parents' F1" in text(browser, "#chart-legend")
            browser.fit_to_content()
            browser.hover("#heatmap-learned rect.cell[data-i='9'][data-j='1']")  # obj0.x -> reward, a false positive
            tip = browser.wait_for("!document.getElementById('tooltip').hidden"
                                   " && document.getElementById('tooltip').innerText", 5, "the tooltip")
            assert "obj0.x → reward" in tip and "reward CMI" in tip and "0.0100" in tip and "false positive" in tip
            browser.screenshot(REWARD_SCREENSHOT)
            select_run(browser, RUN)
            browser.wait_for("document.body.dataset.weightsVersion === '2'", 10, "the CDL run")
            assert not visible(browser, "kpi-reward") and not visible(browser, "reward-counts")
            assert browser.evaluate("document.querySelectorAll('#heatmap-learned rect.cell').length") == 9 * 10
            assert "Definitions 3.1" in text(browser, "#classes-sub")
            assert browser.exceptions == []
    finally:
        cbm.close()
    assert REWARD_SCREENSHOT.stat().st_size > 30_000


def test_undecided_entries_are_outlined_and_hover_shows_the_interval(stack) -> None:
    publisher, latest, base = stack
    plain = make_report(3, version=2, errors=2)
    undecided = np.zeros(plain.cmi.shape, np.uint8)
    undecided[3, 0] = undecided[0, 9] = 1
    report = replace(plain, cmi_stderr=np.full(plain.cmi.shape, 0.002, np.float32), undecided=undecided,
                     edge_rule="fdr", fdr=0.05, min_cmi=5e-4)
    latest.set(encode(report))
    wait_for(lambda: fetch_json(f"{base}/api/runs/{RUN}")["graph"], 10, "the report")
    with Browser(width=1440, height=1000) as browser:
        browser.navigate(f"{base}/?run={RUN}")
        browser.wait_for("document.body.dataset.weightsVersion === '2'", 10, "the first render")
        outlined = browser.evaluate("[...document.querySelectorAll('#heatmap-learned rect.cell-undecided')]"
                                    ".filter(r => r.getAttribute('visibility') === 'visible').length")
        assert outlined == 2
        legend = text(browser, "#legend-learned")
        assert "undecided (2)" in legend and "at FDR 0.05" in legend
        browser.fit_to_content()
        browser.hover("#heatmap-learned rect.cell[data-i='3'][data-j='0']")
        tip = browser.wait_for("!document.getElementById('tooltip').hidden"
                               " && document.getElementById('tooltip').innerText", 5, "the tooltip")
        low, high = (float(x) for x in re.search(r"95% interval\s+([-0-9.e]+) – ([-0-9.e]+) nats", tip).groups())
        cmi = float(report.cmi[3, 0])
        assert low == pytest.approx(cmi - 1.96 * 0.002, rel=5e-3) and high == pytest.approx(cmi + 1.96 * 0.002, rel=5e-3)
        assert "crosses the boundary" in tip and "at FDR 0.05" in tip
        assert browser.exceptions == []
    latest.set(encode(replace(report, weights_version=3, bias="mirror", min_cmi=3.5e-4)))   # the level mirror cut
    with Browser(width=1440, height=1000) as browser:
        browser.navigate(f"{base}/?run={RUN}")
        browser.wait_for("document.body.dataset.weightsVersion === '3'", 10, "the mirror report")
        legend = text(browser, "#legend-learned")
        assert "CMI ≥ 3.50e-4 (the mirror level) at FDR 0.05" in legend and "test of" not in legend
        assert browser.exceptions == []


def test_the_reward_row_shows_its_intervals_and_undecided_entries(stack) -> None:
    """CBM under the fdr rule with an estimated bias: the reward row's standard errors and undecided
    entries reach the page as the dynamics graph's do, its rule (against min_cmi) named apart."""
    publisher, latest, base = stack
    plain = make_reward_report(3, version=4, errors=1, reward_errors=2)
    undecided = np.zeros(plain.cmi.shape, np.uint8)
    undecided[3, 0] = 1
    reward_undecided = np.zeros(10, np.uint8)
    reward_undecided[2] = 1  # obj0.y -> reward
    null = np.full(plain.cmi.shape, 1e-3, np.float32)
    report = replace(plain, cmi_stderr=np.full(plain.cmi.shape, 0.002, np.float32), undecided=undecided,
                     edge_rule="fdr", fdr=0.05, min_cmi=2e-3, bias="pooled", cmi_null=null,
                     reward_stderr=np.full(10, 0.004, np.float32), reward_undecided=reward_undecided,
                     reward_min_cmi=5e-3)  # the row's own effect size, not the dynamics graph's min_cmi
    cbm = publisher.serve_latest(topics.graph("cbm-tested", "cbm"))
    cbm.set(encode(report))
    try:
        wait_for(lambda: fetch_json(f"{base}/api/runs/cbm-tested")["graph"], 10, "the CBM report")
        with Browser(width=1440, height=1000) as browser:
            browser.navigate(f"{base}/?run=cbm-tested")
            browser.wait_for("document.body.dataset.weightsVersion === '4'", 10, "the CBM run")
            outlined = browser.evaluate("[...document.querySelectorAll('#heatmap-learned rect.cell-undecided')]"
                                        ".filter(r => r.getAttribute('visibility') === 'visible')"
                                        ".map(r => [Number(r.getAttribute('y')), Number(r.getAttribute('x'))])")
            assert len(outlined) == 2 and max(outlined)[0] > min(outlined)[0]  # one of them in the reward row
            legend = text(browser, "#legend-learned")
            assert "undecided (2, 1 in the reward row)" in legend
            assert "its output's largest null at FDR 0.05" in legend and "reward row: CMI > 0.00500" in legend
            browser.fit_to_content()
            browser.hover("#heatmap-learned rect.cell[data-i='9'][data-j='1']")  # obj0.x -> reward, 0.05 ± 0.004
            tip = browser.wait_for("!document.getElementById('tooltip').hidden"
                                   " && document.getElementById('tooltip').innerText", 5, "the tooltip")
            low, high = (float(x) for x in re.search(r"95% interval\s+([-0-9.e]+) – ([-0-9.e]+)", tip).groups())
            score = float(report.reward_scores[1])
            assert low == pytest.approx(score - 1.96 * 0.004, rel=5e-3) and high == pytest.approx(score + 1.96 * 0.004, rel=5e-3)
            assert "reward CMI" in tip and "CMI > 0.00500 at FDR 0.05" in tip and "permuted null" not in tip
            browser.hover("#heatmap-learned rect.cell[data-i='9'][data-j='2']")  # obj0.y -> reward, undecided
            tip = browser.wait_for("document.getElementById('tooltip').innerText.includes('obj0.y → reward')"
                                   " && document.getElementById('tooltip').innerText", 5, "the undecided cell")
            assert "crosses the boundary" in tip
            browser.hover("#heatmap-learned rect.cell[data-i='3'][data-j='0']")  # a dynamics entry: its null
            tip = browser.wait_for("document.getElementById('tooltip').innerText.includes('effect (t+1)')"
                                   " && document.getElementById('tooltip').innerText", 5, "a dynamics cell")
            assert re.search(r"permuted null\s+0\.00100 nats", tip) and "CMI > its output's largest null" in tip
            assert browser.exceptions == []
    finally:
        cbm.close()


def test_a_flam_run_shows_its_per_slot_latent_actions(stack) -> None:
    publisher, latest, base = stack
    latest.set(encode(make_report(3, version=2, errors=2)))  # RUN: CDL, no latent actions
    live = {"live_psnr": 24.5, "live_dci_d": 0.12, "live_dci_c": 0.25, "live_dci_i": 0.5,
            **{f"live_slot{k}_kl": kl for k, kl in enumerate((12.0, 3.0, 6.0, 0.5, 24.0))}}
    beat = make_stats("dynamics-learner", "0", updates=1_234.0, env_steps=40_000.0, **live)
    publisher.publish(topics.stats("flam-demo", "dynamics-learner", "0"), encode(beat))
    wait_for(lambda: fetch_json(f"{base}/api/runs/{RUN}")["graph"], 10, "the CDL report")
    with Browser(width=1440, height=1000) as browser:
        browser.navigate(f"{base}/?run=flam-demo")
        browser.wait_for("!document.getElementById('latent-panel').hidden", 10, "the latent-action panel")
        assert text(browser, "#latent-psnr") == "24.50" and text(browser, "#latent-dci-d") == "0.120"
        assert text(browser, "#latent-dci-c") == "0.250" and text(browser, "#latent-dci-i") == "0.500"
        assert "update 1,234" in text(browser, "#latent-sub")
        rows = browser.evaluate("[...document.querySelectorAll('#latent-slots tr[data-slot]')].map(r => "
                                "[r.dataset.slot, r.cells[1].textContent, r.querySelector('.latent-bar').style.width])")
        assert rows == [["0", "12.0", "50%"], ["1", "3.00", "12.5%"], ["2", "6.00", "25%"], ["3", "0.500", "2.1%"],
                        ["4", "24.0", "100%"]]
        assert not visible(browser, "latent-labels")  # no labelling factor-extractor in this run yet
        # the live scores each time they change: a second beat with new scores adds a point to both curves
        later = {**live, "live_psnr": 41.25, "live_dci_d": 0.5}
        publisher.publish(topics.stats("flam-demo", "dynamics-learner", "0"),
                          encode(make_stats("dynamics-learner", "0", updates=1_434.0, env_steps=48_000.0, **later)))
        browser.wait_for("document.getElementById('latent-psnr').textContent === '41.25'", 10, "the second scores")
        curves = browser.evaluate("['latent-psnr-chart', 'latent-dci-chart'].map(id => [...document.querySelectorAll("
                                  "`#${id} path.series`)].map(p => [p.getAttribute('class'), p.getAttribute('d').split('L').length]))")
        assert curves == [[["series series-psnr", 2]],
                          [["series series-dci_d", 2], ["series series-dci_c dashed", 2], ["series series-dci_i dotted", 2]]]
        ticks = browser.evaluate("[...document.querySelectorAll('#latent-psnr-chart .axis text')].map(t => t.textContent)")
        assert "25" in ticks and "40" in ticks and "env steps" in ticks  # the dB axis spans the scores
        history = fetch_json(f"{base}/api/runs/flam-demo")["live_history"]
        assert [(row["updates"], row["psnr"]) for row in history] == [(1_234.0, 24.5), (1_434.0, 41.25)]
        labels = make_stats("factor-extractor", "0", labelled_steps=5_120.0, unlabelled_steps=256.0,
                            labels_weights_version=7.0, **{f"stream_slot{k}_kl": kl for k, kl in enumerate((0.1, 30.0, 29.5))})
        publisher.publish(topics.stats("flam-demo", "factor-extractor", "0"), encode(labels))
        browser.wait_for("!document.getElementById('latent-labels').hidden", 10, "the labels line")
        assert "5,120 steps labelled with weights v7 (256 before" in text(browser, "#latent-labels")
        stream = browser.evaluate("[...document.querySelectorAll('#latent-slots tr[data-slot]')].map(r => "
                                  "r.querySelector('.stream-kl').textContent)")
        assert stream == ["0.100", "30.0", "29.5", "–", "–"]  # the learner names 5 slots, these labels 3
        select_run(browser, RUN)
        browser.wait_for("document.body.dataset.weightsVersion === '2'", 10, "the CDL run")
        assert not visible(browser, "latent-panel")
        assert browser.exceptions == []
