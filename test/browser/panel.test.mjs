// End-to-end tests of the operator panel: a cell of scripted tasks (the Erlang module
// cell_web_demo, driven through its standard input) and the page in Debian's headless
// chromium. Every wait has a deadline; nothing sleeps. Screenshots go to artifacts/.
import { test } from 'node:test';
import assert from 'node:assert/strict';
import { join } from 'node:path';
import { DemoCell, openPages, artifacts } from './demo_cell.mjs';

const cell = new DemoCell({ root: process.env.CELLRT_BROWSER_ROOT });
let page;
openPages(cell, (p) => { page = p; });

const tile = (id) => page.locator(`[data-task="${id}"]`);
const shot = (name) => page.screenshot({ path: join(artifacts, `${name}.png`) });

async function login(user, password) {
  await page.click('#user-button');
  await page.fill('#login-user', user);
  await page.fill('#login-password', password);
  await page.click('#login-submit');
}

async function expectState(id, state) {
  await page.waitForSelector(`[data-task="${id}"][data-state="${state}"]`);
}

// ---------------------------------------------------------------------------------

test('anyone sees the line without logging in, but cannot operate', async () => {
  await page.goto(cell.url);
  for (const id of ['loader', 'router', 'unloader']) await expectState(id, 'OFF');
  await page.waitForSelector('#link.up');
  assert.equal(await page.textContent('#cell-name'), 'Demo router');
  assert.equal(await page.textContent('[data-testid=cell-state]'), 'OFF');
  for (const c of ['start', 'pause', 'stop']) {
    assert.equal(await page.isDisabled(`[data-testid=cmd-${c}]`), true, c);
  }
  await shot('01-anonymous');
});

test('a wrong password is refused and says so', async () => {
  await login('operator', 'not-the-password');
  await page.waitForSelector('[data-testid=login-error]:has-text("wrong user name or password")');
  await page.click('#login-cancel');
  assert.equal(await page.textContent('#user-button'), 'Log in');
});

test('an operator logs in, starts the cell and watches the states change live', async () => {
  await login('operator', 'operator');
  await page.waitForSelector('#user-button:has-text("operator (operator)")');
  await page.waitForSelector('[data-testid=demo-banner]:visible');
  await page.waitForSelector('[data-testid=cmd-start]:enabled');
  await page.click('[data-testid=cmd-start]');
  for (const id of ['loader', 'router', 'unloader']) await expectState(id, 'READY-IDLE-STARVED');
  await cell.cmd('event router unstarved');
  await expectState('router', 'READY-PROCESSING-ACTIVE');
  await cell.cmd('product router P-1001');
  await cell.cmd('event router work_start');
  await expectState('router', 'READY-PROCESSING-EXECUTING');
  await page.waitForSelector('[data-task="router"] [data-testid=serial]:has-text("P-1001")');
  await page.waitForSelector('[data-testid=cell-state]:has-text("PROCESSING-EXECUTING")');
  // IPC-2541 colours: EXECUTING green, STARVED yellow.
  const bg = (id) => tile(id).evaluate((e) => getComputedStyle(e).backgroundColor);
  assert.equal(await bg('router'), 'rgb(30, 158, 58)');
  assert.equal(await bg('loader'), 'rgb(242, 201, 76)');
  await shot('02-running');
});

test('the page never polls: changes arrive over the websocket only', async () => {
  const requests = [];
  const seen = (r) => requests.push(r.url());
  page.on('request', seen);
  await cell.cmd('event loader unstarved');
  await expectState('loader', 'READY-PROCESSING-ACTIVE');
  await cell.cmd('product loader P-1002');
  await page.waitForSelector('[data-task="loader"] [data-testid=serial]:has-text("P-1002")');
  await cell.cmd('log loader board P-1002 clamped');
  await page.waitForSelector('[data-testid=ticker]:has-text("board P-1002 clamped")');
  page.off('request', seen);
  assert.deepEqual(requests, []);
});

test('an injected error offers only its own solutions, and Retry answers it', async () => {
  await cell.cmd('error router retry,reset');
  const item = page.locator('[data-kind=error]');
  await item.waitFor();
  await expectState('router', 'DOWN');
  await page.waitForSelector('[data-task="router"].has-error');
  assert.match(await item.textContent(), /Board jammed/);
  assert.deepEqual(await item.locator('button').allTextContents(), ['Retry', 'Reset']);
  assert.equal(await page.textContent('[data-testid=cell-state]'), 'PROCESSING-ACTIVE');
  await shot('03-error');
  await item.locator('button[data-solution=retry]').click();
  await item.waitFor({ state: 'detached' });
  await expectState('router', 'READY-PROCESSING-EXECUTING');
  const history = await page.evaluate(() => fetch('/api/alarms/history').then((r) => r.json()));
  assert.equal(history[0].what, 'retry');
  assert.equal(history[0].who, 'operator');
});

test('a warning is closed with its only button, Close', async () => {
  await cell.cmd('warning unloader low_boxes Boxes running low');
  const item = page.locator('[data-kind=warning]');
  await item.waitFor();
  assert.deepEqual(await item.locator('button').allTextContents(), ['Close']);
  await expectState('unloader', 'READY-IDLE-STARVED');   // a warning does not stop the task
  await shot('04-warning');
  await item.locator('button').click();
  await item.waitFor({ state: 'detached' });
  await page.waitForSelector('#no-alarms:visible');
});

