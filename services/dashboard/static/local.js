// The local-graph panel: one example transition's estimated local graph beside its truth and the
// comparison (the global graph's heat maps, reused), arrows through the examples, the pooled scores
// as tiles and over env steps. Shown only while the run has local-graph reports.

import { LOCAL_SERIES, renderChart, renderChartLegend } from './chart.js';
import { $, fmt } from './dom.js';
import { GraphViews } from './heatmap.js';

const IDS = { learned: 'local-estimated', truth: 'local-truth', compare: 'local-compare' };
const LARGE_GRAPH_COLUMNS = 16; // beyond this, two heat maps per row, as on the global board
const ESTIMATORS = { pcmi: { score: 'pCMI', unit: 'nats', name: 'point-wise CMI' } };

function labelsOf(estimator) {
  const known = ESTIMATORS[estimator];
  return { score: known ? known.score : estimator, unit: known ? known.unit : '', learned: 'estimated' };
}

/** Example `k` of a local-graph document as the graph-like object GraphViews draws. */
export function exampleGraph(local, k) {
  const ex = local.examples[k];
  return {
    factor_names: local.factor_names, cause_names: local.cause_names, threshold: local.threshold,
    cmi_max: local.score_max, labels: labelsOf(local.estimator),
    cells: ex.scores.map((row, i) => row.map((score, j) => ({
      cmi: score, learned: ex.predicted[i][j] === 1, truth: ex.truth[i][j] === 1, outcome: ex.outcomes[i][j],
    }))),
  };
}

export class LocalPanel {
  constructor() {
    this.local = null;
    this.example = 0;
    this.views = new GraphViews($('legend-local'), IDS);
    $('local-prev').addEventListener('click', () => this.step(-1));
    $('local-next').addEventListener('click', () => this.step(1));
  }

  /** Draw `local` (a snapshot's local_graph), or hide the panel when it is null. */
  render(local) {
    this.local = local;
    $('local-panel').hidden = !local;
    if (!local) {
      this.example = 0; // another run: start at its first example
      return;
    }
    const count = local.examples.length;
    if (this.example >= count) this.example = 0;
    const known = ESTIMATORS[local.estimator];
    setText('local-estimator', known ? known.name : local.estimator);
    setText('local-sub', `${local.kind} · scored over ${fmt.int(local.num_transitions)} held-out transitions, `
      + `self-edges apart · weights v${local.weights_version} · ${fmt.int(local.env_steps)} env steps`);
    this.renderKpis(local.metrics);
    this.drawExample();
    this.drawChart();
    document.body.dataset.localWeightsVersion = String(local.weights_version);
  }

  step(delta) {
    const count = this.local ? this.local.examples.length : 0;
    if (!count) return;
    this.example = (this.example + delta + count) % count;
    this.drawExample();
  }

  renderKpis(m) {
    setText('local-roc-auc', fmt.ratio(m.roc_auc));
    setText('local-pr-auc', fmt.ratio(m.pr_auc));
    setText('local-pr-note', m.positive_rate == null ? '' : `chance ${fmt.ratio(m.positive_rate)}`);
    setText('local-best-f1', fmt.ratio(m.best_f1));
    setText('local-best-threshold', m.best_threshold == null ? '' : `at ε = ${fmt.cmi(m.best_threshold)}`);
    setText('local-f1', fmt.ratio(m.f1));
    setText('local-f1-note', m.precision == null ? '' : `P ${fmt.ratio(m.precision)} · R ${fmt.ratio(m.recall)}`);
    setText('local-positive-rate', m.positive_rate == null ? '–' : `${(100 * m.positive_rate).toFixed(1)}%`);
    setText('local-threshold', fmt.cmi(this.local.threshold));
  }

  drawExample() {
    const local = this.local;
    const count = local.examples.length;
    $('local-maps').hidden = !count;
    $('local-no-examples').hidden = count > 0;
    $('local-prev').disabled = count < 2;
    $('local-next').disabled = count < 2;
    const shown = count < local.num_examples ? ` (${local.num_examples} sent)` : '';
    setText('local-example', count ? `transition ${this.example + 1} of ${count}${shown}` : 'no examples');
    if (!count) return;
    $('local-maps').classList.toggle('large', local.cause_names.length > LARGE_GRAPH_COLUMNS);
    this.views.render(exampleGraph(local, this.example));
    const { confusion } = local.examples[this.example];
    ['tp', 'fp', 'fn', 'tn'].forEach((o) => setText(`local-count-${o}`, String(confusion[o])));
  }

  drawChart() {
    if (!this.local) return;
    renderChart($('local-chart'), this.local.history, LOCAL_SERIES);
    renderChartLegend($('local-chart-legend'), this.local.history, LOCAL_SERIES);
  }

  /** Redraw at a new width (the heat maps and chart size to their boxes). */
  resize() {
    if (!this.local) return;
    if (this.local.examples.length) this.views.render(exampleGraph(this.local, this.example));
    this.drawChart();
  }
}

function setText(id, text) { $(id).textContent = text; }
