// The Simulation page (service): the operator's hand on a simulated machine. The cell
// lists what its simulation lets one do (GET /api/machine/actions: press the emergency
// stop, turn the service key, open a door, drop the air, fault a drive ...), grouped as
// the cell groups them, one touch-size button per position; a button carries it out
// where the machine's physics runs (the cell's VM, or the virtual PLC's process). The
// cell's reaction shows live beside them: its state, emergency stop, service mode and
// the alarms, as the websocket brings them. A machine with a real PLC has none.
'use strict';
(() => {
  const { el } = window.cellUi;
  let panel, root, data = null;
  const alarms = new Map();
  let cell = null;

  function mount(section, p) {
    panel = p;
    root = section;
    section.classList.add('page', 'simulation-page');
    section.append(el('div', { class: 'sim-status', testid: 'sim-status' }),
                   el('p', { class: 'note sim-where', testid: 'sim-where' }),
                   el('div', { class: 'sim-groups scroll' }));
    panel.on('snapshot', (m) => {
      cell = m.cell;
      alarms.clear();
      for (const a of m.alarms) alarms.set(a.id, a);
      status();
    });
    panel.on('cell', (m) => { cell = m.cell; status(); });
    panel.on('alarm', (m) => { alarms.set(m.alarm.id, m.alarm); status(); });
    panel.on('alarm_cleared', (m) => { alarms.delete(m.alarm.id); status(); });
  }

  async function load() {
    const got = await window.cellUi.attempt(panel, () => panel.api('GET', '/api/machine/actions'));
    if (!got) return;
    data = got;
    render();
  }

  // The cell's reaction: what the operator watches while acting on the machine.
  function status() {
    if (!root) return;
    const box = root.querySelector('.sim-status');
    const items = [];
    if (cell) {
      items.push(el('span', { class: 'sim-flag', testid: 'sim-state' }, `Cell: ${cell.state}`),
                 el('span', { class: `sim-flag ${cell.estop ? 'on estop' : ''}`, testid: 'sim-estop' },
                    cell.estop ? 'EMERGENCY STOP' : 'no emergency stop'),
                 el('span', { class: `sim-flag ${cell.service_mode ? 'on' : ''}`, testid: 'sim-service' },
                    cell.service_mode ? 'service mode' : 'production mode'));
    }
    const order = { alarm: 0, error: 1, warning: 2 };
    const list = [...alarms.values()].sort((a, b) => (order[a.kind] ?? 3) - (order[b.kind] ?? 3));
    box.replaceChildren(...items, ...list.map((a) =>
      el('span', { class: `sim-alarm ${a.kind}`, data: { alarm: a.id } }, `${a.kind}: ${a.caption}`)));
  }

  function render() {
    const where = root.querySelector('.sim-where');
    where.textContent = data.where.kind === 'local'
      ? "The machine's physics runs in the cell's own node (simulation mode)."
      : data.where.kind === 'vplc'
        ? `The machine's physics runs in the virtual PLC (${data.where.node}); the cell talks to it over Modbus TCP.`
        : 'This machine has a real PLC: there is nothing simulated to act on.';
    if (data.where.kind !== 'none' && data.actions.length === 0) {
      where.textContent += ' Its cell lists no actions on the machine.';
    }
    const groups = new Map();
    for (const a of data.actions) {
      if (!groups.has(a.group)) groups.set(a.group, []);
      groups.get(a.group).push(a);
    }
    root.querySelector('.sim-groups').replaceChildren(...[...groups].map(([name, actions]) =>
      el('div', { class: 'sim-group', data: { group: name } },
         el('h2', { text: name }),
         actions.map((a) => el('div', { class: 'sim-action', data: { action: a.id } },
                               el('span', { class: 'caption', text: a.caption }),
                               a.choices.map((c) => button(a, c)))))));
  }

  function button(a, c) {
    const b = el('button', { class: `sim-button ${a.id === 'estop' && c.id === 'press' ? 'danger' : ''}`,
                             testid: `sim-${a.id}-${c.id}` }, c.caption);
    b.addEventListener('click', async () => {
      b.disabled = true;
      try {
        await panel.api('POST', '/api/machine/actions', { action: a.id, choice: c.id });
      } catch (e) {
        panel.toast(e.message);
      } finally {
        b.disabled = false;
      }
    });
    return b;
  }

  window.cellPanel.register({ id: 'simulation', title: 'Simulation', minRole: 'service', mount,
                              show() { status(); load(); } });
})();
