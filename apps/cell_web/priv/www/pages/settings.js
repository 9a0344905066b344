// Settings (service, admin): every settings object as a form made from its schema
// (types, ranges, units, defaults, docs), its revisions with who and when, the
// differences between two of them, and restore. A value the cell refuses is shown at
// the field the cell names.
'use strict';

(() => {
  const { el, time, attempt } = window.cellUi;
  let panel;
  let root;
  let chosen = null;     // the object's name
  let object = null;     // as GET /api/settings/:name answers
  let inputs = new Map(); // path -> {read(), box}
  let opening = null;    // the name of the object being read to be shown
  let writes = 0;        // how many times the form was made or saved: older answers are dropped

  const NUMERIC = { integer: true, float: true };

  function range(f) {
    const u = f.unit ? ` ${f.unit}` : '';
    if (f.min !== undefined && f.min !== null && f.max !== undefined && f.max !== null) return `${f.min} to ${f.max}${u}`;
    if (f.min !== undefined && f.min !== null) return `at least ${f.min}${u}`;
    if (f.max !== undefined && f.max !== null) return `at most ${f.max}${u}`;
    if (f.max_length) return `up to ${f.max_length} characters`;
    return u.trim();
  }

  const show = (v) => (v === null || v === undefined ? 'none' : typeof v === 'object' ? JSON.stringify(v) : String(v));

  // One input for a value of a scalar type; read() gives the JSON value.
  function scalar(f, value, disabled, path) {
    const id = `set-${path}`;
    if (f.type === 'boolean') {
      const i = el('input', { type: 'checkbox', id, checked: value === true, disabled, class: 'big-check' });
      return { node: i, read: () => i.checked };
    }
    if (f.type === 'enum') {
      const s = el('select', { id, disabled }, f.values.map((v) => el('option', { value: v, text: v })));
      s.value = value;
      return { node: s, read: () => s.value };
    }
    const i = el('input', { id, disabled, value: value === null || value === undefined ? '' : String(value) });
    if (NUMERIC[f.type]) {
      i.type = 'number';
      i.inputMode = f.type === 'integer' ? 'numeric' : 'decimal';
      i.step = f.type === 'integer' ? '1' : 'any';
      if (f.min !== null && f.min !== undefined) i.min = f.min;
      if (f.max !== null && f.max !== undefined) i.max = f.max;
    } else if (f.max_length) {
      i.maxLength = f.max_length;
    }
    const read = () => {
      if (i.value === '' && f.optional) return null;
      if (NUMERIC[f.type]) return i.value === '' ? '' : Number(i.value);
      return i.value;
    };
    return { node: i, read };
  }

  // A list of scalars: one input a row, with Add and Remove.
  function list(f, values, disabled, path) {
    const box = el('div', { class: 'list-field' });
    const rows = [];
    const add = (v) => {
      const s = scalar(f.of, v, disabled, `${path}-${rows.length + 1}`);
      const row = el('div', { class: 'list-row' }, s.node);
      const entry = { s, row };
      row.append(el('button', { type: 'button', class: 'small', text: 'Remove', disabled,
                                on: { click: () => { rows.splice(rows.indexOf(entry), 1); row.remove(); } } }));
      rows.push(entry);
      box.insertBefore(row, addButton);
    };
    const addButton = el('button', { type: 'button', class: 'small', text: 'Add', disabled,
                                     on: { click: () => add(f.of.default ?? (NUMERIC[f.of.type] ? 0 : '')) } });
    box.append(addButton);
    for (const v of values || []) add(v);
    return { node: box, read: () => rows.map((r) => r.s.read()) };
  }

  // The fields of an object (nested objects as fieldsets); paths as the cell writes
  // them: a.b, a[2].
  function fields(defs, values, disabled, prefix) {
    return defs.map((f) => {
      const path = prefix ? `${prefix}.${f.name}` : f.name;
      const value = values ? values[f.name] : undefined;
      if (f.type === 'object') {
        const inner = fields(f.fields, value, disabled, path);
        const box = el('fieldset', { class: 'object-field', data: { field: path } },
                       el('legend', { text: f.name }), f.doc ? el('p', { class: 'doc', text: f.doc }) : null, inner);
        inputs.set(path, { box, read: () => collect(f.fields, path), nested: true });
        return box;
      }
      const input = f.type === 'list' ? list(f, value, disabled, path) : scalar(f, value, disabled, path);
      const facts = [range(f), f.default !== null && f.default !== undefined ? `default ${show(f.default)}` : ''];
      const box = el('div', { class: 'field', data: { field: path }, testid: `field-${path}` },
        el('label', { class: 'name', for: `set-${path}`, text: f.name }),
        el('div', { class: 'input' }, input.node, f.unit && f.type !== 'list' ? el('span', { class: 'unit', text: f.unit }) : null),
        el('div', { class: 'facts', text: facts.filter(Boolean).join(' · ') }),
        f.doc ? el('div', { class: 'doc', text: f.doc }) : null,
        el('div', { class: 'field-error', testid: 'field-error' }));
      inputs.set(path, { box, read: input.read });
      return box;
    });
  }

  function collect(defs, prefix) {
    const out = {};
    for (const f of defs) {
      const path = prefix ? `${prefix}.${f.name}` : f.name;
      out[f.name] = inputs.get(path).read();
    }
    return out;
  }

  function clearErrors() {
    for (const e of root.querySelectorAll('.field.invalid')) e.classList.remove('invalid');
    for (const e of root.querySelectorAll('.field-error')) e.textContent = '';
  }

  // The error at the field the cell names: the longest field path it starts with.
  function markError(path, message) {
    const names = [...inputs.keys()].filter((p) => !inputs.get(p).nested &&
      (path === p || path.startsWith(p + '.') || path.startsWith(p + '[')));
    names.sort((a, b) => b.length - a.length);
    const target = names.length ? inputs.get(names[0]).box : null;
    if (!target) { panel.toast(message); return; }
    target.classList.add('invalid');
    target.querySelector('.field-error').textContent = message;
    target.scrollIntoView({ block: 'nearest' });
  }

  async function loadList() {
    const list = await attempt(panel, () => panel.api('GET', '/api/settings'));
    if (!list) return;
    const box = root.querySelector('.objects');
    box.replaceChildren(...list.map((o) => el('button', {
      class: 'object' + (o.name === chosen ? ' active' : ''), testid: `settings-${o.name}`,
      data: { name: o.name },
      on: { click: () => open(o.name) } }, o.name, o.pending ? el('span', { class: 'pending', text: ' ●' }) : null)));
    if (!chosen && list.length) open(list[0].name);
  }

  // The object chosen again while its form is shown (or on its way) keeps the form
  // and what is typed in it: its marks of changes waiting are brought again.
  async function open(name) {
    if (name === chosen && (opening === name || (object && object.name === name))) {
      if (opening !== name) refresh();
      return;
    }
    chosen = name;
    opening = name;
    for (const b of root.querySelectorAll('.objects .object')) b.classList.toggle('active', b.dataset.name === name);
    const obj = await attempt(panel, () => panel.api('GET', `/api/settings/${encodeURIComponent(name)}`));
    if (opening === name) opening = null;
    if (!obj || chosen !== name) return;
    object = obj;
    renderForm();
    loadRevisions();
  }

  // The marks of changes waiting, read again; an answer read before the form last
  // changed (a save, a restore, the form made anew) is older than what it shows.
  async function refresh() {
    if (!object) return;
    const name = object.name;
    const seen = writes;
    const obj = await attempt(panel, () => panel.api('GET', `/api/settings/${encodeURIComponent(name)}`));
    if (!obj || !object || object.name !== name || seen !== writes) return;
    object.pending = obj.pending;
    object.in_force = obj.in_force;
    const note = root.querySelector('[data-testid=settings-pending]');
    if (note) note.classList.toggle('hidden', !obj.pending);
  }

  function mayEdit() {
    return object && panel.rank(panel.session().role) >= panel.rank(object.edit_role);
  }

  function renderForm() {
    writes += 1;
    inputs = new Map();
    const disabled = !mayEdit();
    const form = root.querySelector('.settings-form');
    form.replaceChildren(
      el('h2', { text: object.name }),
      object.pending ? el('p', { class: 'note', testid: 'settings-pending',
                                 text: 'Saved changes apply at the next Start.' }) : null,
      disabled ? el('p', { class: 'note', text: `Editing ${object.name} needs the role ${object.edit_role}.` }) : null,
      ...fields(object.fields, object.values, disabled, ''),
      el('div', { class: 'actions' },
         el('button', { type: 'submit', class: 'primary', testid: 'settings-save', disabled, text: 'Save' })));
  }

  async function save(ev) {
    ev.preventDefault();
    clearErrors();
    const values = collect(object.fields, '');
    const changed = {};
    for (const [k, v] of Object.entries(values)) {
      if (JSON.stringify(v) !== JSON.stringify(object.values[k])) changed[k] = v;
    }
    if (Object.keys(changed).length === 0) { panel.toast('Nothing changed.'); return; }
    writes += 1;
    try {
      object = await panel.api('PUT', `/api/settings/${encodeURIComponent(object.name)}`, changed);
      renderForm();
      panel.toast(`${object.name} saved.`);
      loadRevisions();
      loadList();
    } catch (e) {
      if (e.field) markError(e.field, e.message);
      else panel.toast(e.message);
    }
  }

  async function loadRevisions() {
    const name = object.name;
    const revs = await attempt(panel, () => panel.api('GET', `/api/settings/${encodeURIComponent(name)}/revisions`));
    if (!revs || name !== chosen) return;
    const may = mayEdit();
    const body = root.querySelector('.revisions tbody');
    body.replaceChildren(...revs.map((r, i) => el('tr', { data: { rev: r.rev } },
      el('td', { text: String(r.rev) }), el('td', { text: time(r.time) }), el('td', { text: r.who }),
      el('td', {}, i === 0 ? el('span', { class: 'quiet', text: 'current' }) :
        el('button', { class: 'small', text: 'Restore', disabled: !may, testid: `restore-${r.rev}`,
                       on: { click: () => restore(r.rev) } })))));
    const opts = revs.map((r) => el('option', { value: r.rev, text: `${r.rev} · ${time(r.time)} · ${r.who}` }));
    const from = root.querySelector('.diff-from');
    const to = root.querySelector('.diff-to');
    from.replaceChildren(...opts.map((o) => o.cloneNode(true)));
    to.replaceChildren(...opts);
    if (revs.length > 1) from.value = revs[1].rev;
    if (revs.length) to.value = revs[0].rev;
    root.querySelector('.diff').replaceChildren();
  }

  async function diff(ev) {
    ev.preventDefault();
    const from = root.querySelector('.diff-from').value;
    const to = root.querySelector('.diff-to').value;
    const changes = await attempt(panel, () =>
      panel.api('GET', `/api/settings/${encodeURIComponent(object.name)}/diff?from=${from}&to=${to}`));
    if (!changes) return;
    const box = root.querySelector('.diff');
    box.replaceChildren(changes.length === 0
      ? el('p', { class: 'quiet', text: `Revisions ${from} and ${to} are the same.` })
      : el('table', { class: 'log diff-table', testid: 'settings-diff' },
          el('thead', {}, el('tr', {}, el('th', { text: 'field' }), el('th', { text: `revision ${from}` }),
                                    el('th', { text: `revision ${to}` }))),
          el('tbody', {}, changes.map((c) => el('tr', { data: { path: c.path } },
            el('td', { text: c.path }), el('td', { class: 'old', text: show(c.from) }),
            el('td', { class: 'new', text: show(c.to) }))))));
  }

  async function restore(rev) {
    if (!window.confirm(`Make revision ${rev} of ${object.name} current again?`)) return;
    writes += 1;
    const obj = await attempt(panel, () =>
      panel.api('POST', `/api/settings/${encodeURIComponent(object.name)}/restore`, { rev }));
    if (!obj) return;
    object = obj;
    renderForm();
    panel.toast(`${object.name} restored to revision ${rev}.`);
    loadRevisions();
  }

  // A Start takes the saved changes into force: the marks of changes waiting are
  // brought again (the form keeps what is being typed).
  let request = null;
  let visible = false;
  async function started(msg) {
    const was = request;
    request = msg.cell && msg.cell.request;
    if (!visible || was === request || !object) return;
    loadList();
    refresh();
  }

  window.cellPanel.register({
    id: 'settings', title: 'Settings', minRole: 'service',
    mount(section, p) {
      panel = p;
      root = section;
      section.classList.add('page', 'settings-page');
      section.append(
        el('div', { class: 'objects', testid: 'settings-objects' }),
        el('form', { class: 'settings-form', testid: 'settings-form', on: { submit: save } }),
        el('div', { class: 'history' },
          el('h2', { text: 'Revisions' }),
          el('div', { class: 'scroll' }, el('table', { class: 'log revisions', testid: 'settings-revisions' },
            el('thead', {}, el('tr', {}, el('th', { text: 'rev' }), el('th', { text: 'when' }),
                                       el('th', { text: 'who' }), el('th', {}))),
            el('tbody'))),
          el('form', { class: 'filters diff-form', on: { submit: diff } },
            el('label', {}, 'from ', el('select', { class: 'diff-from', testid: 'diff-from' })),
            el('label', {}, 'to ', el('select', { class: 'diff-to', testid: 'diff-to' })),
            el('button', { type: 'submit', class: 'small', testid: 'settings-diff-show', text: 'Differences' })),
          el('div', { class: 'diff' })));
      p.on('cell', started);
      p.on('snapshot', started);
    },
    show() { visible = true; chosen = null; loadList(); },
    hide() { visible = false; },
  });
})();
