// Audit (admin): the audit trail of every change made through the panel — who, with
// which role, from where, what, and the answer — filtered by user, action and time,
// a page at a time.
'use strict';

(() => {
  const { el, time, localInput, fromInput, attempt } = window.cellUi;
  const LIMIT = 100;
  let panel;
  let root;
  let offset = 0;
  let asked = 0;   // the latest search: the answer of an older one is not drawn

  // The rows shown no longer answer a new search: they go at once, and only the
  // latest search's answer takes their place.
  async function load(at) {
    const f = root.querySelector('.audit-form');
    const q = new URLSearchParams();
    const who = f.querySelector('.who').value.trim();
    const action = f.querySelector('.action').value;
    if (who) q.set('who', who);
    if (action) q.set('action', action);
    const from = fromInput(f.querySelector('.from').value);
    const to = fromInput(f.querySelector('.to').value);
    if (from !== undefined) q.set('from', String(from));
    if (to !== undefined) q.set('to', String(to));
    q.set('limit', String(LIMIT));
    q.set('offset', String(at));
    const n = ++asked;
    root.querySelector('.audit-lines').replaceChildren();
    root.querySelector('.audit-range').textContent = 'searching…';
    const page = await attempt(panel, () => panel.api('GET', `/api/audit?${q}`));
    if (n !== asked) return;
    if (!page) { root.querySelector('.audit-range').textContent = ''; return; }
    offset = at;
    root.querySelector('.audit-lines').replaceChildren(...page.entries.map((e) => el('tr', { data: { who: e.who, action: e.action } },
      el('td', { class: 'time', text: time(e.time) }), el('td', { class: 'who', text: e.who }), el('td', { text: e.role }),
      el('td', { text: e.address }), el('td', { class: 'action', text: e.action }), el('td', { class: 'text', text: e.target }),
      el('td', { class: 'outcome', text: e.outcome }), el('td', { class: 'text', text: e.detail || '' }))));
    root.querySelector('.audit-range').textContent = page.entries.length
      ? `entries ${at + 1}–${at + page.entries.length}` : 'no entries';
    root.querySelector('.audit-prev').disabled = at === 0;
    root.querySelector('.audit-next').disabled = !page.more;
  }

  window.cellPanel.register({
    id: 'audit', title: 'Audit', minRole: 'admin',
    mount(section, p) {
      panel = p;
      root = section;
      section.classList.add('page', 'audit-page');
      const now = Date.now();
      section.append(
        el('form', { class: 'filters audit-form', on: { submit: (e) => { e.preventDefault(); load(0); } } },
          el('label', {}, 'user ', el('input', { class: 'who', testid: 'audit-who', maxLength: 64, autocomplete: 'off' })),
          el('label', {}, 'action ', el('select', { class: 'action', testid: 'audit-action' },
            ['', 'POST', 'PUT', 'DELETE'].map((a) => el('option', { value: a, text: a || 'all' })))),
          el('label', {}, 'from ', el('input', { type: 'datetime-local', class: 'from', testid: 'audit-from',
                                                 value: localInput(now - 86400000) })),
          el('label', {}, 'to ', el('input', { type: 'datetime-local', class: 'to', testid: 'audit-to' })),
          el('button', { type: 'submit', class: 'small primary', testid: 'audit-search', text: 'Search' })),
        el('div', { class: 'pager' },
          el('button', { class: 'small audit-prev', text: 'Earlier', on: { click: () => load(Math.max(0, offset - LIMIT)) } }),
          el('span', { class: 'audit-range' }),
          el('button', { class: 'small audit-next', text: 'Later', on: { click: () => load(offset + LIMIT) } })),
        el('div', { class: 'scroll' }, el('table', { class: 'log audit' },
          el('thead', {}, el('tr', {}, ['time', 'user', 'role', 'from', 'action', 'what', 'answer', 'detail'].map((t) => el('th', { text: t })))),
          el('tbody', { class: 'audit-lines', testid: 'audit-lines' }))));
    },
    show() { load(0); },
  });
})();
