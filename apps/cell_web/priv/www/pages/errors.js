// The Errors page (operators): the active errors, alarms and warnings with their own
// solutions, and the history of answers (who answered what, when), filterable. The
// active list follows the websocket; the history is read when the page is shown and
// again whenever an error is answered, closed or cleared (a websocket message).
'use strict';
(() => {
  const SOLUTIONS = { retry: 'Retry', ignore: 'Ignore', reset: 'Reset', close: 'Close' };
  const ORDER = { alarm: 0, error: 1, warning: 2 };
  let panel, root, shown = false;
  const active = new Map();
  let history = [];

  function html(tag, cls, text) {
    const e = document.createElement(tag);
    if (cls) e.className = cls;
    if (text !== undefined) e.textContent = text;
    return e;
  }
  function when(ms) {
    if (!ms) return '';
    const d = new Date(ms), pad = (n) => String(n).padStart(2, '0');
    return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ` +
           `${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
  }

  function mount(section, p) {
    panel = p;
    root = section;
    section.classList.add('errors-page');
    const list = html('div', 'panel errors-active');
    list.append(html('h2', '', 'Active'), html('div', 'list'));
    list.querySelector('.list').dataset.testid = 'errors-active';
    const form = html('form', 'filters');
    form.innerHTML = `
      <label>task <select name="task"><option value="">all</option></select></label>
      <label>answer <select name="what"><option value="">all</option></select></label>
      <label>who <input name="who" size="10" autocomplete="off"></label>
      <label>text <input name="text" size="14" autocomplete="off"></label>
      <label>from <input type="datetime-local" name="from"></label>`;
    form.dataset.testid = 'history-filters';
    form.addEventListener('input', renderHistory);
    form.addEventListener('submit', (ev) => ev.preventDefault());
    const table = html('table', 'log history');
    table.innerHTML = '<thead><tr><th>when</th><th>task</th><th>error</th>' +
                      '<th>answer</th><th>who</th></tr></thead><tbody data-testid="history"></tbody>';
    const hist = html('div', 'errors-history');
    hist.append(html('h2', '', 'History'), form, table);
    section.append(list, hist);
    panel.on('snapshot', (m) => { active.clear(); for (const a of m.alarms) active.set(a.id, a); renderActive(); });
    panel.on('alarm', (m) => { active.set(m.alarm.id, m.alarm); renderActive(); });
    panel.on('alarm_cleared', (m) => { active.delete(m.alarm.id); renderActive(); if (shown) load(); });
  }

  function renderActive() {
    if (!root) return;
    const box = root.querySelector('.errors-active .list');
    const may = panel.rank(panel.session().role) >= panel.rank('operator');
    const list = [...active.values()].sort((a, b) => ORDER[a.kind] - ORDER[b.kind] || a.raised - b.raised);
    box.replaceChildren(...list.map((a) => {
      const item = html('div', 'alarm ' + (a.kind === 'alarm' ? 'alarm-kind' : a.kind));
      // Named apart from the Line view's error items, which are in the page too.
      item.dataset.errorId = a.id;
      item.dataset.errorKind = a.kind;
      const head = html('div', 'head');
      head.append(html('span', 'caption', a.caption), html('span', 'who', `${a.kind} · ${a.task} · ${when(a.raised)}`));
      item.append(head, html('div', 'description', a.description));
      if (a.kind === 'alarm') {
        item.append(html('div', 'note', 'Clears by itself when its cause is gone.'));
      } else {
        const buttons = html('div', 'solutions');
        for (const s of a.solutions) {
          const b = html('button', '', SOLUTIONS[s] || s);
          b.dataset.solution = s;
          b.disabled = !may;
          b.addEventListener('click', async () => {
            b.disabled = true;
            try {
              await panel.api('POST', `/api/alarms/${encodeURIComponent(a.id)}/answer`, { solution: s });
            } catch (e) {
              panel.toast(e.message);
              b.disabled = false;
            }
          });
          buttons.append(b);
        }
        item.append(buttons);
      }
      return item;
    }));
    if (list.length === 0) box.append(html('p', 'quiet', 'No errors, no warnings.'));
  }

  async function load() {
    const got = await window.cellUi.attempt(panel, () => panel.api('GET', '/api/alarms/history'));
    if (!got) return;
    history = got;
    options('task', history.map((r) => r.task));
    options('what', history.map((r) => r.what));
    renderHistory();
  }

  function options(name, values) {
    const select = root.querySelector(`select[name=${name}]`);
    const keep = select.value;
    const all = [...new Set(values.filter((v) => v != null).map(String))].sort();
    select.replaceChildren(new Option('all', ''), ...all.map((v) => new Option(v, v)));
    select.value = all.includes(keep) ? keep : '';
  }

  function renderHistory() {
    const f = new FormData(root.querySelector('form'));
    const task = f.get('task'), what = f.get('what');
    const who = String(f.get('who') || '').toLowerCase(), text = String(f.get('text') || '').toLowerCase();
    const from = f.get('from') ? new Date(f.get('from')).getTime() : null;
    const rows = history.filter((r) =>
      (!task || String(r.task) === task) && (!what || String(r.what) === what) &&
      (!who || String(r.who || '').toLowerCase().includes(who)) &&
      (!text || `${r.caption || ''} ${r.id || ''}`.toLowerCase().includes(text)) &&
      (!from || (r.time || 0) >= from));
    const body = root.querySelector('[data-testid=history]');
    body.replaceChildren(...rows.map((r) => {
      const tr = html('tr', r.kind || '');
      tr.dataset.id = r.id;
      for (const [cls, v] of [['time', when(r.time)], ['source', r.task],
                              ['text', r.caption], ['what', r.what], ['who', r.who]]) {
        tr.append(html('td', cls, v == null ? '' : String(v)));
      }
      return tr;
    }));
    if (rows.length === 0) {
      const tr = html('tr');
      const td = html('td', 'quiet', history.length ? 'Nothing matches the filter.' : 'No answers yet.');
      td.colSpan = 5;
      tr.append(td);
      body.append(tr);
    }
  }

  window.cellPanel.register({
    id: 'errors', title: 'Errors', minRole: 'operator', mount,
    show() { shown = true; load(); renderActive(); },
    hide() { shown = false; },
  });
})();
