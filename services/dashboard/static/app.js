// Causeway live causal-graph page. No framework, no network beyond this server: one EventSource on
// /events?run=<run> delivers "runs", "snapshot" and "services" events; everything is drawn in SVG.
// A snapshot carries the global graph, local graphs, or both: the page shows what the run has.

import { LATENT_DCI_SERIES, LATENT_PSNR_SERIES, renderChart, renderChartLegend } from './chart.js';
import { $, debounce, fmt, html } from './dom.js';
import { GraphViews } from './heatmap.js';
import { LocalPanel } from './local.js';

const LARGE_GRAPH_COLUMNS = 16; // beyond this, two heat maps per row (see .board.large)
const SERVICE_VALUES = ['env_steps', 'updates', 'evaluated_version', 'heldout', 'episodes', 'runs', 'sse_clients'];
const STATUS_TEXT = { live: 'live', connecting: 'connecting…', reconnecting: 'reconnecting…', offline: 'offline' };

const params = new URLSearchParams(window.location.search);
const view = {
  run: params.get('run'), userPicked: params.has('run'), source: null, retry: null,
  graph: null, local: null, history: [], liveHistory: [], services: [], servicesAt: Date.now(), clockOffsetMs: 0,
};
const graphViews = new GraphViews($('legend-learned'));
const localPanel = new LocalPanel();
const serverNow = () => (Date.now() + view.clockOffsetMs) / 1000;

function setText(id, text) { $(id).textContent = text; }

function drawChart() {
  renderChart($('chart'), view.history);
  renderChartLegend($('chart-legend'), view.history);
}

function renderKpis(graph, previous) {
  const m = graph.metrics;
  setText('f1', fmt.ratio(m.f1));
  setText('accuracy', fmt.ratio(m.accuracy));
  setText('precision', fmt.ratio(m.precision));
  setText('recall', fmt.ratio(m.recall));
  setText('roc-auc', fmt.ratio(m.roc_auc));
  setText('best-f1', fmt.ratio(m.best_threshold_f1));
  setText('best-threshold', m.best_threshold == null ? '' : `at ε = ${fmt.cmi(m.best_threshold)}`);
  const identifiable = m.identifiable_f1 != null && m.identifiable_f1 !== m.f1;
  $('kpi-identifiable').hidden = !identifiable;
  setText('identifiable-f1', identifiable ? fmt.ratio(m.identifiable_f1) : '–');
  const withSelf = m.with_self_best_threshold_f1 != null;
  $('kpi-with-self').hidden = !withSelf;
  setText('with-self-f1', withSelf ? fmt.ratio(m.with_self_best_threshold_f1) : '–');
  setText('with-self-note', withSelf ? `accuracy ${fmt.ratio(m.with_self_accuracy)}` : '');
  setText('env-steps', fmt.int(graph.env_steps));
  setText('updates', fmt.int(graph.updates));
  setText('weights-version', String(graph.weights_version));
  setText('last-update', fmt.clock(graph.received_at));
  const delta = $('f1-delta');
  if (previous && previous.weights_version !== graph.weights_version && m.f1 != null && previous.metrics.f1 != null) {
    const d = m.f1 - previous.metrics.f1;
    delta.textContent = `${d >= 0 ? '▲' : '▼'} ${Math.abs(d).toFixed(3)} vs v${previous.weights_version}`;
    delta.className = `kpi-note ${d > 0 ? 'up' : d < 0 ? 'down' : ''}`;
    const kpis = document.querySelector('.kpis');
    kpis.classList.remove('flash');
    void kpis.offsetWidth; // restart the animation
    kpis.classList.add('flash');
  } else if (!previous) {
    delta.textContent = '';
  }
  ['tp', 'fp', 'fn', 'tn'].forEach((o) => setText(`count-${o}`, graph.confusion ? String(graph.confusion[o]) : ''));
  renderRewardKpis(graph);
}

