// The IO page (service): every IO group and point of the cell live (value, type,
// caption, unit, address, quality), grouped as the cell spec groups them; the PLC
// connections with their status and reconnections; the hardware objects (a camera's
// image grabbed on request, an axis's state and position and a channel's progress,
// live as they move). In service mode a service user forces an output or a simulated
// input and releases it; the server decides and records each one.
'use strict';
(() => {
  let panel, root, data = null, forced = new Set();
  const cells = new Map();      // "group.point" -> {value, quality, row}

  function html(tag, cls, text) {
    const e = document.createElement(tag);
    if (cls) e.className = cls;
    if (text !== undefined) e.textContent = text;
    return e;
  }
  const show = (v) => (v === null || v === undefined ? '—' : typeof v === 'number' && !Number.isInteger(v)
    ? String(Math.round(v * 1000) / 1000) : String(v));

  function mount(section, p) {
    panel = p;
    root = section;
    section.classList.add('io-page');
    section.append(html('div', 'io-conns'), html('div', 'io-hardware'), html('div', 'io-groups'));
    section.querySelector('.io-conns').dataset.testid = 'io-connections';
    panel.on('snapshot', (m) => { forced = keys(m.forces || []); if (data) load(); });
    panel.on('io', (m) => { for (const pt of m.points) update(pt); });
    panel.on('io_conn', (m) => {
      if (!data) return;
      const c = data.connections.find((x) => x.id === m.connection);
      if (c) { c.status = m.status; c.reconnects = m.reconnects; renderConns(); }
    });
    panel.on('hardware', (m) => { for (const h of m.hardware) updateHardware(h); });
    panel.on('forces', (m) => { forced = keys(m.forces); for (const k of cells.keys()) mark(k); });
    panel.on('cell', () => { for (const k of cells.keys()) mark(k); });
  }

  const keys = (forces) => new Set(forces.map((f) => `${f.group}.${f.point}`));

  async function load() {
    const got = await window.cellUi.attempt(panel, () => panel.api('GET', '/api/io'));
    if (!got) return;
    data = got;
    forced = keys(data.forces);
    renderConns();
    renderHardware();
    renderGroups();
  }

  function renderConns() {
    const box = root.querySelector('.io-conns');
    box.replaceChildren(...data.connections.map((c) => {
      const d = html('div', `conn ${c.status}`);
      d.dataset.connection = c.id;
      d.append(html('b', '', c.id), html('span', '', ` ${c.endpoint || ''} · ${c.status}`),
               html('span', 'quiet', ` · reconnects ${c.reconnects}` +
                                     (c.faults ? ` · ${c.faults} point(s) unusable` : '') +
                                     (c.status !== 'up' && c.reason ? ` · ${c.reason}` : '')));
      return d;
    }));
    if (data.connections.length === 0) box.append(html('p', 'quiet', 'This cell has no PLC connection.'));
  }

  function renderHardware() {
    const box = root.querySelector('.io-hardware');
    box.replaceChildren(...data.hardware.map((h) => {
      const d = html('div', `hw ${h.status}`);
      d.dataset.hardware = h.id;
      d.append(html('b', '', h.id), html('span', 'hw-status', ` ${h.kind} · ${h.status}`));
      // An axis or a channel as its NC has it, kept live by the 'hardware' messages.
      if (h.axis || h.channel) {
        const s = html('span', 'motion', motion(h));
        s.dataset.testid = `${h.axis ? 'axis' : 'channel'}-${h.id}`;
        d.append(s);
      }
      if (h.kind === 'camera') {
        const b = html('button', 'small', 'Grab image');
        b.dataset.testid = `grab-${h.id}`;
        const img = html('img', 'grab');
        img.alt = `image of ${h.id}`;
        b.addEventListener('click', () => grab(h.id, img, b));
        d.append(b, img);
      }
      return d;
    }));
  }

  function motion(h) {
    if (h.axis) {
      const a = h.axis;
      return ` · ${a.state.replace('_', ' ')} · ${show(a.position)} · ${show(a.velocity)}/s`
        + ` · override ${show(a.override)} %` + (a.error ? ` · error ${a.error}` : '')
        + (a.homed ? '' : ' · not homed');
    }
    if (h.channel) {
      const c = h.channel;
      return ` · ${c.state} · ${show(c.along)} of ${show(c.length)}`
        + ` · segment ${c.segment} of ${c.segments}`;
    }
    return '';
  }

  // An axis or a channel that changed: its line on the page, as /api/io would give it.
  function updateHardware(h) {
    if (!data) return;
    const i = data.hardware.findIndex((x) => x.id === h.id);
    if (i < 0) return;
    const kind = data.hardware[i].kind;
    data.hardware[i] = { ...h, kind };
    const d = root.querySelector(`[data-hardware="${CSS.escape(h.id)}"]`);
    if (!d) return;
    d.className = `hw ${h.status}`;
    d.querySelector('.hw-status').textContent = ` ${kind} · ${h.status}`;
    const s = d.querySelector('.motion');
    if (s && (h.axis || h.channel)) s.textContent = motion(h);
  }

  // The image is the answer of a GET the <img> makes itself (the panel's content
  // policy takes images from the cell only); a failed grab is shown as a toast.
  let grabs = 0;
  function grab(id, img, button) {
    button.disabled = true;
    img.dataset.loaded = 'false';
    img.onload = () => { img.dataset.loaded = 'true'; button.disabled = false; };
    img.onerror = () => {
      button.disabled = false;
      panel.toast(`The camera ${id} did not give an image; see the log.`);
    };
    img.src = `/api/io/hardware/${encodeURIComponent(id)}/image?grab=${++grabs}`;
  }

  function renderGroups() {
    const box = root.querySelector('.io-groups');
    cells.clear();
    box.replaceChildren(...data.groups.map((g) => {
      const sec = html('div', 'io-group');
      sec.dataset.group = g.id;
      sec.append(html('h2', '', `${g.id} · ${g.connection}`));
      const table = html('table', 'log io');
      table.innerHTML = '<thead><tr><th>point</th><th>caption</th><th>dir</th><th>type</th>' +
        '<th>value</th><th>unit</th><th>address</th><th>quality</th><th>force</th></tr></thead>';
      const body = html('tbody');
      for (const p of g.points) {
        const tr = html('tr');
        const key = `${g.id}.${p.point}`;
        tr.dataset.point = key;
        const value = html('td', 'value', show(p.value));
        const quality = html('td', 'quality', p.quality);
        const force = html('td', 'force');
        tr.append(html('td', 'name', p.point), html('td', '', p.caption), html('td', '', p.dir),
                  html('td', '', p.type), value, html('td', '', p.unit), html('td', 'address', p.address),
                  quality, force);
        cells.set(key, { p, value, quality, force, tr });
        body.append(tr);
        mark(key);
      }
      table.append(body);
      sec.append(table);
      return sec;
    }));
  }

  function update(pt) {
    const c = cells.get(`${pt.group}.${pt.point}`);
    if (!c) return;
    c.p.value = pt.value;
    c.p.quality = pt.quality;
    c.value.textContent = show(pt.value);
    c.quality.textContent = pt.quality;
    c.tr.classList.toggle('bad', pt.quality !== 'good');
  }

  // The forced mark on the row, and the force controls for who may use them now.
  function mark(key) {
    const c = cells.get(key);
    if (!c) return;
    const isForced = forced.has(key);
    c.tr.classList.toggle('forced', isForced);
    c.tr.dataset.forced = String(isForced);
    const s = panel.session();
    const may = panel.rank(s.role) >= panel.rank('service') && s.service && c.p.forceable;
    c.force.replaceChildren();
    if (isForced) c.force.append(html('span', 'forced-tag', 'FORCED'));
    if (!may) return;
    const [group, point] = [key.slice(0, key.indexOf('.')), key.slice(key.indexOf('.') + 1)];
    const act = (label, body, testid) => {
      const b = html('button', 'small', label);
      b.dataset.testid = testid;
      b.addEventListener('click', async () => {
        b.disabled = true;
        try {
          if (body === null) {
            await panel.api('DELETE', `/api/forces/${encodeURIComponent(group)}/${encodeURIComponent(point)}`);
          } else {
            await panel.api('POST', '/api/forces', { group, point, value: body() });
          }
        } catch (e) {
          panel.toast(e.message);
        } finally {
          b.disabled = false;
        }
      });
      return b;
    };
    if (c.p.type === 'BOOL') {
      c.force.append(act('1', () => true, `force-${key}-1`), act('0', () => false, `force-${key}-0`));
    } else {
      const input = html('input');
      input.size = 6;
      input.dataset.testid = `force-${key}-input`;
      const parse = () => (/^-?\d+(\.\d+)?([eE]-?\d+)?$/.test(input.value) ? Number(input.value) : input.value);
      c.force.append(input, act('Force', parse, `force-${key}-set`));
    }
    if (isForced) c.force.append(act('Release', null, `release-${key}`));
  }

  window.cellPanel.register({ id: 'io', title: 'IO', minRole: 'service', mount, show() { load(); } });
})();
