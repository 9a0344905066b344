// The operator panel. It renders a snapshot the cell sends over the websocket when
// the page connects, then applies every change the cell sends: it never polls. Commands
// and answers go to the REST API with the session's CSRF token.
'use strict';

const $ = (id) => document.getElementById(id);
const RANK = { anonymous: 0, operator: 1, service: 2, admin: 3 };
const SOLUTIONS = { retry: 'Retry', ignore: 'Ignore', reset: 'Reset', close: 'Close' };
const RECONNECT_MS = [500, 1000, 2000, 5000, 10000];
const LIVE_LINES = 500;

const model = {
  session: { user: null, role: 'anonymous', csrf: null, anonymous_view: true, demo_password: false },
  cell: null,
  tasks: new Map(),
  alarms: new Map(),
  log: [],
  plcMessages: [],
  forces: [],
  connected: false,
};
// Pages added by files of pages/ (see cellPanel.register), by id, in the order added.
const pages = new Map();
const listeners = new Map();
let socket = null;
let attempts = 0;
let logMode = { live: true, offset: 0, limit: 100, query: null };

// ---------------------------------------------------------------------------------
// REST

async function api(method, path, body) {
  const headers = { accept: 'application/json' };
  if (body !== undefined) headers['content-type'] = 'application/json';
  if (method !== 'GET' && model.session.csrf) headers['x-csrf-token'] = model.session.csrf;
  const res = await fetch(path, {
    method, headers, credentials: 'same-origin',
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  const data = await res.json().catch(() => ({ error: 'bad_answer', message: res.statusText }));
  if (!res.ok) {
    const err = new Error(data.message || res.statusText);
    err.status = res.status;
    err.code = data.error;
    err.field = data.field;   // the settings field a refused value is at
    throw err;
  }
  return data;
}

async function releaseAll() {
  try {
    await api('DELETE', '/api/forces');
  } catch (e) {
    toast(e.message);
  }
}

async function command(name) {
  try {
    await api('POST', `/api/cell/${name}`);
  } catch (e) {
    toast(e.message);
  }
}

async function answer(id, solution) {
  try {
    await api('POST', `/api/alarms/${encodeURIComponent(id)}/answer`, { solution });
  } catch (e) {
    toast(e.message);
  }
}

// An answer to a message of an inspection block's PLC: yes, no, or a text.
async function answerPlc(m, answer, text) {
  try {
    await api('POST', '/api/inspect/messages/answer',
      text === undefined ? { block: m.block, ref: m.ref, answer }
                         : { block: m.block, ref: m.ref, answer, text });
  } catch (e) {
    toast(e.message);
    renderPlcMessages();
  }
}

// ---------------------------------------------------------------------------------
// Live updates

function connect() {
  const scheme = location.protocol === 'https:' ? 'wss://' : 'ws://';
  socket = new WebSocket(scheme + location.host + '/api/ws');
  socket.onopen = () => { attempts = 0; setLink(true); };
  socket.onmessage = (ev) => { for (const msg of JSON.parse(ev.data)) apply(msg); };
  socket.onclose = (ev) => {
    socket = null;
    setLink(false);
    if (ev.code === 4001) {
      // The session ended (logout elsewhere, expiry, a changed password).
      loadSession().then(connect, later);
    } else {
      later();
    }
  };
}

// Connect again after a pause that grows, after asking who we are (a page that may no
// longer look without a login asks for one instead).
function later() {
  const delay = RECONNECT_MS[Math.min(attempts++, RECONNECT_MS.length - 1)];
  setTimeout(() => {
    loadSession().then(() => {
      if (!model.session.user && !model.session.anonymous_view) openLogin();
      else connect();
    }, later);
  }, delay);
}

function reconnect() {
  if (socket) {
    socket.onclose = null;
    socket.close();
    socket = null;
  }
  connect();
}

let snapshotSeen = false;

function apply(msg) {
  if (msg.type === 'snapshot') snapshotSeen = true;
  builtIn(msg);
  for (const fn of [...(listeners.get(msg.type) || [])]) {
    try { fn(msg); } catch (e) { console.error(e); }
  }
  for (const p of pages.values()) {
    if (!p.onEvent) continue;
    try { p.onEvent(msg); } catch (e) { console.error(e); }
  }
}

function builtIn(msg) {
  switch (msg.type) {
    case 'snapshot':
      model.cell = msg.cell;
      model.tasks = new Map(msg.tasks.map((t) => [t.id, t]));
      model.alarms = new Map(msg.alarms.map((a) => [a.id, a]));
      model.log = msg.log.slice(-LIVE_LINES);
      model.forces = msg.forces || [];
      renderAll();
      break;
    case 'forces':
      model.forces = msg.forces;
      renderForces();
      break;
    case 'cell':
      model.cell = msg.cell;
      renderCell();
      break;
    case 'task':
      model.tasks.set(msg.task.id, msg.task);
      renderTask(msg.task);
      break;
    case 'alarm':
      model.alarms.set(msg.alarm.id, msg.alarm);
      renderAlarms();
      break;
    case 'alarm_cleared':
      model.alarms.delete(msg.alarm.id);
      renderAlarms();
      break;
    case 'inspect_messages':
      model.plcMessages = msg.messages;
      renderPlcMessages();
      break;
    case 'log':
      model.log.push(msg.line);
      if (model.log.length > LIVE_LINES) model.log.shift();
      renderTicker();
      if (logMode.live) renderLogLines(liveLines());
      break;
    default:
      break;  // item events and the like: the task message that follows shows them
  }
}

// ---------------------------------------------------------------------------------
// Rendering

function stateClass(name) {
  const parts = (name || 'OFF').split('-');
  return 'state-' + parts[parts.length - 1];
}

function stateLabel(name) {
  return (name || 'OFF').replace('READY-', '');
}

function renderAll() {
  renderCell();
  renderLine();
  renderAlarms();
  renderTicker();
  renderTaskOptions();
  renderForces();
  if (logMode.live) renderLogLines(liveLines());
}

// While any point is forced a banner says so on every page, with Release all for
// those who may (the server decides; a refusal is shown as a toast).
function renderForces() {
  const n = model.forces.length;
  $('force-banner').classList.toggle('hidden', n === 0);
  $('force-text').textContent = n === 0 ? '' : `${n} IO point${n === 1 ? '' : 's'} forced: ` +
    model.forces.map((f) => `${f.group}.${f.point} = ${JSON.stringify(f.value)} (${f.who})`).join(', ');
  $('force-release-all').disabled = RANK[model.session.role] < RANK.service;
}

function renderCell() {
  const c = model.cell;
  if (!c) return;
  $('cell-name').textContent = c.name;
  document.title = `${c.name} — ${stateLabel(c.state)}`;
  const badge = $('cell-state');
  badge.className = 'badge ' + stateClass(c.state);
  badge.textContent = stateLabel(c.state);
  const request = `request: ${c.request}` + (c.service_mode ? ' · service mode' : '');
  $('cell-request').textContent = request;
  $('cell-request').title = request;   // the whole of it where the header cuts it short
  $('estop-banner').classList.toggle('hidden', !c.estop);
  renderCommands();
}

function renderLine() {
  const line = $('line');
  line.replaceChildren();
  if (model.tasks.size === 0) {
    const p = document.createElement('p');
    p.className = 'empty';
    p.textContent = 'This cell has no device tasks.';
    line.append(p);
    return;
  }
  for (const t of model.tasks.values()) line.append(taskTile(t));
  markErrors();
}

function taskTile(t) {
  const tile = document.createElement('div');
  tile.dataset.task = t.id;
  fillTile(tile, t);
  return tile;
}

function fillTile(tile, t) {
  tile.className = 'task ' + stateClass(t.state) + (t.running ? '' : ' gone');
  tile.dataset.state = t.state;
  tile.replaceChildren(
    taskName(t.id),
    div('where', `${t.zone} · ${t.lane}`),
    div('serial', t.serial ? t.serial : '—'),
    div('state', stateLabel(t.state)),
  );
  tile.querySelector('.serial').dataset.testid = 'serial';
  tile.querySelector('.state').dataset.testid = 'state';
}

// A task's name broken only where its words meet (after an underscore, a dash or a
// dot), never inside a word: "loading_<wbr>front".
function taskName(id) {
  const e = document.createElement('div');
  e.className = 'id';
  for (const part of String(id).split(/(?<=[_.-])/)) {
    if (e.childNodes.length) e.append(document.createElement('wbr'));
    e.append(part);
  }
  return e;
}

function renderTask(t) {
  const tile = $('line').querySelector(`[data-task="${CSS.escape(t.id)}"]`);
  if (tile) fillTile(tile, t);
  else renderLine();
  markErrors();
}

function markErrors() {
  const withError = new Set([...model.alarms.values()].filter((a) => a.kind === 'error').map((a) => a.task));
  for (const tile of $('line').querySelectorAll('.task')) {
    tile.classList.toggle('has-error', withError.has(tile.dataset.task));
  }
}

function renderAlarms() {
  const box = $('alarms');
  box.replaceChildren();
  const order = { alarm: 0, error: 1, warning: 2 };
  const list = [...model.alarms.values()].sort((a, b) =>
    order[a.kind] - order[b.kind] || a.raised - b.raised);
  const may = RANK[model.session.role] >= RANK.operator;
  for (const a of list) {
    const item = document.createElement('div');
    item.className = 'alarm ' + (a.kind === 'alarm' ? 'alarm-kind' : a.kind);
    item.dataset.alarm = a.id;
    item.dataset.kind = a.kind;
    const head = document.createElement('div');
    head.className = 'head';
    head.append(span('caption', a.caption), span('who', `${a.kind} · ${a.task} · ${time(a.raised)}`));
    item.append(head, div('description', a.description));
    if (a.kind === 'alarm') {
      item.append(div('note', 'Clears by itself when its cause is gone.'));
    } else {
      const buttons = document.createElement('div');
      buttons.className = 'solutions';
      for (const s of a.solutions) {
        const b = document.createElement('button');
        b.textContent = SOLUTIONS[s] || s;
        b.dataset.solution = s;
        b.disabled = !may;
        b.addEventListener('click', () => { b.disabled = true; answer(a.id, s); });
        buttons.append(b);
      }
      item.append(buttons);
    }
    box.append(item);
  }
  $('no-alarms').classList.toggle('hidden', list.length > 0);
  markErrors();
}

// The PLC's messages: Yes / No, OK, or a text (a number, a password) with OK and
// Cancel, as the message asks. Answering needs an operator.
function renderPlcMessages() {
  const box = $('plc-messages');
  box.replaceChildren();
  const may = RANK[model.session.role] >= RANK.operator;
  for (const m of model.plcMessages) {
    const item = document.createElement('div');
    item.className = 'plc-message';
    item.dataset.block = m.block;
    item.dataset.ref = m.ref;
    item.dataset.kind = m.kind;
    const head = document.createElement('div');
    head.className = 'head';
    head.append(span('caption', m.text), span('who', `${m.block} · message ${m.id} · ${time(m.since)}`));
    item.append(head);
    const buttons = document.createElement('div');
    buttons.className = 'solutions';
    const button = (label, answer, input) => {
      const b = document.createElement('button');
      b.textContent = label;
      b.dataset.answer = answer;
      b.disabled = !may;
      b.addEventListener('click', () => {
        for (const x of buttons.querySelectorAll('button')) x.disabled = true;
        answerPlc(m, answer, input ? input.value : undefined);
      });
      return b;
    };
    if (m.kind === 'yes_no') {
      buttons.append(button('Yes', 'yes'), button('No', 'no'));
    } else if (m.kind === 'ok') {
      buttons.append(button('OK', 'yes'));
    } else {
      const input = document.createElement('input');
      input.type = m.kind === 'password' ? 'password' : m.kind === 'number' ? 'number' : 'text';
      input.maxLength = m.max_length;
      input.disabled = !may;
      input.dataset.testid = 'plc-answer-text';
      buttons.append(input, button('OK', 'text', input), button('Cancel', 'no'));
    }
    item.append(buttons);
    box.append(item);
  }
  $('plc-messages-box').classList.toggle('hidden', model.plcMessages.length === 0);
}

function renderTicker() {
  const box = $('ticker');
  box.replaceChildren(...model.log.slice(-4).reverse().map((l) =>
    div(l.level, `${time(l.time)}  ${l.source}: ${l.text}`)));
}

function renderCommands() {
  const may = RANK[model.session.role] >= RANK.operator && model.connected;
  const estop = model.cell && model.cell.estop;
  $('cmd-start').disabled = !may || estop;
  $('cmd-pause').disabled = !may;
  $('cmd-stop').disabled = !may;
  $('cmd-hint').textContent = !model.session.user ? 'Log in to operate the cell.'
    : !may ? (model.connected ? 'Your role may only watch.' : 'Waiting for the cell…') : '';
}

function renderSession() {
  const s = model.session;
  $('user-button').textContent = s.user ? `${s.user} (${s.role})` : 'Log in';
  $('demo-banner').classList.toggle('hidden', !s.demo_password);
  renderCommands();
  renderAlarms();
  renderPlcMessages();
  renderForces();
  const admin = RANK[s.role] >= RANK.admin;
  $('tab-users').classList.toggle('hidden', !admin);
  if (!admin && !$('view-users').classList.contains('hidden')) show('line');
  for (const p of pages.values()) {
    const may = RANK[s.role] >= RANK[p.minRole];
    $(`tab-${p.id}`).classList.toggle('hidden', !may);
    if (!may && current === p.id) show('line');
  }
}

function setLink(up) {
  model.connected = up;
  const link = $('link');
  link.classList.toggle('up', up);
  link.textContent = up ? 'live' : 'reconnecting…';
  renderCommands();
}

// ---------------------------------------------------------------------------------
// The log page

function liveLines() {
  const levels = checkedLevels();
  const task = $('log-task').value;
  return model.log.filter((l) => levels.includes(l.level) && (!task || l.source === task)).reverse();
}

function checkedLevels() {
  return [...document.querySelectorAll('input[name=level]:checked')].map((i) => i.value);
}

function renderLogLines(lines) {
  $('log-lines').replaceChildren(...lines.map((l) => {
    const tr = document.createElement('tr');
    tr.className = l.level;
    tr.append(td('time', time(l.time, true)), td('level', l.level), td('source', l.source),
              td('text', l.text));
    return tr;
  }));
}

function renderTaskOptions() {
  const select = $('log-task');
  const keep = select.value;
  const names = ['cell', ...model.tasks.keys()];
  select.replaceChildren(option('', 'all'), ...names.map((n) => option(n, n)));
  select.value = names.includes(keep) ? keep : '';
}

async function searchLog(offset) {
  const params = new URLSearchParams();
  const levels = checkedLevels();
  if (levels.length === 0) return renderLogLines([]);
  params.set('level', levels.join(','));
  if ($('log-task').value) params.set('task', $('log-task').value);
  if ($('log-from').value) params.set('from', String(new Date($('log-from').value).getTime()));
  if ($('log-to').value) params.set('to', String(new Date($('log-to').value).getTime()));
  params.set('limit', String(logMode.limit));
  params.set('offset', String(offset));
  try {
    const page = await api('GET', `/api/log?${params}`);
    logMode = { ...logMode, live: false, offset, more: page.more };
    renderLogLines(page.lines);
    $('pager').classList.remove('hidden');
    $('log-range').textContent = page.lines.length
      ? `lines ${offset + 1}–${offset + page.lines.length}` : 'no lines';
    $('log-prev').disabled = offset === 0;
    $('log-next').disabled = !page.more;
  } catch (e) {
    toast(e.message);
  }
}

function liveLog() {
  logMode = { ...logMode, live: true, offset: 0 };
  $('pager').classList.add('hidden');
  renderLogLines(liveLines());
}

// ---------------------------------------------------------------------------------
// Session and dialogs

async function loadSession() {
  model.session = await api('GET', '/api/session');
  renderSession();
}

function openLogin() {
  $('login-error').textContent = '';
  $('login-dialog').showModal();
  $('login-user').focus();
}

async function login(ev) {
  ev.preventDefault();
  try {
    model.session = await api('POST', '/api/session',
      { user: $('login-user').value, password: $('login-password').value });
    $('login-password').value = '';
    $('login-dialog').close();
    renderSession();
    reconnect();
  } catch (e) {
    $('login-error').textContent = e.message;
  }
}

async function logout() {
  try {
    model.session = await api('DELETE', '/api/session');
  } catch (e) {
    toast(e.message);
  }
  $('account-dialog').close();
  renderSession();
  if (model.session.anonymous_view) reconnect();
  else openLogin();
}

async function changePassword(ev) {
  ev.preventDefault();
  try {
    model.session = await api('POST', '/api/session/password',
      { old: $('pw-old').value, new: $('pw-new').value });
    $('pw-old').value = '';
    $('pw-new').value = '';
    $('account-dialog').close();
    renderSession();
    reconnect();
    toast('Password changed.');
  } catch (e) {
    $('pw-error').textContent = e.message;
  }
}

let toastTimer = null;
function toast(text) {
  const t = $('toast');
  t.textContent = text;
  t.classList.remove('hidden');
  clearTimeout(toastTimer);
  toastTimer = setTimeout(() => t.classList.add('hidden'), 5000);
}

// ---------------------------------------------------------------------------------
// Users (admins)

async function loadUsers() {
  try {
    renderUsers(await api('GET', '/api/users'));
  } catch (e) {
    toast(e.message);
  }
}

function renderUsers(users) {
  const body = $('users');
  body.replaceChildren();
  for (const u of users) {
    const tr = document.createElement('tr');
    tr.dataset.user = u.name;
    const remove = document.createElement('button');
    remove.className = 'small';
    remove.textContent = 'Remove';
    remove.dataset.testid = `remove-${u.name}`;
    remove.addEventListener('click', () => removeUser(u.name));
    const edit = td('', '');
    edit.append(remove);
    tr.append(td('name', u.name), td('role', u.role), edit);
    tr.addEventListener('click', (ev) => {
      if (ev.target === remove) return;
      $('user-name').value = u.name;
      $('user-role').value = u.role;
      $('user-password').value = '';
    });
    body.append(tr);
  }
}

async function saveUser(ev) {
  ev.preventDefault();
  const name = $('user-name').value;
  const body = { role: $('user-role').value };
  if ($('user-password').value) body.password = $('user-password').value;
  try {
    renderUsers(await api('PUT', `/api/users/${encodeURIComponent(name)}`, body));
    $('user-password').value = '';
    toast(`User ${name} saved.`);
    if (name === model.session.user) await loadSession();
  } catch (e) {
    toast(e.message);
  }
}

async function removeUser(name) {
  if (!window.confirm(`Remove the user ${name}?`)) return;
  try {
    renderUsers(await api('DELETE', `/api/users/${encodeURIComponent(name)}`));
    toast(`User ${name} removed.`);
  } catch (e) {
    toast(e.message);
  }
}

// ---------------------------------------------------------------------------------
// Small DOM helpers

function div(cls, text) { const e = document.createElement('div'); e.className = cls; e.textContent = text; return e; }
function span(cls, text) { const e = document.createElement('span'); e.className = cls; e.textContent = text; return e; }
function td(cls, text) { const e = document.createElement('td'); e.className = cls; e.textContent = text; return e; }
function option(value, text) { const e = document.createElement('option'); e.value = value; e.textContent = text; return e; }

function time(ms, full) {
  const d = new Date(ms);
  const pad = (n, w = 2) => String(n).padStart(w, '0');
  const hms = `${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
  return full ? `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ${hms}.${pad(d.getMilliseconds(), 3)}` : hms;
}

// ---------------------------------------------------------------------------------
// Start

let current = 'line';

function show(view) {
  const was = current;
  current = view;
  for (const v of ['line', 'log', 'users', ...pages.keys()]) {
    $(`view-${v}`).classList.toggle('hidden', v !== view);
    $(`tab-${v}`).classList.toggle('active', v === view);
  }
  // A tab chosen other than by a touch (a role's page left) is brought into the row's view.
  $(`tab-${view}`).scrollIntoView({ block: 'nearest', inline: 'nearest' });
  if (was !== view && pages.has(was) && pages.get(was).hide) pages.get(was).hide();
  if (was !== view && pages.has(view) && pages.get(view).show) pages.get(view).show();
}

// ---------------------------------------------------------------------------------
// Pages of their own (pages/<id>.js): the contract they are written against.

function register(page) {
  if (!page || !page.id || pages.has(page.id) || ['line', 'log', 'users'].includes(page.id)) {
    throw new Error(`cannot register the page ${page && page.id}`);
  }
  const p = { minRole: 'anonymous', ...page };
  if (!(p.minRole in RANK)) throw new Error(`page ${p.id}: unknown role ${p.minRole}`);
  const tab = document.createElement('button');
  tab.className = 'tab';
  tab.dataset.view = p.id;
  tab.id = `tab-${p.id}`;
  tab.dataset.testid = `tab-${p.id}`;
  tab.textContent = p.title;
  tab.classList.toggle('hidden', RANK[model.session.role] < RANK[p.minRole]);
  tab.addEventListener('click', () => show(p.id));
  document.querySelector('nav.tabs').append(tab);
  const section = document.createElement('section');
  section.className = 'view hidden';
  section.id = `view-${p.id}`;
  document.querySelector('main').append(section);
  pages.set(p.id, p);
  p.mount(section, window.cellPanel);
}

// A snapshot listener added after the snapshot came (a page's script run late) gets
// one made of what the page holds now, so no page waits for the next resync.
function on(type, fn) {
  if (!listeners.has(type)) listeners.set(type, new Set());
  listeners.get(type).add(fn);
  if (type === 'snapshot' && snapshotSeen) {
    queueMicrotask(() => fn({
      type: 'snapshot', resync: false, cell: model.cell, tasks: [...model.tasks.values()],
      alarms: [...model.alarms.values()], log: [...model.log], forces: model.forces,
    }));
  }
  return () => listeners.get(type).delete(fn);
}

window.cellPanel = {
  api,
  register,
  session: () => ({ user: model.session.user, role: model.session.role,
                    csrf: model.session.csrf,
                    service: !!(model.cell && model.cell.service_mode) }),
  on,
  toast,
  rank: (role) => RANK[role] ?? 0,
};

function wire() {
  $('cmd-start').addEventListener('click', () => command('start'));
  $('cmd-pause').addEventListener('click', () => command('pause'));
  $('cmd-stop').addEventListener('click', () => command('stop'));
  $('force-release-all').addEventListener('click', releaseAll);
  $('tab-line').addEventListener('click', () => show('line'));
  $('tab-log').addEventListener('click', () => show('log'));
  $('tab-users').addEventListener('click', () => { show('users'); loadUsers(); });
  $('user-form').addEventListener('submit', saveUser);
  $('user-button').addEventListener('click', () => {
    if (model.session.user) {
      $('account-title').textContent = `${model.session.user} (${model.session.role})`;
      $('pw-error').textContent = '';
      $('account-dialog').showModal();
    } else {
      openLogin();
    }
  });
  $('login-form').addEventListener('submit', login);
  $('login-cancel').addEventListener('click', () => $('login-dialog').close());
  $('password-form').addEventListener('submit', changePassword);
  $('logout').addEventListener('click', logout);
  $('account-close').addEventListener('click', () => $('account-dialog').close());
  $('log-form').addEventListener('submit', (ev) => { ev.preventDefault(); searchLog(0); });
  $('log-live').addEventListener('click', liveLog);
  $('log-prev').addEventListener('click', () => searchLog(Math.max(0, logMode.offset - logMode.limit)));
  $('log-next').addEventListener('click', () => searchLog(logMode.offset + logMode.limit));
  for (const input of document.querySelectorAll('input[name=level]')) {
    input.addEventListener('change', () => { if (logMode.live) liveLog(); });
  }
  $('log-task').addEventListener('change', () => { if (logMode.live) liveLog(); });
}

wire();
loadSession().then(() => {
  if (!model.session.user && !model.session.anonymous_view) openLogin();
  else connect();
}, later);
