// Learning curves: scores against env steps, one SVG line per score, values on hover. SERIES are the
// global graph's; a caller passes its own (the local-graph panel's LOCAL_SERIES, the latent-action
// panel's LATENT_DCI_SERIES and LATENT_PSNR_SERIES). Scores lie in [0, 1]; `{ unit }` scales the
// y axis to the data instead (PSNR in dB).

import { fmt, html, svg, tooltip } from './dom.js';

const SERIES = [
  { key: 'f1', label: 'F1' },
  { key: 'best_threshold_f1', label: 'best-threshold F1', dashed: true },
  { key: 'accuracy', label: 'accuracy' },
  { key: 'roc_auc', label: 'ROC AUC' },
  { key: 'identifiable_f1', label: 'identifiable F1', dashed: true, optional: 'differs' },
  { key: 'with_self_best_threshold_f1', label: 'best F1, Table 3.1 scoring', dotted: true, optional: 'present' },
  { key: 'reward_f1', label: "reward parents' F1", optional: 'present' },
  { key: 'abstraction_accuracy', label: 'abstraction accuracy', dashed: true, optional: 'present' },
];

export const LOCAL_SERIES = [
  { key: 'roc_auc', label: 'ROC AUC' },
  { key: 'pr_auc', label: 'PR AUC' },
  { key: 'best_f1', label: 'best F1', dashed: true },
  { key: 'f1', label: 'F1 at ε', optional: 'present' },
  { key: 'positive_rate', label: 'positive rate (chance PR AUC)', dotted: true, optional: 'present' },
];

export const LATENT_DCI_SERIES = [
  { key: 'dci_d', label: 'DCI D' },
  { key: 'dci_c', label: 'DCI C', dashed: true },
  { key: 'dci_i', label: 'DCI I', dotted: true },
];

export const LATENT_PSNR_SERIES = [{ key: 'psnr', label: 'prediction PSNR (dB)' }];

// Optional series are drawn only where they tell something new: identifiable F1 where it differs
// from F1 (environments with constant factors, i.e. manipulation); the Table 3.1-scored F1 (every
// entry, self-edges counted found) where the evaluator reports it (older runs do not); the reward
// parents' F1 and the minimal abstraction's accuracy where the method has a reward graph (CBM).
function activeSeries(points, all) {
  const shows = { differs: (p, key) => p[key] != null && p[key] !== p.f1, present: (p, key) => p[key] != null };
  return all.filter(({ key, optional }) => !optional || points.some((p) => shows[optional](p, key)));
}

const lineClass = ({ key, dashed, dotted }) => `series-${key}${dashed ? ' dashed' : ''}${dotted ? ' dotted' : ''}`;

function niceTicks(lo, hi, count) {
  const raw = (hi - lo) / Math.max(count, 1);
  const magnitude = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 2.5, 5, 10].map((m) => m * magnitude).find((s) => s >= raw) || raw;
  const ticks = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) ticks.push(v);
  return ticks;
}

// The y range: [0, 1] for scores; with a unit, nice bounds around the shown series' values.
function yDomain(points, series, unit) {
  if (!unit) return { lo: 0, hi: 1, ticks: [0, 0.25, 0.5, 0.75, 1], label: (v) => v.toFixed(2), value: fmt.ratio };
  const values = points.flatMap((p) => series.map(({ key }) => p[key])).filter(Number.isFinite);
  let lo = values.length ? Math.min(...values) : 0;
  let hi = values.length ? Math.max(...values) : 1;
  if (hi - lo < 1e-9) { lo -= 1; hi += 1; }
  const nice = niceTicks(lo, hi, 4);
  const step = nice.length > 1 ? nice[1] - nice[0] : hi - lo;
  lo = Math.floor(lo / step) * step;
  hi = Math.ceil(hi / step) * step;
  const ticks = [];
  for (let v = lo; v <= hi + step * 1e-9; v += step) ticks.push(v);
  const digits = step >= 1 ? 0 : 1;
  return { lo, hi, ticks, label: (v) => v.toFixed(digits), value: (v) => (Number.isFinite(v) ? `${v.toFixed(2)} ${unit}` : '–') };
}

