"""The live page shows SkiLD's induced-graph coverage (headless Chromium, a real router, the dashboard as
a process): a run whose policy-learner beats coverage values gets the panel, one row per dependency and
one column per phase; a run without them does not."""
from __future__ import annotations

import pytest

from proto import topics
from proto.codec import encode
from tests.dashboard.reports import make_report, make_stats
from tests.dashboard.test_browser import RUN, Browser, fetch_json, select_run, stack, text, visible, wait_for

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]
__all__ = ["stack"]  # the page fixture of test_browser, used here by name


def test_a_skild_run_shows_its_induced_graph_coverage(request: pytest.FixtureRequest) -> None:
    publisher, latest, base = request.getfixturevalue("stack")
    latest.set(encode(make_report(3, version=2, errors=2)))  # RUN: CDL, no coverage
    beat = make_stats("policy-learner", "0", updates=10.0, coverage_episodes_pretrain=40.0,
                      coverage_episodes_task=8.0, **{"coverage_pretrain: table, printer -> printer": 0.25,
                                                     "coverage_pretrain: agent, printer, action -> printer": 0.5,
                                                     "coverage_task: agent, printer, action -> printer": 0.75})
    publisher.publish(topics.stats("skild-demo", "policy-learner", "0"), encode(beat))
    wait_for(lambda: fetch_json(f"{base}/api/runs/{RUN}")["graph"], 10, "the CDL report")
    with Browser(width=1440, height=1000) as browser:
        browser.navigate(f"{base}/?run=skild-demo")
        browser.wait_for("!document.getElementById('coverage-panel').hidden", 10, "the coverage panel")
        rows = browser.evaluate("[...document.querySelectorAll('#coverage-table tr')].map(r => "
                                "[...r.cells].map(c => c.textContent))")
        assert rows == [["dependency", "pretrain (40 episodes)", "task (8 episodes)"],
                        ["agent, printer, action -> printer", "0.500", "0.750"],
                        ["table, printer -> printer", "0.250", "–"]]
        assert "Induced-graph coverage" in text(browser, "#coverage-panel h2")
        select_run(browser, RUN)
        browser.wait_for("document.body.dataset.weightsVersion === '2'", 10, "the CDL run")
        assert not visible(browser, "coverage-panel")
        assert browser.exceptions == []