// A method with a reward graph (CBM): its reward parents' F1 and the minimal abstraction's accuracy.
function renderRewardKpis(graph) {
  const m = graph.metrics;
  const reward = Boolean(graph.reward) && m.reward_f1 != null;
  $('kpi-reward').hidden = !reward;
  setText('reward-f1', reward ? fmt.ratio(m.reward_f1) : '–');
  setText('reward-note', reward ? `accuracy ${fmt.ratio(m.reward_accuracy)}` : '');
  const abstraction = Boolean(graph.reward) && m.abstraction_accuracy != null;
  $('kpi-abstraction').hidden = !abstraction;
  setText('abstraction-accuracy', abstraction ? fmt.ratio(m.abstraction_accuracy) : '–');
  setText('abstraction-note', abstraction ? `true reward parents: ${fmt.ratio(m.abstraction_accuracy_true_reward)}` : '');
  const counts = graph.reward && graph.reward.confusion;
  $('reward-counts').hidden = !counts;
  setText('reward-counts', counts ? `reward row: TP ${counts.tp} · FP ${counts.fp} · FN ${counts.fn} · TN ${counts.tn}` : '');
}

function renderClasses(graph) {
  setText('classes-sub', graph.abstraction === 'minimal'
    ? "minimal task abstraction: the reward's parents and their ancestors (Theorem 4.1)"
    : 'from the learned graph (Definitions 3.1–3.3)');
  $('classes').replaceChildren(...graph.classes.map((cls) => {
    const chips = cls.factors.map((f) => {
      const chip = html('span', { className: 'chip', text: f.name, data: { index: f.index } });
      chip.addEventListener('mouseenter', () => graphViews.highlightFactor(f.index));
      chip.addEventListener('mouseleave', () => graphViews.highlightFactor(null));
      return chip;
    });
    return html('div', { className: `class-block class-${cls.key}`, data: { class: cls.key } }, [
      html('div', { className: 'class-head' }, [
        html('span', { className: 'class-dot' }), html('span', { text: cls.label }),
        html('span', { className: 'count', text: `${cls.factors.length}` }),
      ]),
      html('div', { className: 'chips' }, chips.length ? chips : [html('span', { className: 'none', text: 'none' })]),
    ]);
  }));
}

function renderServices() {
  const elapsed = (Date.now() - view.servicesAt) / 1000;
  const items = view.services.map((s) => {
    const shown = SERVICE_VALUES.filter((k) => k in s.values).slice(0, 2)
      .map((k) => `${k.replace(/_/g, ' ')} ${fmt.compact(s.values[k])}`).join(' · ');
    const age = s.age_s + elapsed;
    return html('li', { className: s.stale || age > 10 ? 'stale' : '' }, [
      html('span', { className: 'svc-dot' }),
      html('div', {}, [html('div', { className: 'svc-name', text: `${s.service}/${s.instance}` }),
        html('div', { className: 'svc-values', text: shown })]),
      html('span', { className: 'svc-age', text: fmt.age(age) }),
    ]);
  });
  $('services').replaceChildren(...(items.length ? items : [html('li', { className: 'empty', text: 'no beats yet' })]));
  renderLatentActions();
}