export function renderChart(chart, points, all = SERIES, { unit = '' } = {}) {
  chart.replaceChildren();
  const width = chart.parentElement.clientWidth;
  const height = 250;
  const m = { l: 40, r: 16, t: 10, b: 34 };
  chart.setAttribute('width', width);
  chart.setAttribute('height', height);
  const X0 = 0;
  const X1 = Math.max(1, ...points.map((p) => p.env_steps));
  const x = (v) => m.l + ((v - X0) / (X1 - X0)) * (width - m.l - m.r);
  const series = activeSeries(points, all);
  const domain = yDomain(points, series, unit);
  const y = (v) => m.t + (1 - (v - domain.lo) / (domain.hi - domain.lo)) * (height - m.t - m.b);
  const axis = svg('g', { class: 'axis' }, chart);
  domain.ticks.forEach((v) => {
    svg('line', { class: 'grid', x1: m.l, x2: width - m.r, y1: y(v), y2: y(v) }, axis);
    svg('text', { x: m.l - 8, y: y(v), 'text-anchor': 'end', 'dominant-baseline': 'central' }, axis, domain.label(v));
  });
  niceTicks(X0, X1, Math.max(2, Math.floor(width / 110))).forEach((v) => {
    svg('text', { x: x(v), y: height - m.b + 16, 'text-anchor': 'middle' }, axis, fmt.compact(v));
  });
  svg('text', { x: width - m.r, y: height - 2, 'text-anchor': 'end' }, axis, 'env steps');
  if (!points.length) {
    svg('text', { class: 'empty-note', x: width / 2, y: height / 2, 'text-anchor': 'middle' }, chart, 'no scores yet');
    return;
  }
  series.forEach((line) => {
    const { key } = line;
    let d = '';
    let pen = 'M';
    let last = null;
    points.forEach((p) => {
      if (p[key] == null) { pen = 'M'; return; }
      d += `${pen}${x(p.env_steps).toFixed(1)},${y(p[key]).toFixed(1)}`;
      pen = 'L';
      last = p;
    });
    if (!last) return;
    svg('path', { class: `series ${lineClass(line)}`, d }, chart);
    svg('circle', { class: `end-dot series-${key}`, cx: x(last.env_steps), cy: y(last[key]), r: 3.5 }, chart);
  });
  const crosshair = svg('line', { class: 'crosshair', y1: m.t, y2: height - m.b, visibility: 'hidden' }, chart);
  const overlay = svg('rect', {
    class: 'overlay', x: m.l, y: m.t, width: width - m.l - m.r, height: height - m.t - m.b,
  }, chart);
  overlay.addEventListener('mousemove', (e) => {
    const steps = X0 + ((e.offsetX - m.l) / (width - m.l - m.r)) * (X1 - X0);
    const p = points.reduce((best, q) => (Math.abs(q.env_steps - steps) < Math.abs(best.env_steps - steps) ? q : best));
    crosshair.setAttribute('x1', x(p.env_steps));
    crosshair.setAttribute('x2', x(p.env_steps));
    crosshair.setAttribute('visibility', 'visible');
    tooltip.show(`${fmt.int(p.env_steps)} env steps`, [
      ...series.map(({ key, label }) => [label, domain.value(p[key])]),
      ['updates', fmt.int(p.updates)],
    ], null, e.clientX, e.clientY);
  });
  overlay.addEventListener('mouseleave', () => { crosshair.setAttribute('visibility', 'hidden'); tooltip.hide(); });
}

export function renderChartLegend(container, points = [], all = SERIES) {
  container.replaceChildren(...activeSeries(points, all).map((line) => html('span', { className: 'key' }, [
    html('span', { className: `swatch-line ${lineClass(line)}` }), document.createTextNode(line.label),
  ])));
}
