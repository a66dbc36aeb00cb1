// The three heat maps (learned CMI, ground truth, comparison) with linked hover, and the CMI colour bar.
// Where the report has standard errors, hover shows each entry's 95% interval and the learned map
// outlines (dashed) the entries the held-out data cannot yet decide, the reward row's (CBM) too.
// The local-graph panel reuses them for one example transition: its graph-like object carries
// `labels` (score name and unit, what a found edge is called) where they differ from the global graph's.

import { $, fmt, html, svg, tooltip } from './dom.js';

const BLUES = [[247, 251, 255], [198, 219, 239], [107, 174, 214], [33, 113, 181], [8, 48, 107]];
const GLOBAL_IDS = { learned: 'heatmap-learned', truth: 'heatmap-truth', compare: 'heatmap-compare' };
const GLOBAL_LABELS = { score: 'CMI', unit: 'nats', learned: 'learned' };

const labelsOf = (graph) => ({ ...GLOBAL_LABELS, ...graph.labels });

// A graph with a reward graph (CBM) has one more effect row under the factors: the reward, its cells
// scored against the true reward parents with their own threshold.
const rowNames = (graph) => (graph.reward ? [...graph.factor_names, graph.reward.row_name] : graph.factor_names);
const cellRows = (graph) => (graph.reward ? [...graph.cells, graph.reward.cells] : graph.cells);
const isRewardRow = (graph, i) => Boolean(graph.reward) && i === graph.factor_names.length;

// CMI on a log scale: a decade below the threshold is the lightest blue.
function cmiDomain(graph) {
  const lo = Math.max(graph.threshold, 1e-4) / 10;
  return [lo, Math.max(graph.cmi_max, graph.threshold * 10, lo * 100)];
}

function cmiPosition(value, [lo, hi]) {
  const t = (Math.log(Math.max(value, lo)) - Math.log(lo)) / (Math.log(hi) - Math.log(lo));
  return Math.min(1, Math.max(0, t));
}

function blue(t) {
  const x = t * (BLUES.length - 1);
  const i = Math.min(Math.floor(x), BLUES.length - 2);
  const f = x - i;
  const rgb = BLUES[i].map((c, k) => Math.round(c + (BLUES[i + 1][k] - c) * f));
  return { css: `rgb(${rgb.join(',')})`, dark: 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2] < 140 };
}

class Heatmap {
  constructor(id, mode, owner) {
    this.svg = $(id);
    this.mode = mode;
    this.key = '';
    this.svg.addEventListener('mousemove', (e) => {
      const cell = e.target.closest('.cell');
      if (cell) owner.hover(Number(cell.dataset.i), Number(cell.dataset.j), e);
      else owner.clear();
    });
    this.svg.addEventListener('mouseleave', () => owner.clear());
  }

  render(graph) {
    const width = this.svg.parentElement.clientWidth;
    const key = `${width}|${rowNames(graph).join(',')}|${graph.cause_names.length}`;
    if (key !== this.key) this.build(graph, width);
    this.key = key;
    this.paint(graph);
  }

  build(graph, width) {
    this.svg.replaceChildren();
    const rows = rowNames(graph);
    const cols = graph.cause_names;
    const font = cols.length > 20 ? 10 : 11;
    this.svg.style.setProperty('--label-size', `${font}px`);
    const rowLabels = rows.map((name) => svg('text', { 'text-anchor': 'end', 'dominant-baseline': 'central' },
      this.svg, name));
    const colLabels = cols.map((name) => svg('text', { 'dominant-baseline': 'central' }, this.svg, name));
    const longest = (labels) => Math.max(...labels.map((t) => t.getComputedTextLength()));
    const x0 = Math.ceil(longest(rowLabels)) + 8;
    const y0 = Math.ceil(longest(colLabels)) + 8;
    const cell = Math.max(8, Math.min(36, Math.floor((width - x0 - 2) / cols.length)));
    this.svg.setAttribute('width', x0 + cell * cols.length + 2);
    this.svg.setAttribute('height', y0 + cell * rows.length + 2);
    rowLabels.forEach((t, i) => { t.setAttribute('x', x0 - 6); t.setAttribute('y', y0 + (i + 0.5) * cell); });
    if (graph.reward) {
      rowLabels[rows.length - 1].classList.add('reward-label');
      svg('line', { class: 'reward-separator', x1: x0, x2: x0 + cell * cols.length,
        y1: y0 + (rows.length - 1) * cell, y2: y0 + (rows.length - 1) * cell }, this.svg);
    }
    colLabels.forEach((t, j) => {
      t.setAttribute('transform', `translate(${x0 + (j + 0.5) * cell},${y0 - 6}) rotate(-90)`);
    });
    const group = svg('g', {}, this.svg);
    this.cells = rows.map((_, i) => cols.map((__, j) => svg('rect', {
      class: 'cell', x: x0 + j * cell + 0.5, y: y0 + i * cell + 0.5, width: cell - 1, height: cell - 1,
      rx: Math.min(2, cell / 6), 'data-i': i, 'data-j': j,
    }, group)));
    if (this.mode === 'learned') {
      this.dots = rows.map((_, i) => cols.map((__, j) => svg('circle', {
        class: 'cell-dot', cx: x0 + (j + 0.5) * cell, cy: y0 + (i + 0.5) * cell, r: Math.max(1.5, cell * 0.14),
      }, group)));
      this.undecided = rows.map((_, i) => cols.map((__, j) => svg('rect', {
        class: 'cell-undecided', x: x0 + j * cell + 1.5, y: y0 + i * cell + 1.5, width: cell - 3, height: cell - 3,
        rx: Math.min(2, cell / 6), visibility: 'hidden',
      }, group)));
    }
    this.rowLabels = rowLabels;
    this.colLabels = colLabels;
    this.hoverBoxes = ['hover-halo', 'hover-box'].map((cls) => svg('rect', {
      class: cls, width: cell, height: cell, rx: 2, visibility: 'hidden',
    }, this.svg));
    this.geometry = { x0, y0, cell };
  }