// FLAM: the dynamics-learner's live scores (live_* values of its beat): PSNR, DCI, each slot's KL; with
// --label-latent-actions, the factor-extractor's labels of the workers' own steps (stream_slot*_kl).
function renderLatentActions() {
  const learner = view.services.find((s) => s.service === 'dynamics-learner' && 'live_psnr' in s.values);
  $('latent-panel').hidden = !learner;
  if (!learner) return;
  const v = learner.values;
  const labeller = view.services.find((s) => s.service === 'factor-extractor' && 'labelled_steps' in s.values);
  const stream = labeller ? labeller.values : {};
  setText('latent-psnr', Number.isFinite(v.live_psnr) ? v.live_psnr.toFixed(2) : '–');
  setText('latent-dci-d', fmt.ratio(v.live_dci_d));
  setText('latent-dci-c', fmt.ratio(v.live_dci_c));
  setText('latent-dci-i', fmt.ratio(v.live_dci_i));
  setText('latent-sub', `FLAM: the learner's model at update ${fmt.int(v.updates)} on fixed unseen videos`);
  $('latent-labels').hidden = !labeller;
  if (labeller) {
    setText('latent-labels', `The workers' stream: ${fmt.int(stream.labelled_steps)} steps labelled with weights `
      + `v${fmt.int(stream.labels_weights_version)} (${fmt.int(stream.unlabelled_steps)} before trained weights)`);
  }
  const slots = Object.keys(v).filter((k) => /^live_slot\d+_kl$/.test(k))
    .sort((a, b) => parseInt(a.slice(9), 10) - parseInt(b.slice(9), 10));
  const most = Math.max(1e-9, ...slots.map((k) => v[k]));
  const rows = slots.map((k) => {
    const slot = k.slice(9, -3);
    const bar = html('span', { className: 'latent-bar' });
    bar.style.width = `${(100 * Math.max(v[k], 0) / most).toFixed(1)}%`;
    const cells = [html('td', { text: `slot ${slot}` }), html('td', { text: fmt.cmi(v[k]) }),
      html('td', { className: 'bar-cell' }, [bar])];
    if (labeller) {
      const kl = stream[`stream_slot${slot}_kl`];
      cells.push(html('td', { className: 'stream-kl', text: Number.isFinite(kl) ? fmt.cmi(kl) : '–' }));
    }
    return html('tr', { data: { slot } }, cells);
  });
  const head = [html('th', { text: 'slot' }), html('th', { text: 'KL (nats)' }), html('th', { text: '' })];
  if (labeller) head.push(html('th', { text: "KL, workers' stream (newest labels)" }));
  $('latent-slots').replaceChildren(html('tr', {}, head), ...rows);
  drawLatentCharts();
}

// The live scores each time the learner computed them (the server keeps the run's curve).
function drawLatentCharts() {
  if ($('latent-panel').hidden) return;
  renderChart($('latent-psnr-chart'), view.liveHistory, LATENT_PSNR_SERIES, { unit: 'dB' });
  renderChartLegend($('latent-psnr-legend'), view.liveHistory, LATENT_PSNR_SERIES);
  renderChart($('latent-dci-chart'), view.liveHistory, LATENT_DCI_SERIES);
  renderChartLegend($('latent-dci-legend'), view.liveHistory, LATENT_DCI_SERIES);
}

// Local graphs but no global graph (a method without one): hide the global scores and heat maps.
function setLocalOnly(on) {
  $('kpis').hidden = on;
  $('board').classList.toggle('local-only', on);
}

function showKind(kind) {
  setText('kind', kind || '');
  $('kind').hidden = !kind;
}

function renderGraph(graph) {
  const previous = view.graph;
  view.graph = graph;
  setLocalOnly(false); // before drawing: hidden heat maps have no width to size to
  $('waiting').hidden = true;
  showKind(graph.kind);
  setText('learned-sub', `CMI per edge, nats · ${fmt.int(graph.num_heldout)} held-out transitions`);
  $('board').classList.toggle('large', graph.cause_names.length > LARGE_GRAPH_COLUMNS);
  graphViews.render(graph);
  renderKpis(graph, previous);
  renderClasses(graph);
  document.body.dataset.weightsVersion = String(graph.weights_version);
}

function renderWaiting(local = null) {
  view.graph = null;
  setLocalOnly(Boolean(local));
  showKind(local && local.kind);
  $('waiting').hidden = Boolean(local);
  $('waiting').textContent = view.run ? `Waiting for the first graph report of run “${view.run}”…`
    : 'Waiting for a run to report on the bus…';
}

function renderAge() {
  if (view.graph) setText('last-update-age', fmt.age(serverNow() - view.graph.received_at));
  renderServices();
}

// ------------------------------------------------------------------ event stream

function setStatus(state) {
  $('status').dataset.state = state === 'reconnecting' ? 'connecting' : state;
  setText('status-text', STATUS_TEXT[state]);
}

