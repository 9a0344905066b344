// The Simulation page: a service user acts on the simulated router (its physics in the
// cell's node) and watches the cell react; an operator has no such page and cannot act.
import { test } from 'node:test';
import assert from 'node:assert/strict';
import { DemoCell, openPages, openPanel, login, logout, shot, call } from './demo_cell.mjs';

const cell = new DemoCell({ main: 'cell_web_router_demo:main()' });
let page;
openPages(cell, (p) => { page = p; });

test('an operator sees no Simulation page and cannot act on the machine', async () => {
  await openPanel(page, cell);
  await login(page, 'operator');
  await page.waitForSelector('[data-testid=tab-simulation]', { state: 'hidden' });
  const r = await call(page, 'POST', '/api/machine/actions', { action: 'estop', choice: 'press' });
  assert.equal(r.status, 403, JSON.stringify(r));
  assert.equal(r.code, 'forbidden');
  assert.equal((await call(page, 'GET', '/api/cell')).body.estop, false);
  await logout(page);
});

test('a service user presses the emergency stop and sees the cell stop', async () => {
  await login(page, 'service');
  await cell.cmd('start');
  await page.waitForSelector('#cell-state:not(:text-is("OFF"))');
  await page.click('[data-testid=tab-simulation]');
  await page.waitForSelector('[data-testid=sim-where]:has-text("cell\'s own node")');
  // The machine's actions, grouped, each position a button.
  for (const id of ['estop-press', 'estop-release', 'service_key-service', 'door_loading-open',
                    'air-drop', 'drive_lower-fault']) {
    await page.waitForSelector(`[data-testid=sim-${id}]`);
  }
  await shot(page, 'simulation-page', 'simulation');
  // It fits a 1024x768 touch panel, every button touch-sized.
  const size = await page.evaluate(() => ({
    width: document.documentElement.scrollWidth, height: document.documentElement.scrollHeight }));
  assert.ok(size.width <= 1024 && size.height <= 768, JSON.stringify(size));
  const small = await page.locator('#view-simulation button:visible').evaluateAll((bs) =>
    bs.map((b) => ({ text: b.textContent, ...b.getBoundingClientRect().toJSON() }))
      .filter((b) => b.height < 44 || b.width < 44));
  assert.deepEqual(small, []);
  await page.click('[data-testid=sim-estop-press]');
  // The cell reacts: its emergency stop, every task off, the banner on every page.
  await page.waitForSelector('[data-testid=sim-estop]:has-text("EMERGENCY STOP")');
  await page.waitForSelector('#estop-banner:not(.hidden)');
  await page.waitForSelector('#cell-state:text-is("OFF")');
  await shot(page, 'simulation-estop');
  const c = (await call(page, 'GET', '/api/cell')).body;
  assert.equal(c.estop, true, JSON.stringify(c));
  // Released: the emergency stop ends; the cell waits for Start.
  await page.click('[data-testid=sim-estop-release]');
  await page.waitForSelector('[data-testid=sim-estop]:has-text("no emergency stop")');
  await page.waitForSelector('#estop-banner.hidden', { state: 'attached' });
  // A door opened is a warning, shown beside the buttons; closed, it goes.
  await page.click('[data-testid=sim-door_loading-open]');
  await page.waitForSelector('.sim-alarm.warning[data-alarm="cell:door"]');
  await page.click('[data-testid=sim-door_loading-close]');
  await page.waitForSelector('.sim-alarm[data-alarm="cell:door"]', { state: 'detached' });
  // Each action is in the audit trail, in the operator's words.
  const audit = await call(page, 'GET', '/api/audit?limit=1000');
  const details = audit.body.entries.filter((e) => e.target === '/api/machine/actions' && e.who === 'service')
    .map((e) => e.detail);
  for (const d of ['Emergency stop: Press', 'Emergency stop: Release', 'Loading side door: Open']) {
    assert.ok(details.includes(d), `${d} in ${JSON.stringify(details)}`);
  }
  await logout(page);
});