test('the log page shows lines live, filters them, and searches the files', async () => {
  await page.click('#tab-log');
  await cell.cmd('log router cut 4 of 12 done');
  const row = page.locator('[data-testid=log-lines] tr', { hasText: 'cut 4 of 12 done' });
  await row.waitFor();
  await page.uncheck('input[name=level][value=brief]');
  await row.waitFor({ state: 'detached' });
  await page.check('input[name=level][value=brief]');
  await row.waitFor();
  await page.selectOption('#log-task', 'router');
  await page.click('[data-testid=log-search]');
  await page.waitForSelector('#pager:visible');
  await row.waitFor();
  const sources = await page.locator('[data-testid=log-lines] td.source').allTextContents();
  assert.ok(sources.length > 0 && sources.every((s) => s === 'router'), sources.join());
  await shot('05-log');
  await page.click('[data-testid=log-live]');
  await page.click('#tab-line');
});

test('Pause holds every task in DOWN, Stop takes them to OFF', async () => {
  await page.click('[data-testid=cmd-pause]');
  for (const id of ['loader', 'router', 'unloader']) await expectState(id, 'DOWN');
  await page.click('[data-testid=cmd-stop]');
  for (const id of ['loader', 'router', 'unloader']) await expectState(id, 'OFF');
  await page.waitForSelector('[data-testid=cell-state]:has-text("OFF")');
  await shot('06-stopped');
});

test('fits a 1024x768 touch panel with touch-sized buttons', async () => {
  const size = await page.evaluate(() => ({
    width: document.documentElement.scrollWidth, height: document.documentElement.scrollHeight,
  }));
  assert.ok(size.width <= 1024 && size.height <= 768, JSON.stringify(size));
  for (const c of ['start', 'pause', 'stop']) {
    const box = await page.locator(`[data-testid=cmd-${c}]`).boundingBox();
    assert.ok(box.height >= 80 && box.width >= 160, `${c}: ${JSON.stringify(box)}`);
  }
  const user = await page.locator('#user-button').boundingBox();
  assert.ok(user.height >= 48, JSON.stringify(user));
});

test('logging out ends the session: the panel is read-only again', async () => {
  await page.click('#user-button');
  await page.click('[data-testid=logout]');
  await page.waitForSelector('#user-button:has-text("Log in")');
  await page.waitForSelector('[data-testid=cmd-start]:disabled');
  const status = await page.evaluate(() =>
    fetch('/api/cell/start', { method: 'POST' }).then((r) => r.status));
  assert.equal(status, 401);
});

test('an admin manages the users on the Users page; others do not see it', async () => {
  await page.waitForSelector('[data-testid=tab-users]', { state: 'hidden' });
  await login('admin', 'admin');
  await page.waitForSelector('#user-button:has-text("admin (admin)")');
  await page.click('[data-testid=tab-users]');
  await page.waitForSelector('[data-testid=users] tr[data-user="operator"] td.role:has-text("operator")');
  // A new user, with a role and a password.
  await page.fill('#user-name', 'line-lead');
  await page.selectOption('#user-role', 'service');
  await page.fill('#user-password', 'lead-password');
  await page.click('[data-testid=user-save]');
  await page.waitForSelector('tr[data-user="line-lead"] td.role:has-text("service")');
  const session = (password) => fetch(new URL('api/session', cell.url), {
    method: 'POST', headers: { 'content-type': 'application/json', origin: cell.url.slice(0, -1) },
    body: JSON.stringify({ user: 'line-lead', password }),
  }).then((r) => r.status);
  assert.equal(await session('lead-password'), 200);
  // Its role changed from its row, the password left as it is.
  await page.click('tr[data-user="line-lead"] td.name');
  assert.equal(await page.inputValue('#user-name'), 'line-lead');
  await page.selectOption('#user-role', 'operator');
  await page.click('[data-testid=user-save]');
  await page.waitForSelector('tr[data-user="line-lead"] td.role:has-text("operator")');
  assert.equal(await session('lead-password'), 200);
  // A new user without a password is refused, and the operator is told why.
  await page.fill('#user-name', 'no-password');
  await page.fill('#user-password', '');
  await page.click('[data-testid=user-save]');
  await page.waitForSelector('[data-testid=toast]:has-text("needs a role and a password")');
  assert.equal(await page.locator('tr[data-user="no-password"]').count(), 0);
  await shot('07-users');
  // Removed after a confirmation; it cannot log in any more.
  page.once('dialog', (d) => d.accept());
  await page.click('[data-testid=remove-line-lead]');
  await page.waitForSelector('tr[data-user="line-lead"]', { state: 'detached' });
  assert.equal(await session('lead-password'), 401);
  // Logged out, the page goes back to the line and hides the tab.
  await page.click('#user-button');
  await page.click('[data-testid=logout]');
  await page.waitForSelector('[data-testid=tab-users]', { state: 'hidden' });
  await page.waitForSelector('#view-line:not(.hidden)');
});