function onRuns(runs) {
  const select = $('run');
  const known = runs.some((r) => r.run === view.run);
  const options = runs.map((r) => {
    const local = r.has_local ? ` — local ROC AUC ${fmt.ratio(r.local_roc_auc)} · v${r.local_weights_version}` : null;
    const note = r.has_graph ? ` — F1 ${fmt.ratio(r.f1)} · v${r.weights_version}` : local || ' — no graph yet';
    const option = html('option', { text: `${r.run}${note}` });
    option.value = r.run;
    return option;
  });
  if (view.run && !known) {
    const option = html('option', { text: `${view.run} — not seen yet` });
    option.value = view.run;
    options.unshift(option);
  }
  select.replaceChildren(...options);
  if (view.run) select.value = view.run;
  const best = runs[0];
  const shown = view.graph || view.local;
  if (!view.userPicked && best && best.run !== view.run
      && (view.run == null || (!shown && (best.has_graph || best.has_local)))) {
    selectRun(best.run, false);
  }
}

function onSnapshot(snapshot) {
  if (snapshot.run !== view.run) return;
  view.clockOffsetMs = snapshot.server_time * 1000 - Date.now();
  view.history = snapshot.history;
  onServices(snapshot);
  view.local = snapshot.local_graph;
  if (snapshot.graph) renderGraph(snapshot.graph);
  else renderWaiting(view.local);
  localPanel.render(view.local);
  drawChart();
  renderAge();
}

function onServices(message) {
  if (message.run !== view.run) return;
  view.services = message.services;
  view.liveHistory = message.live_history || [];
  view.servicesAt = Date.now();
  renderServices();
  renderCoverage(message.induced_coverage);
}

// SkiLD's induced-graph coverage: one row per dependency, one column per phase (share of episodes).
function renderCoverage(coverage) {
  $('coverage-panel').hidden = !coverage;
  if (!coverage) return;
  const phases = Object.keys(coverage);
  const rows = [...new Set(phases.flatMap((p) => Object.keys(coverage[p].rows)))];
  const head = html('tr', {}, [html('th', { text: 'dependency' }),
    ...phases.map((p) => html('th', { text: `${p} (${fmt.int(coverage[p].episodes)} episodes)` }))]);
  const body = rows.map((row) => html('tr', {}, [html('td', { text: row }),
    ...phases.map((p) => html('td', { text: fmt.ratio(coverage[p].rows[row]) }))]));
  $('coverage-table').replaceChildren(head, ...body);
}

function connect() {
  if (view.source) view.source.close();
  clearTimeout(view.retry);
  const source = new EventSource(view.run ? `/events?run=${encodeURIComponent(view.run)}` : '/events');
  view.source = source;
  setStatus('connecting');
  source.onopen = () => setStatus('live');
  source.onerror = () => {
    if (source !== view.source) return;
    if (source.readyState === EventSource.CLOSED) { // refused (e.g. 503: too many streams): retry later
      setStatus('offline');
      view.retry = setTimeout(connect, 5000);
    } else {
      setStatus('reconnecting');
    }
  };
  const on = (name, handler) => source.addEventListener(name, (e) => handler(JSON.parse(e.data)));
  on('runs', onRuns);
  on('snapshot', onSnapshot);
  on('services', onServices);
}

function selectRun(run, byUser) {
  view.run = run;
  view.userPicked = view.userPicked || byUser;
  view.history = [];
  view.liveHistory = [];
  view.services = [];
  view.local = null;
  localPanel.render(null);
  if (byUser) window.history.replaceState(null, '', `?run=${encodeURIComponent(run)}`);
  renderWaiting();
  drawChart();
  renderServices();
  connect();
}

$('run').addEventListener('change', (e) => selectRun(e.target.value, true));
window.addEventListener('resize', debounce(() => {
  if (view.graph) graphViews.render(view.graph);
  drawChart();
  drawLatentCharts();
  localPanel.resize();
}, 150));
renderWaiting();
drawChart();
renderServices();
setInterval(renderAge, 1000);
connect();