  paint(graph) {
    const domain = cmiDomain(graph);
    cellRows(graph).forEach((row, i) => row.forEach((c, j) => {
      const rect = this.cells[i][j];
      if (this.mode === 'learned') {
        const colour = blue(cmiPosition(c.cmi, domain));
        rect.setAttribute('fill', colour.css);
        const dot = this.dots[i][j];
        dot.setAttribute('visibility', c.learned ? 'visible' : 'hidden');
        dot.setAttribute('fill', colour.dark ? '#ffffff' : '#0f172a');
        this.undecided[i][j].setAttribute('visibility', c.undecided ? 'visible' : 'hidden');
      } else if (this.mode === 'truth') {
        rect.setAttribute('class', `cell ${c.truth == null ? 'outcome-none' : c.truth ? 'truth-edge' : 'truth-none'}`);
      } else {
        rect.setAttribute('class', `cell outcome-${c.outcome || 'none'}`);
      }
    }));
  }

  highlight(i, j) {
    if (!this.geometry) return;
    const { x0, y0, cell } = this.geometry;
    this.rowLabels.forEach((t, k) => t.classList.toggle('active', k === i));
    this.colLabels.forEach((t, k) => t.classList.toggle('active', k === j));
    this.hoverBoxes.forEach((box) => {
      if (i == null || j == null) {
        box.setAttribute('visibility', 'hidden');
        return;
      }
      box.setAttribute('x', x0 + j * cell);
      box.setAttribute('y', y0 + i * cell);
      box.setAttribute('visibility', 'visible');
    });
  }
}

/** The three heat maps of one graph; hovering a cell highlights it, its row and column in all three.
 *  `ids` names the three SVG elements by mode (learned, truth, compare). */
export class GraphViews {
  constructor(legend, ids = GLOBAL_IDS) {
    this.graph = null;
    this.legend = legend;
    this.maps = Object.entries(ids).map(([mode, id]) => new Heatmap(id, mode, this));
  }

  render(graph) {
    this.graph = graph;
    this.maps.forEach((m) => m.render(graph));
    renderColorbar(graph, this.legend);
  }

  hover(i, j, event) {
    const graph = this.graph;
    if (!graph) return;
    const c = cellRows(graph)[i][j];
    const labels = labelsOf(graph);
    const reward = isRewardRow(graph, i);
    this.maps.forEach((m) => m.highlight(i, j));
    const yesNo = (v) => (v == null ? 'unknown' : v ? 'edge' : 'no edge');
    const unit = labels.unit ? ` ${labels.unit}` : '';
    const effect = rowNames(graph)[i];
    const tested = c.stderr == null ? [] : [
      ['95% interval', `${fmt.cmi(c.cmi - 1.96 * c.stderr)} – ${fmt.cmi(c.cmi + 1.96 * c.stderr)}${unit}`],
      ['decided', c.undecided ? 'no: the interval crosses the boundary' : 'yes'],
    ];
    const nulled = c.null == null || reward ? [] : [['permuted null', `${fmt.cmi(c.null)}${unit}`]];
    tooltip.show(`${graph.cause_names[j]} → ${effect}`, [
      ['cause (t)', graph.cause_names[j]],
      reward ? ['effect', 'reward r_t (causal reward model)'] : ['effect (t+1)', effect],
      [reward ? 'reward CMI' : labels.score, `${fmt.cmi(c.cmi)}${unit}`],
      ...tested,
      ...nulled,
      graph.edge_rule === 'fdr' ? ['edge rule', `${testedAgainst(graph, reward, 'CMI')} at FDR ${graph.fdr}`]
        : ['threshold ε', `${fmt.cmi(c.threshold ?? graph.threshold)}${unit}`],
      [labels.learned, yesNo(c.learned)],
      ['truth', yesNo(c.truth)],
    ], c.outcome, event.clientX, event.clientY);
  }

