// Recipes (service): the list, upload of a .zprd file, download, copy, rename,
// delete, a drawing imported from DXF, and a preview of the recipe's drawing drawn as
// SVG from its drawing tree, with the order the cuts are worked in (ExecOrder).
'use strict';

(() => {
  const { el, svg, time, attempt, send } = window.cellUi;
  let panel;
  let root;
  let chosen = null;
  let recipes = [];

  const enc = encodeURIComponent;
  const may = () => panel.rank(panel.session().role) >= panel.rank('service');
  const kb = (n) => (n < 1024 ? `${n} B` : `${(n / 1024).toFixed(1)} KiB`);

  async function load() {
    const list = await attempt(panel, () => panel.api('GET', '/api/recipes'));
    if (!list) return;
    recipes = list;
    const body = root.querySelector('.recipe-list tbody');
    body.replaceChildren(...list.map((r) => el('tr', {
      class: r.name === chosen ? 'active' : '', data: { recipe: r.name },
      on: { click: () => open(r.name) } },
      el('td', { class: 'name', text: r.name }),
      el('td', { text: r.error || r.description }),
      el('td', { text: r.author || '' }),
      el('td', { text: r.modified ? time(r.modified) : '' }),
      el('td', { text: r.bytes ? kb(r.bytes) : '' }))));
    root.querySelector('.no-recipes').classList.toggle('hidden', list.length > 0);
    if (chosen && !list.some((r) => r.name === chosen)) { chosen = null; detail(); }
    renderTools();
  }

  function renderTools() {
    for (const b of root.querySelectorAll('.needs-service')) b.disabled = !may();
  }

  async function open(name) {
    chosen = name;
    for (const tr of root.querySelectorAll('.recipe-list tbody tr')) tr.classList.toggle('active', tr.dataset.recipe === name);
    detail();
    const drawing = await attempt(panel, () => panel.api('GET', `/api/recipes/${enc(name)}/drawing`));
    if (drawing && chosen === name) root.querySelector('.preview').replaceChildren(preview(drawing));
  }

  function detail() {
    const box = root.querySelector('.recipe-detail');
    if (!chosen) { box.replaceChildren(el('p', { class: 'quiet', text: 'Choose a recipe to see its drawing.' })); return; }
    const name = chosen;
    const target = el('input', { class: 'new-name', testid: 'recipe-new-name', placeholder: 'new name', maxLength: 128 });
    box.replaceChildren(
      el('h2', { testid: 'recipe-title', text: name }),
      el('div', { class: 'filters' },
        el('a', { class: 'button small', href: `/api/recipes/${enc(name)}/file`, download: `${name}.zprd`,
                  testid: 'recipe-download', text: 'Download' }),
        target,
        el('button', { class: 'small needs-service', testid: 'recipe-copy', text: 'Copy',
                       on: { click: () => move('copy', name, target.value) } }),
        el('button', { class: 'small needs-service', testid: 'recipe-rename', text: 'Rename',
                       on: { click: () => move('rename', name, target.value) } }),
        el('button', { class: 'small needs-service danger', testid: 'recipe-delete', text: 'Delete',
                       on: { click: () => remove(name) } })),
      el('div', { class: 'preview', testid: 'recipe-preview' }, el('p', { class: 'quiet', text: 'Loading the drawing…' })));
    renderTools();
  }

  async function move(op, name, to) {
    if (!to) { panel.toast('Type the new name first.'); return; }
    const done = await attempt(panel, () => panel.api('POST', `/api/recipes/${enc(name)}/${op}`, { to }));
    if (!done) return;
    panel.toast(op === 'copy' ? `${name} copied to ${to}.` : `${name} renamed ${to}.`);
    if (op === 'rename') chosen = to;
    await load();
    open(chosen);
  }

  async function remove(name) {
    if (!window.confirm(`Delete the recipe ${name}?`)) return;
    const done = await attempt(panel, () => panel.api('DELETE', `/api/recipes/${enc(name)}`));
    if (!done) return;
    panel.toast(`${name} deleted.`);
    chosen = null;
    detail();
    load();
  }

  // A file chosen: uploaded as a recipe (.zprd) or imported as a drawing (DXF).
  async function upload(kind, file) {
    const nameInput = root.querySelector('.upload-name');
    const name = nameInput.value.trim() || file.name.replace(/\.(zprd|dxf)$/i, '');
    const replace = root.querySelector('.upload-replace').checked;
    const path = kind === 'dxf' ? `/api/recipes/${enc(name)}/dxf?replace=${replace}`
                                : `/api/recipes/${enc(name)}?replace=${replace}`;
    const type = kind === 'dxf' ? 'application/dxf' : 'application/zip';
    try {
      const answer = await send(panel, 'PUT', path, file, type);
      if (kind === 'dxf') {
        const skipped = Object.entries(answer.skipped || {}).map(([k, n]) => `${n} ${k}`).join(', ');
        panel.toast(`${name}: ${answer.imported} items imported from DXF` + (skipped ? `; left out: ${skipped}.` : '.'));
      } else {
        panel.toast(`${name} uploaded.`);
      }
      nameInput.value = '';
      chosen = name;
      await load();
      open(name);
    } catch (e) {
      panel.toast(e.message);
    }
  }

  // ---------------------------------------------------------------------------
  // The drawing as SVG: Y up as in CAD; items coloured by ItemType; the items with an
  // ExecOrder numbered and joined in that order.

  const pt = (p) => [p[0], -p[1]];

  function bbox(items) {
    const b = { x0: Infinity, y0: Infinity, x1: -Infinity, y1: -Infinity };
    const add = (x, y) => { b.x0 = Math.min(b.x0, x); b.x1 = Math.max(b.x1, x); b.y0 = Math.min(b.y0, y); b.y1 = Math.max(b.y1, y); };
    for (const it of items) {
      if (it.kind === 'line') { add(...pt(it.from)); add(...pt(it.to)); }
      else if (it.kind === 'circle' || it.kind === 'arc') {
        const [x, y] = pt(it.center); add(x - it.radius, y - it.radius); add(x + it.radius, y + it.radius);
      } else if (it.kind === 'polyline') for (const p of it.points) add(...pt(p));
      else if (it.kind === 'polyface') for (const p of it.vertices) add(...pt(p));
    }
    return b;
  }

  function flat(item, out) {
    if (item.kind === 'container') for (const c of item.children) flat(c, out);
    else out.push(item);
    return out;
  }

  function arcPath(c, r, a0, a1) {
    const rad = (d) => (d * Math.PI) / 180;
    let sweep = ((a1 - a0) % 360 + 360) % 360;
    if (sweep === 0) sweep = 360;
    const [cx, cy] = pt(c);
    const at = (a) => [cx + r * Math.cos(rad(a)), cy - r * Math.sin(rad(a))];
    if (sweep >= 360) {
      const [x0, y0] = at(a0); const [xm, ym] = at(a0 + 180);
      return `M${x0} ${y0}A${r} ${r} 0 1 0 ${xm} ${ym}A${r} ${r} 0 1 0 ${x0} ${y0}`;
    }
    const [x0, y0] = at(a0); const [x1, y1] = at(a0 + sweep);
    return `M${x0} ${y0}A${r} ${r} 0 ${sweep > 180 ? 1 : 0} 0 ${x1} ${y1}`;
  }

  // A DXF bulge is tan(θ/4) of the arc from one point to the next, positive counter-clockwise.
  function bulgeSegment(p, q, b) {
    const [x1, y1] = pt(q);
    if (!b) return `L${x1} ${y1}`;
    const [x0, y0] = pt(p);
    const d = Math.hypot(x1 - x0, y1 - y0);
    const r = (d * (1 + b * b)) / (4 * Math.abs(b));
    return `A${r} ${r} 0 ${Math.abs(b) > 1 ? 1 : 0} ${b > 0 ? 0 : 1} ${x1} ${y1}`;
  }

  function shape(it) {
    const a = it.attributes || {};
    const attrs = { class: `prim type-${(a.ItemType || 'none').replace(/[^A-Za-z0-9_-]/g, '')}`,
                    'vector-effect': 'non-scaling-stroke', 'data-kind': it.kind };
    if (it.kind === 'line') {
      const [x1, y1] = pt(it.from); const [x2, y2] = pt(it.to);
      return svg('line', { ...attrs, x1, y1, x2, y2 });
    }
    if (it.kind === 'circle') {
      const [cx, cy] = pt(it.center);
      return svg('circle', { ...attrs, cx, cy, r: it.radius });
    }
    if (it.kind === 'arc') return svg('path', { ...attrs, d: arcPath(it.center, it.radius, it.start_angle, it.end_angle) });
    if (it.kind === 'polyline') {
      const ps = it.points;
      if (!ps.length) return null;
      const [x0, y0] = pt(ps[0]);
      let d = `M${x0} ${y0}`;
      for (let i = 1; i < ps.length; i++) d += bulgeSegment(ps[i - 1], ps[i], it.bulges[i - 1]);
      if (it.closed && ps.length > 1) d += bulgeSegment(ps[ps.length - 1], ps[0], it.bulges[ps.length - 1]) + 'Z';
      return svg('path', { ...attrs, d });
    }
    if (it.kind === 'polyface') {
      return svg('g', attrs, it.faces.map((f) => svg('polygon', {
        'vector-effect': 'non-scaling-stroke',
        points: f.map((i) => pt(it.vertices[Math.abs(i) - 1]).join(',')).join(' ') })));
    }
    return null;
  }

  function tree(item) {
    if (item.kind !== 'container') return shape(item);
    const a = item.attributes || {};
    return svg('g', { class: `container type-${(a.ItemType || 'none').replace(/[^A-Za-z0-9_-]/g, '')}` },
               item.children.map(tree));
  }

  // The items worked in order: every item (container or primitive) with an ExecOrder,
  // each with the middle of its box.
  function ordered(item, out) {
    const n = item.attributes && item.attributes.ExecOrder;
    if (n !== undefined && n !== '') {
      const b = bbox(flat(item, []));
      if (Number.isFinite(b.x0)) out.push({ n: Number(n), type: item.attributes.ItemType || '', x: (b.x0 + b.x1) / 2, y: (b.y0 + b.y1) / 2 });
    }
    if (item.kind === 'container') for (const c of item.children) ordered(c, out);
    return out;
  }

  function preview(drawing) {
    const prims = flat(drawing, []);
    if (prims.length === 0) return el('p', { class: 'quiet', testid: 'drawing-empty', text: 'This recipe has no drawing.' });
    const b = bbox(prims);
    const w = Math.max(b.x1 - b.x0, 1e-6);
    const h = Math.max(b.y1 - b.y0, 1e-6);
    const m = Math.max(w, h) * 0.06;
    const font = Math.max(w, h) * 0.035;
    const order = ordered(drawing, []).sort((p, q) => p.n - q.n);
    const marks = [];
    if (order.length > 1) {
      marks.push(svg('polyline', { class: 'exec-path', 'vector-effect': 'non-scaling-stroke',
                                   points: order.map((o) => `${o.x},${o.y}`).join(' '), 'marker-mid': 'url(#exec-arrow)',
                                   'marker-end': 'url(#exec-arrow)' }));
    }
    order.forEach((o, i) => marks.push(svg('g', { class: 'exec-mark', 'data-exec-order': o.n, 'data-step': i + 1 },
      svg('circle', { cx: o.x, cy: o.y, r: font * 0.8 }),
      svg('text', { x: o.x, y: o.y, 'font-size': font, 'text-anchor': 'middle', 'dominant-baseline': 'central' }, String(o.n)))));
    const typesOf = (it) => [(it.attributes || {}).ItemType, ...(it.children || []).flatMap(typesOf)];
    const types = [...new Set(typesOf(drawing).filter(Boolean))];
    return el('figure', { class: 'drawing' },
      svg('svg', { viewBox: `${b.x0 - m} ${b.y0 - m} ${w + 2 * m} ${h + 2 * m}`, preserveAspectRatio: 'xMidYMid meet',
                   role: 'img', 'aria-label': 'recipe drawing', 'data-testid': 'drawing-svg',
                   'data-primitives': prims.length },
        svg('defs', {}, svg('marker', { id: 'exec-arrow', viewBox: '0 0 10 10', refX: 5, refY: 5, markerWidth: 5,
                                       markerHeight: 5, orient: 'auto-start-reverse' },
                            svg('path', { d: 'M0 0L10 5L0 10z', class: 'exec-arrow' }))),
        tree(drawing), marks),
      el('figcaption', {},
        `${prims.length} primitives` + (types.length ? ` · ${types.join(', ')}` : '') +
        (order.length ? ` · worked in order ${order.map((o) => o.n).join(' → ')}` : ' · no ExecOrder')));
  }

  window.cellPanel.register({
    id: 'recipes', title: 'Recipes', minRole: 'service',
    mount(section, p) {
      panel = p;
      root = section;
      section.classList.add('page', 'recipes-page');
      const zprd = el('input', { type: 'file', accept: '.zprd,application/zip', class: 'hidden', testid: 'recipe-file',
                                 on: { change: (e) => { if (e.target.files[0]) upload('zprd', e.target.files[0]); e.target.value = ''; } } });
      const dxf = el('input', { type: 'file', accept: '.dxf', class: 'hidden', testid: 'dxf-file',
                                on: { change: (e) => { if (e.target.files[0]) upload('dxf', e.target.files[0]); e.target.value = ''; } } });
      section.append(
        el('div', { class: 'filters recipe-tools' },
          el('label', {}, 'name ', el('input', { class: 'upload-name', testid: 'upload-name', placeholder: 'from the file', maxLength: 128 })),
          el('label', {}, el('input', { type: 'checkbox', class: 'upload-replace' }), ' replace'),
          el('button', { class: 'small needs-service', testid: 'recipe-upload', text: 'Upload .zprd', on: { click: () => zprd.click() } }),
          el('button', { class: 'small needs-service', testid: 'dxf-import', text: 'Import DXF', on: { click: () => dxf.click() } }),
          zprd, dxf),
        el('div', { class: 'recipe-body' },
          el('div', { class: 'scroll recipe-table' },
            el('table', { class: 'log recipe-list', testid: 'recipe-list' },
              el('thead', {}, el('tr', {}, ['recipe', 'description', 'author', 'changed', 'size'].map((t) => el('th', { text: t })))),
              el('tbody')),
            el('p', { class: 'quiet no-recipes hidden', text: 'No recipes yet: upload one or import a DXF drawing.' })),
          el('div', { class: 'recipe-detail' })));
      detail();
    },
    show() { load(); },
  });
})();
