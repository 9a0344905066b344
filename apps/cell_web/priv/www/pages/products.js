// Products (everyone): the products in the cell now, a search by serial, and a
// product's history as a timeline — entry with its recipe, transfers, work, changes,
// errors and the answers given, inspection results, exit — from
// /api/products/:serial/history (and the inspection's parts, where the cell runs it).
// A product in the cell is followed live: each of its tasks' changes on the websocket
// brings its history again.
'use strict';

(() => {
  const { el, time, duration, attempt } = window.cellUi;
  let panel;
  let root;
  let serial = null;
  let visible = false;
  let pending = null;
  const REFRESH_MS = 1200;

  const enc = encodeURIComponent;

  // What an entry of the history is, for its mark on the timeline and its words.
  function kind(e) {
    switch (e.event) {
      case 'entered': return ['entry', `entered at ${e.task}` + (e.recipe ? ` with recipe ${e.recipe}` : '')];
      case 'item_transfer_in': return ['transfer', `transferred into ${e.task}`];
      case 'item_transfer_out': return ['transfer', `transferred out of ${e.task}`];
      case 'item_identifier_read': return ['transfer', `identifier read at ${e.task}` + (e.scanner ? ` by ${e.scanner}` : '')];
      case 'item_work_start': return ['work', `work started at ${e.task}`];
      case 'item_work_pause': return ['work', `work paused at ${e.task}`];
      case 'item_work_resume': return ['work', `work resumed at ${e.task}`];
      case 'item_work_complete': return ['work', `work completed at ${e.task}`];
      case 'item_work_abort': return ['error', `work aborted at ${e.task}`];
      case 'changed': return ['change', `changed at ${e.task}: ` +
        Object.entries(e.changes || {}).map(([k, v]) => `${k} = ${typeof v === 'object' ? JSON.stringify(v) : v}`).join(', ')];
      case 'alarm_raised': return ['error', `${e.kind || 'error'} at ${e.task}: ${e.caption}`];
      case 'alarm_answered': return ['answer', `${e.who || 'someone'} answered ${e.solution} to “${e.caption}” at ${e.task}`];
      case 'alarm_cleared': return ['answer', `cleared at ${e.task}: ${e.caption}` + (e.who ? ` (${e.who})` : '')];
      case 'left': return ['exit', `left the cell through ${e.task}, ${e.quality}`];
      case 'scrapped': return ['exit', `scrapped: ${e.text || ''}`];
      default: return ['inspection', `${e.event}` + (e.task ? ` at ${e.task}` : '') +
        (e.detail !== undefined ? `: ${typeof e.detail === 'object' ? JSON.stringify(e.detail) : e.detail}` : '')];
    }
  }

  async function search(s) {
    serial = s.trim();
    if (!serial) return;
    root.querySelector('.serial-input').value = serial;
    const box = root.querySelector('.history');
    try {
      const h = await panel.api('GET', `/api/products/${enc(serial)}/history`);
      if (h.serial !== undefined && h.serial !== serial) return;
      const parts = await panel.api('GET', `/api/inspect/parts/${enc(serial)}`).catch(() => null);
      box.replaceChildren(timeline(h, parts));
    } catch (e) {
      box.replaceChildren(el('p', { class: 'note', testid: 'product-not-found',
                                    text: e.status === 404 ? `No product ${serial} has been recorded.` : e.message }));
    }
  }

  // The inspection blocks' records of the part, where the cell runs them: each
  // inspection and override as its fields.
  function inspection(parts) {
    if (!parts) return null;
    const rows = [...(parts.inspections || []).map((r) => ['inspection', r]),
                  ...(parts.overrides || []).map((r) => ['override', r])];
    if (rows.length === 0) return null;
    const words = (v) => (typeof v === 'object' && v !== null ? JSON.stringify(v) : String(v));
    return el('div', { class: 'inspection', testid: 'product-inspection' },
      el('h3', { text: 'Inspection' }),
      el('ul', {}, rows.map(([k, r]) => el('li', { data: { kind: k } }, el('b', { text: `${k}: ` }),
        Object.entries(r).map(([f, v]) => `${f} ${words(v)}`).join(' · ')))));
  }

  function timeline(h, parts) {
    const events = h.events || [];
    const first = events.length ? events[0].time : h.entered;
    const where = (h.in_cell || []).map((p) => `${p.task} (${p.state})`).join(', ');
    const status = h.status === 'in_cell' ? `in the cell${where ? ' at ' + where : ''}`
      : h.status === 'out' ? `left the cell ${h.failed ? 'failed' : 'good'}` : String(h.status);
    const facts = [
      ['serial', h.serial], ['status', status], ['recipe', h.recipe || '—'],
      ['entered', h.entered ? `${time(h.entered)} at ${h.entry_task || '—'}` : '—'],
      ['left', h.left ? `${time(h.left)} through ${h.exit_task || '—'}` : '—'],
      ['time in the cell', h.entered ? duration((h.left || Date.now()) - h.entered) : '—'],
    ];
    return el('div', { class: 'product', testid: 'product-history', data: { serial: h.serial } },
      el('dl', { class: 'facts' }, facts.map(([k, v]) => [el('dt', { text: k }), el('dd', { text: v, data: { fact: k } })])),
      inspection(parts),
      el('ol', { class: 'timeline', testid: 'product-timeline' }, events.map((e) => {
        const [k, words] = kind(e);
        return el('li', { class: `ev ev-${k}`, data: { kind: k, event: e.event } },
          el('span', { class: 'when', text: time(e.time) }),
          el('span', { class: 'since', text: `+${duration(e.time - first)}` }),
          el('span', { class: 'mark', text: k }),
          el('span', { class: 'what', text: words }));
      })));
  }

  async function loadInCell() {
    const list = await attempt(panel, () => panel.api('GET', '/api/products'));
    if (!list) return;
    root.querySelector('.in-cell').replaceChildren(...(
      list.length === 0 ? [el('span', { class: 'quiet', text: 'No product in the cell.' })] :
        list.map((p) => el('button', { class: 'small chip', testid: `in-cell-${p.serial}`,
                                       on: { click: () => search(p.serial) } }, `${p.serial} · ${p.task}`))));
  }

  function changed() {
    if (!visible || pending) return;
    pending = setTimeout(() => {
      pending = null;
      if (!visible) return;
      loadInCell();
      if (serial) search(serial);
    }, REFRESH_MS);
  }

  window.cellPanel.register({
    id: 'products', title: 'Products', minRole: 'anonymous',
    mount(section, p) {
      panel = p;
      root = section;
      section.classList.add('page', 'products-page');
      const input = el('input', { class: 'serial-input', testid: 'serial-input', placeholder: 'serial', maxLength: 128,
                                  autocomplete: 'off' });
      section.append(
        el('form', { class: 'filters', on: { submit: (e) => { e.preventDefault(); search(input.value); } } },
          el('label', {}, 'serial ', input),
          el('button', { type: 'submit', class: 'small primary', testid: 'serial-search', text: 'Find' })),
        el('div', { class: 'in-cell filters', testid: 'products-in-cell' }),
        el('div', { class: 'history scroll' }));
      p.on('task', changed);
    },
    show() { visible = true; loadInCell(); },
    hide() { visible = false; },
  });
})();