  clear() {
    this.maps.forEach((m) => m.highlight(null, null));
    tooltip.hide();
  }

  /** Emphasise one factor's row and column labels (hovering its abstraction chip); null clears. */
  highlightFactor(index) {
    this.maps.forEach((m) => {
      if (!m.rowLabels) return;
      m.rowLabels.forEach((t, k) => t.classList.toggle('active', k === index));
      m.colLabels.forEach((t, k) => t.classList.toggle('active', k === index));
    });
  }
}

// What the fdr rule tests a score against: min_cmi, or (dynamics rows under an estimated bias) the
// permuted-input null; the reward row (CBM) has no null and is always tested against the configured
// min_cmi (reward_min_cmi: under bias split or mirror min_cmi is the dynamics level). Under
// bias mirror a dynamics entry is an edge when its score reaches the level (min_cmi in the report)
// that the table's negative side puts at the requested rate: no test above the level.
const NULLS = { permuted: 'its permuted null', pooled: "its output's largest null", global: "the graph's largest null" };
function testedAgainst(graph, reward, score) {
  if (!reward && graph.bias === 'mirror') return `${score} ≥ ${fmt.cmi(graph.min_cmi)} (the mirror level)`;
  const null_ = !reward && NULLS[graph.bias];
  return null_ ? `${score} > ${null_}` : `${score} > ${fmt.cmi(reward ? graph.reward_min_cmi : graph.min_cmi)}`;
}

function renderColorbar(graph, container) {
  const domain = cmiDomain(graph);
  const labels = labelsOf(graph);
  const width = 220;
  const bar = svg('svg', { class: 'colorbar', width: width + 8, height: 44 });
  const gradientId = `${container.id}-gradient`; // one per colour bar: a hidden panel's would not paint
  const gradient = svg('linearGradient', { id: gradientId }, svg('defs', {}, bar));
  BLUES.forEach((_, k) => svg('stop', {
    offset: `${(100 * k) / (BLUES.length - 1)}%`, 'stop-color': blue(k / (BLUES.length - 1)).css,
  }, gradient));
  svg('rect', { x: 4, y: 14, width, height: 10, rx: 2, fill: `url(#${gradientId})`, stroke: '#e2e7ee' }, bar);
  const at = (value) => 4 + cmiPosition(value, domain) * width;
  svg('text', { x: 4, y: 38 }, bar, `≤ ${fmt.cmi(domain[0])}`);
  svg('text', { x: 4 + width, y: 38, 'text-anchor': 'end' }, bar, `${fmt.cmi(domain[1])} ${labels.unit}`.trim());
  svg('line', { class: 'threshold', x1: at(graph.threshold), x2: at(graph.threshold), y1: 11, y2: 27 }, bar);
  svg('text', { x: at(graph.threshold), y: 8, 'text-anchor': 'middle' }, bar, `ε = ${fmt.cmi(graph.threshold)}`);
  const dot = html('span', { className: 'key' }, [svg('svg', { width: 12, height: 12 })]);
  svg('circle', { cx: 6, cy: 6, r: 3, fill: '#0f172a' }, dot.firstChild);
  const rule = graph.edge_rule === 'fdr'
    ? `${graph.bias === 'mirror' ? '' : 'test of '}${testedAgainst(graph, false, labels.score)} at FDR ${graph.fdr}`
    : `${labels.score} ≥ ε`;
  const rewardRule = graph.reward && graph.edge_rule === 'fdr' && NULLS[graph.bias]
    ? `; reward row: ${testedAgainst(graph, true, labels.score)}` : '';
  dot.append(`${labels.learned} edge (${rule}${rewardRule})`);
  const keys = [bar, dot];
  const inReward = graph.reward ? graph.reward.undecided : null;
  if (graph.undecided != null || inReward != null) {
    const box = html('span', { className: 'key' }, [svg('svg', { width: 12, height: 12 })]);
    svg('rect', { class: 'cell-undecided', x: 1, y: 1, width: 10, height: 10, rx: 2 }, box.firstChild);
    const total = (graph.undecided ?? 0) + (inReward ?? 0);
    box.append(`undecided (${total}${inReward ? `, ${inReward} in the reward row` : ''})`);
    keys.push(box);
  }
  container.replaceChildren(...keys);
}
