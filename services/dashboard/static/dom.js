// DOM helpers shared by the page's modules: element builders, number formats, the one tooltip.

const SVG_NS = 'http://www.w3.org/2000/svg';

const OUTCOME_NAMES = {
  tp: 'true positive', fp: 'false positive', fn: 'false negative', tn: 'true negative',
  self: 'self-edge (assumed, not scored)',
};

export const $ = (id) => document.getElementById(id);

export function html(tag, props = {}, children = []) {
  const node = document.createElement(tag);
  if (props.className) node.className = props.className;
  if (props.text != null) node.textContent = props.text;
  Object.entries(props.data || {}).forEach(([k, v]) => { node.dataset[k] = v; });
  children.forEach((child) => child && node.appendChild(child));
  return node;
}

export function svg(tag, attrs = {}, parent = null, text = null) {
  const node = document.createElementNS(SVG_NS, tag);
  Object.entries(attrs).forEach(([k, v]) => node.setAttribute(k, v));
  if (text != null) node.textContent = text;
  if (parent) parent.appendChild(node);
  return node;
}

export const fmt = {
  ratio: (v) => (v == null || !Number.isFinite(v) ? '–' : v.toFixed(3)),
  int: (v) => (v == null ? '–' : Math.round(v).toLocaleString('en-US')),
  compact: (v) => {
    const a = Math.abs(v);
    if (a >= 1e6) return `${(v / 1e6).toFixed(a >= 1e7 ? 0 : 1)}M`;
    if (a >= 1e3) return `${(v / 1e3).toFixed(a >= 1e4 ? 0 : 1)}k`;
    return String(Math.round(v));
  },
  cmi: (v) => {
    const a = Math.abs(v);
    if (a === 0) return '0';
    return a < 1e-3 || a >= 1e3 ? v.toExponential(2) : v.toPrecision(3);
  },
  clock: (t) => new Date(t * 1000).toLocaleTimeString('en-GB', { hour12: false }),
  age: (s) => {
    if (s < 1.5) return 'just now';
    if (s < 90) return `${Math.round(s)} s ago`;
    if (s < 5400) return `${Math.round(s / 60)} min ago`;
    return `${(s / 3600).toFixed(1)} h ago`;
  },
};

export function debounce(fn, ms) {
  let timer = null;
  return () => { clearTimeout(timer); timer = setTimeout(fn, ms); };
}

export const tooltip = {
  show(title, rows, badge, x, y) {
    const el = $('tooltip');
    const lines = rows.map(([label, value]) => html('div', { className: 'tt-row' },
      [html('span', { text: label }), html('b', { text: value })]));
    const tag = badge ? html('span', { className: `tt-badge outcome-${badge}`, text: OUTCOME_NAMES[badge] }) : null;
    el.replaceChildren(html('div', { className: 'tt-title', text: title }), ...lines, ...(tag ? [tag] : []));
    el.hidden = false;
    this.move(x, y);
  },
  move(x, y) {
    const el = $('tooltip');
    const box = el.getBoundingClientRect();
    const left = x + 16 + box.width > window.innerWidth - 8 ? x - box.width - 16 : x + 16;
    const top = y + 16 + box.height > window.innerHeight - 8 ? y - box.height - 16 : y + 16;
    el.style.left = `${Math.max(4, left)}px`;
    el.style.top = `${Math.max(4, top)}px`;
  },
  hide() { $('tooltip').hidden = true; },
};
