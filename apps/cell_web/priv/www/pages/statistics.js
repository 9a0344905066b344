// Statistics (everyone): charts drawn as SVG from /api/statistics/charts — time in each
// IPC-2541 state per task (stacked bars), products out per hour, the spread of the
// cycle times, OEE per shift — for a shift, a day or a time range. Each figure is the
// API's number as it is (the bars carry it in data-ms, data-out ...). While the choice
// includes now, a change of a task's state seen on the websocket brings the figures
// again once the statistics have written it (they write once a second).
'use strict';

(() => {
  const { el, svg, time, clock, duration, percent, localInput, fromInput, attempt } = window.cellUi;
  const STATES = ['executing', 'active', 'starved', 'blocked', 'setup', 'down', 'off'];
  const STATE_NAMES = { executing: 'EXECUTING', active: 'ACTIVE', starved: 'STARVED', blocked: 'BLOCKED',
                        setup: 'SETUP', down: 'DOWN', off: 'OFF' };
  const REFRESH_MS = 1500;
  let panel;
  let root;
  let query = 'period=shift';
  let visible = false;
  let pending = null;
  let data = null;

  const live = () => query === 'period=shift' || query === 'period=total';

  async function load() {
    const q = query;
    const answer = await attempt(panel, () => panel.api('GET', `/api/statistics/charts?${q}`));
    if (!answer || q !== query) return;
    data = answer;
    render();
  }

  function choose(q) {
    query = q;
    // A refresh due for the choice before is not this one's.
    clearTimeout(pending);
    pending = null;
    load();
  }

  // -------------------------------------------------------------------------
  // Charts

  const W = 460;
  const H = 220;

  function frame(title, testid, body, note) {
    return el('figure', { class: 'chart', testid },
      el('figcaption', { text: title }), body, note ? el('p', { class: 'chart-note', text: note }) : null);
  }

  // One horizontal bar per task, its states stacked, the width its time.
  function stateBars(tasks) {
    const ids = Object.keys(tasks).sort();
    if (ids.length === 0) return el('p', { class: 'quiet', text: 'No task counted yet.' });
    const total = (t) => STATES.reduce((s, k) => s + (t.time_ms[k] || 0), 0);
    const max = Math.max(1, ...ids.map((id) => total(tasks[id])));
    const rowH = 30;
    const labelW = 110;
    const h = ids.length * (rowH + 8) + 8;
    const rows = ids.map((id, i) => {
      let x = labelW;
      const y = 8 + i * (rowH + 8);
      const segs = STATES.filter((s) => tasks[id].time_ms[s]).map((s) => {
        const ms = tasks[id].time_ms[s];
        const w = ((W - labelW - 10) * ms) / max;
        const r = svg('rect', { x, y, width: Math.max(w, 0.5), height: rowH, class: `seg state-fill-${s}`,
                                'data-task': id, 'data-state': s, 'data-ms': ms },
                      svg('title', {}, `${id} ${STATE_NAMES[s]}: ${duration(ms)}`));
        x += w;
        return r;
      });
      return svg('g', { class: 'bar-row' },
        svg('text', { x: labelW - 6, y: y + rowH / 2, 'text-anchor': 'end', 'dominant-baseline': 'central', class: 'axis' }, id),
        segs);
    });
    return el('div', {},
      svg('svg', { viewBox: `0 0 ${W} ${h}`, class: 'chart-svg', role: 'img', 'aria-label': 'time in each state per task' }, rows),
      el('div', { class: 'legend' }, STATES.map((s) => el('span', { class: 'key' },
        el('i', { class: `swatch state-fill-${s}` }), STATE_NAMES[s]))),
      el('table', { class: 'log state-table', testid: 'state-table' },
        el('thead', {}, el('tr', {}, el('th', { text: 'task' }), STATES.map((s) => el('th', { text: STATE_NAMES[s] })))),
        el('tbody', {}, ids.map((id) => el('tr', { data: { task: id } }, el('td', { text: id }),
          STATES.map((s) => el('td', { data: { state: s }, text: duration(tasks[id].time_ms[s] || 0) })))))));
  }

  // Vertical bars with a label under each and the value over it.
  function columns(items, label, value, attrs, cls) {
    if (items.length === 0) return el('p', { class: 'quiet', text: 'Nothing in this time.' });
    const max = Math.max(1, ...items.map(value));
    const bottom = H - 30;
    const gap = items.length > 60 ? 0 : 4;
    const bw = Math.max(0.5, (W - 30) / items.length - gap);
    const step = Math.ceil(items.length / 12);
    return svg('svg', { viewBox: `0 0 ${W} ${H}`, class: 'chart-svg', role: 'img' },
      svg('line', { x1: 20, y1: bottom, x2: W - 5, y2: bottom, class: 'axis-line' }),
      items.map((it, i) => {
        const v = value(it);
        const x = 24 + i * (bw + gap);
        const h = ((bottom - 20) * v) / max;
        return svg('g', {},
          svg('rect', { x, y: bottom - h, width: bw, height: Math.max(h, 0), class: cls, ...attrs(it) }),
          v > 0 ? svg('text', { x: x + bw / 2, y: bottom - h - 4, 'text-anchor': 'middle', class: 'value' }, String(v)) : null,
          i % step === 0 ? svg('text', { x: x + bw / 2, y: bottom + 16, 'text-anchor': 'middle', class: 'axis' }, label(it)) : null);
      }));
  }

  // Per hour; over two days of hours, per day (the hours added up).
  function hourly(rows) {
    if (rows.length <= 48) {
      return columns(rows, (r) => clock(r.start), (r) => r.out,
                     (r) => ({ 'data-hour': r.start, 'data-out': r.out, 'data-good': r.good }), 'bar-out');
    }
    const days = new Map();
    for (const r of rows) {
      const day = time(r.start).slice(0, 10);
      const d = days.get(day) || { day, out: 0, good: 0 };
      d.out += r.out;
      d.good += r.good;
      days.set(day, d);
    }
    return columns([...days.values()], (d) => d.day.slice(5), (d) => d.out,
                   (d) => ({ 'data-day': d.day, 'data-out': d.out, 'data-good': d.good }), 'bar-out');
  }

  function cycles(c) {
    return columns(c.histogram, (b) => duration(b.from), (b) => b.count,
                   (b) => ({ 'data-from': b.from, 'data-to': b.to, 'data-count': b.count }), 'bar-cycle');
  }

  // OEE per shift: the three factors and their product, as bars of 0 to 100 %.
  function oee(shifts) {
    if (shifts.length === 0) return el('p', { class: 'quiet', text: 'No shift in this time.' });
    const keys = ['availability', 'performance', 'quality', 'oee'];
    const rowH = 16;
    const groupH = keys.length * (rowH + 3) + 16;
    const labelW = 120;
    const h = shifts.length * groupH + 10;
    const scale = (W - labelW - 60);
    return svg('svg', { viewBox: `0 0 ${W} ${h}`, class: 'chart-svg', role: 'img', 'aria-label': 'OEE per shift' },
      shifts.map((s, i) => {
        const y0 = 8 + i * groupH;
        return svg('g', { 'data-period': s.period },
          svg('text', { x: 0, y: y0 + 12, class: 'axis strong' }, s.period),
          keys.map((k, j) => {
            const v = s.oee[k];
            const y = y0 + 16 + j * (rowH + 3);
            return svg('g', {},
              svg('text', { x: labelW - 6, y: y + rowH / 2, 'text-anchor': 'end', 'dominant-baseline': 'central', class: 'axis' }, k),
              svg('rect', { x: labelW, y, width: v === null ? 0 : Math.min(v, 1.2) * scale, height: rowH, class: `oee-${k}`,
                            'data-factor': k, 'data-value': v === null ? '' : v }),
              svg('text', { x: labelW + (v === null ? 0 : Math.min(v, 1.2) * scale) + 6, y: y + rowH / 2,
                            'dominant-baseline': 'central', class: 'value' }, percent(v)));
          }));
      }));
  }

  function figures(sum) {
    const c = sum.cell;
    const fig = (k, v, id) => el('div', { class: 'figure', testid: id ? `figure-${id}` : undefined },
                                  el('div', { class: 'v', text: String(v) }), el('div', { class: 'k', text: k }));
    return el('div', { class: 'figures' },
      fig('in', c.in, 'in'), fig('out', c.out, 'out'), fig('good', c.good, 'good'), fig('failed', c.failed, 'failed'),
      fig('scrapped', c.scrapped, 'scrapped'), fig('OEE', percent(sum.oee.oee), 'oee'));
  }

  function render() {
    const d = data;
    const sel = d.selection;
    const shifts = root.querySelector('.shift-select');
    const keep = shifts.value;
    shifts.replaceChildren(el('option', { value: '', text: 'a shift…' }),
      ...d.periods.filter((p) => p !== 'total').reverse().map((p) => el('option', { value: p, text: p })));
    shifts.value = d.periods.includes(keep) ? keep : '';
    const span = sel.from === null ? 'nothing recorded in this time'
      : `${time(sel.from)} to ${time(sel.to)}`;
    const what = sel.kind === 'period' ? (sel.label === 'total' ? 'Since the cell was first counted' : `Shift ${sel.label}`)
      : sel.kind === 'day' ? `Day ${sel.label} (${d.shifts.length} shifts)` : `Range (${d.shifts.length} shifts)`;
    // The day offered is the one the shift shown is named for (the day it began), so
    // just after midnight a night shift's day is still the one it belongs to; once the
    // user picks a day, it is theirs.
    const named = sel.kind === 'period' && /^(\d{4}-\d{2}-\d{2})\//.exec(sel.label);
    const dayInput = root.querySelector('[data-testid=stats-day]');
    if (named && !dayInput.dataset.chosen) dayInput.value = named[1];
    root.querySelector('.selection').textContent = `${what}: ${span}`;
    root.querySelector('.selection').dataset.kind = sel.kind;
    root.querySelector('.stats-body').replaceChildren(
      figures(d.sum),
      el('div', { class: 'charts' },
        frame('Time in each state per task', 'chart-states', stateBars(d.sum.tasks)),
        frame(d.hourly.length > 48 ? 'Products out per day' : 'Products out per hour', 'chart-hourly',
              hourly(d.hourly), d.hourly_from > (d.sum.from ?? 0) ? `since ${time(d.hourly_from)}` : null),
        frame(`Cycle times (${d.cycles.n} between products out)`, 'chart-cycles', cycles(d.cycles)),
        frame('OEE per shift', 'chart-oee', oee(d.shifts),
              `ideal cycle time ${duration(d.ideal_cycle_ms)} (settings: oee)` +
              (d.shifts.some((s) => s.oee.performance > 1)
                ? ' · a performance above 100 % says the ideal cycle time is longer than the cell\'s real cycles: check the setting'
                : ''))),
      el('div', { class: 'definitions', testid: 'oee-definitions' },
        el('h3', { text: 'How the figures are made' }),
        el('p', { text: 'Time in each state: every task\'s time in each IPC-2541 state, counted by the cell; the time since the last write (at most a second) is not in yet.' }),
        el('p', { text: 'Planned time: each task\'s time not OFF, averaged over the tasks. Run time: the planned time less the time DOWN or in SETUP, averaged alike.' }),
        el('p', { text: 'Availability = run time ÷ planned time. Performance = ideal cycle time × products out ÷ run time. Quality = good products ÷ products out. OEE = availability × performance × quality.' }),
        el('p', { text: 'Products out per hour and cycle times: the products that left the cell in this time, by the hour of the clock they left in; a cycle time is the time between two products out.' })));
  }

  function schedule() {
    if (!visible || !live() || pending) return;
    pending = setTimeout(() => { pending = null; if (visible && live()) load(); }, REFRESH_MS);
  }

  window.cellPanel.register({
    id: 'statistics', title: 'Statistics', minRole: 'anonymous',
    mount(section, p) {
      panel = p;
      root = section;
      section.classList.add('page', 'statistics-page');
      const now = Date.now();
      const day = el('input', { type: 'date', class: 'day', testid: 'stats-day', value: localInput(now).slice(0, 10),
                                on: { change: (e) => { e.target.dataset.chosen = 'yes'; } } });
      const from = el('input', { type: 'datetime-local', testid: 'stats-from', value: localInput(now - 86400000) });
      const to = el('input', { type: 'datetime-local', testid: 'stats-to', title: 'empty: now' });
      section.append(
        el('div', { class: 'filters stats-choice' },
          el('button', { class: 'small', testid: 'stats-shift', text: 'This shift', on: { click: () => choose('period=shift') } }),
          el('button', { class: 'small', testid: 'stats-total', text: 'Total', on: { click: () => choose('period=total') } }),
          el('select', { class: 'shift-select', testid: 'stats-shift-select',
                         on: { change: (e) => { if (e.target.value) choose(`period=${encodeURIComponent(e.target.value)}`); } } }),
          el('label', {}, 'day ', day),
          el('button', { class: 'small', testid: 'stats-day-show', text: 'Day', on: { click: () => { if (day.value) choose(`day=${day.value}`); } } }),
          el('label', {}, 'from ', from), el('label', {}, 'to ', to),
          el('button', { class: 'small', testid: 'stats-range-show', text: 'Range',
                         on: { click: () => {
                           if (!from.value) { panel.toast('Choose where the range begins.'); return; }
                           choose(`from=${fromInput(from.value)}` + (to.value ? `&to=${fromInput(to.value)}` : ''));
                         } } })),
        el('p', { class: 'selection', testid: 'stats-selection' }),
        el('div', { class: 'stats-body' }));
      p.on('task', schedule);
      p.on('snapshot', schedule);
    },
    show() { visible = true; load(); },
    hide() { visible = false; },
  });
})();
