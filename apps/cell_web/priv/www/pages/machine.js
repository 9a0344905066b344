// The Machine page: a picture of the cell drawn from its spec (GET /api/layout): zones
// as columns in the order products flow, lanes as rows, a robot shared by the lanes
// across them, the handshake links as arrows with their phase. Each task is drawn in
// its IPC-2541 state colour with its product's serial; the beacon and this shift's
// counters beside it. Everything live over the websocket: task, link, io, counters.
'use strict';
(() => {
  const SVG = 'http://www.w3.org/2000/svg';
  // Sizes in the picture's own units; the picture is scaled to the page's width, so a
// line of five zones stays readable on a 1024-pixel screen.
const COL = 150, GAP = 64, ROW = 150, TOP = 40, LEFT = 64;
  const LAMPS = { beacon_red: 'red', beacon_yellow: 'yellow', beacon_green: 'green', beacon_blue: 'blue' };
  let panel, root, svg, layout = null;
  const tasks = new Map();      // id -> task as the websocket sends it
  const links = new Map();      // id -> {phase, serial}
  const lamps = new Map();      // "group.point" -> lamp of the layout's beacon
  let forced = new Set();

  function el(name, attrs, text) {
    const e = document.createElementNS(SVG, name);
    for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
    if (text !== undefined) e.textContent = text;
    return e;
  }
  function html(tag, cls, text) {
    const e = document.createElement(tag);
    if (cls) e.className = cls;
    if (text !== undefined) e.textContent = text;
    return e;
  }
  const stateOf = (s) => { const p = (s || 'OFF').split('-'); return p[p.length - 1]; };
  const label = (s) => (s || 'OFF').replace('READY-', '');

  function mount(section, p) {
    panel = p;
    root = section;
    section.classList.add('machine');
    const side = html('div', 'machine-side');
    const beacon = html('div', 'beacon');
    beacon.dataset.testid = 'beacon';
    const counters = html('dl', 'counters');
    counters.dataset.testid = 'counters';
    side.append(html('h2', '', 'Beacon'), beacon, html('h2', '', 'This shift'), counters);
    svg = el('svg', { class: 'machine-svg', 'data-testid': 'machine-svg', role: 'img' });
    const pic = html('div', 'machine-picture');
    pic.append(svg);
    section.append(pic, side);
    panel.on('snapshot', (m) => { tasks.clear(); for (const t of m.tasks) tasks.set(t.id, t);
                                  forced = keys(m.forces || []); load(); });
    panel.on('task', (m) => { tasks.set(m.task.id, m.task); paintTask(m.task.id); });
    panel.on('link', (m) => { links.set(m.link.link, m.link); paintLink(m.link.link); });
    panel.on('counters', (m) => paintCounters(m.counters));
    panel.on('forces', (m) => { forced = keys(m.forces); paintBeacon(); });
    panel.on('io', (m) => {
      let any = false;
      for (const pt of m.points) {
        const lamp = lamps.get(`${pt.group}.${pt.point}`);
        if (lamp) { lamp.value = pt.value; any = true; }
      }
      if (any) paintBeacon();
    });
  }

  const keys = (forces) => new Set(forces.map((f) => `${f.group}.${f.point}`));

  // Read once at each snapshot (connect, resync): what the websocket does not carry.
  async function load() {
    const got = await window.cellUi.attempt(panel, () => panel.api('GET', '/api/layout'));
    if (!got) return;
    layout = got;
    links.clear();
    for (const l of layout.links) links.set(l.id, { link: l.id, phase: l.phase, serial: l.serial });
    lamps.clear();
    for (const b of layout.beacon) lamps.set(`${b.group}.${b.point}`, { ...b });
    draw();
    paintBeacon();
    paintCounters(layout.counters);
  }

  function box(t) {
    const w = COL / t.slots;
    return { x: LEFT + t.column * (COL + GAP) + t.slot * w, y: TOP + t.row * ROW,
             w: w - 8, h: t.rows * ROW - 16 };
  }

  function draw() {
    svg.replaceChildren();
    const cols = Math.max(layout.zones.length, 1);
    const width = LEFT + cols * (COL + GAP);
    const height = TOP + layout.rows * ROW + 10;
    svg.setAttribute('viewBox', `0 0 ${width} ${height}`);
    const defs = el('defs');
    const marker = el('marker', { id: 'arrow', viewBox: '0 0 10 10', refX: '9', refY: '5',
                                  markerWidth: '16', markerHeight: '16', markerUnits: 'userSpaceOnUse',
                                  orient: 'auto-start-reverse' });
    marker.append(el('path', { d: 'M0,0 L10,5 L0,10 z', class: 'arrow-head' }));
    defs.append(marker);
    svg.append(defs);
    for (const z of layout.zones) {
      svg.append(el('text', { x: LEFT + z.column * (COL + GAP) + COL / 2, y: 22, class: 'zone' }, z.name));
    }
    for (const l of layout.lanes.filter((x) => !x.shared)) {
      svg.append(el('text', { x: 8, y: TOP + l.row * ROW + ROW / 2 - 8, class: 'lane' }, l.name));
    }
    const byId = new Map(layout.tasks.map((t) => [t.id, t]));
    const labels = [];
    for (const l of layout.links) {
      const from = byId.get(l.from), to = byId.get(l.to);
      const g = el('g', { class: 'link', 'data-link': l.id });
      let x1, y1, x2, y2;
      if (from) { const b = box(from); x1 = b.x + b.w; y1 = b.y + b.h / 2; }
      if (to) { const b = box(to); x2 = b.x; y2 = b.y + b.h / 2; }
      if (!from) { x1 = x2 - GAP + 6; y1 = y2; }
      if (!to) { x2 = x1 + GAP - 6; y2 = y1; }
      g.append(el('path', { d: `M${x1},${y1} C${(x1 + x2) / 2},${y1} ${(x1 + x2) / 2},${y2} ${x2},${y2}`,
                            'marker-end': 'url(#arrow)' }));
      g.append(el('title', {}, l.id));
      svg.append(g);
      // The phase is written over the tasks (drawn last), with a halo, so a label wider
      // than the gap between two zones stays readable.
      labels.push(el('text', { x: (x1 + x2) / 2, y: (y1 + y2) / 2 + 24, class: 'phase', 'data-link': l.id }),
                  el('text', { x: (x1 + x2) / 2, y: (y1 + y2) / 2 + 42, class: 'phase serial', 'data-link': l.id }));
    }
    for (const t of layout.tasks) {
      const b = box(t);
      const g = el('g', { class: 'node', 'data-node': t.id });
      g.append(el('rect', { x: b.x, y: b.y, width: b.w, height: b.h, rx: 10 }));
      if (t.shared) {
        // A robot shared by the lanes: its arm drawn in the corner.
        g.append(el('path', { class: 'robot', d: `M${b.x + b.w - 30},${b.y + b.h - 10} l8,-22 l14,8 l4,-10` }));
      }
      g.append(el('text', { x: b.x + 8, y: b.y + 24, class: 'name' }, t.id));
      g.append(el('text', { x: b.x + 8, y: b.y + 48, class: 'serial', 'data-testid': 'node-serial' }));
      g.append(el('text', { x: b.x + 8, y: b.y + 72, class: 'state', 'data-testid': 'node-state' }));
      svg.append(g);
      fit(g.querySelector('.name'), b.w - 16);
    }
    svg.append(...labels);
    for (const id of byId.keys()) paintTask(id);
    for (const id of links.keys()) paintLink(id);
  }

  // A text longer than its box is narrowed to fit it, never cut or broken.
  function fit(text, width) {
    text.removeAttribute('textLength');
    if (text.getComputedTextLength() > width) {
      text.setAttribute('textLength', width);
      text.setAttribute('lengthAdjust', 'spacingAndGlyphs');
    }
  }

  function paintTask(id) {
    if (!svg) return;
    const g = svg.querySelector(`g.node[data-node="${CSS.escape(id)}"]`);
    const t = tasks.get(id);
    if (!g || !t) return;
    g.setAttribute('class', `node st-${stateOf(t.state)}${t.running ? '' : ' gone'}`);
    g.dataset.state = t.state;
    g.querySelector('.serial').textContent = t.serial || '—';
    fit(g.querySelector('.serial'), Number(g.querySelector('rect').getAttribute('width')) - 16);
    g.querySelector('.state').textContent = stateOf(t.state);
    g.querySelector('.state').append(el('title', {}, label(t.state)));
  }

  function paintLink(id) {
    if (!svg) return;
    const g = svg.querySelector(`g.link[data-link="${CSS.escape(id)}"]`);
    const l = links.get(id);
    if (!g || !l) return;
    g.dataset.phase = l.phase;
    g.setAttribute('class', `link ph-${l.phase}`);
    const [phase, serial] = svg.querySelectorAll(`text.phase[data-link="${CSS.escape(id)}"]`);
    phase.textContent = l.phase === 'idle' ? '' : l.phase;
    serial.textContent = l.serial || '';
    for (const t of [phase, serial]) t.classList.toggle('moving', !['idle', 'unknown'].includes(l.phase));
  }

  function paintBeacon() {
    if (!root) return;
    const box = root.querySelector('.beacon');
    box.replaceChildren();
    if (lamps.size === 0) { box.append(html('p', 'quiet', 'This cell has no beacon.')); return; }
    for (const [key, l] of lamps) {
      const lamp = html('div', `lamp ${LAMPS[l.lamp] || ''}${l.value === true ? ' on' : ''}` +
                              (forced.has(key) ? ' forced' : ''));
      lamp.dataset.lamp = l.lamp;
      lamp.dataset.on = String(l.value === true);
      lamp.title = forced.has(key) ? `${key} (forced)` : key;
      box.append(lamp);
    }
  }

  function paintCounters(c) {
    if (!root || !c) return;
    const dl = root.querySelector('.counters');
    const cycle = c.cycle_ms == null ? '—' : `${(c.cycle_ms / 1000).toFixed(1)} s`;
    const rows = [['in', c.in], ['out', c.out], ['good', c.good], ['scrapped', c.scrapped],
                  ['cycle time', cycle]];
    dl.replaceChildren(...rows.flatMap(([k, v]) => {
      const dt = html('dt', '', k), dd = html('dd', '', String(v));
      dd.dataset.counter = k;
      return [dt, dd];
    }));
    if (c.period) dl.title = `shift ${c.period}`;
  }

  window.cellPanel.register({ id: 'machine', title: 'Machine', minRole: 'anonymous', mount });
})();
