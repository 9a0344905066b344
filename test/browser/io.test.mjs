// The IO page and forcing: every point live, who may force and when, a forced point
// marked on every page with a banner, forces audited and ended by an emergency stop,
// the end of service mode and the logout of whoever set them.
import { test } from 'node:test';
import assert from 'node:assert/strict';
import { DemoCell, openPages, login, logout, shot, call } from './demo_cell.mjs';

const cell = new DemoCell();
let page;
openPages(cell, (p) => { page = p; });

const row = (key) => page.locator(`tr[data-point="${key}"]`);

async function audit() {
  const r = await call(page, 'GET', '/api/audit?limit=1000');
  assert.equal(r.status, 200, JSON.stringify(r));
  return r.body.entries;
}

test('an operator sees no IO page and cannot force', async () => {
  await page.goto(cell.url);
  await page.waitForSelector('#link.up');
  await login(page, 'operator', 'operator');
  await page.waitForSelector('[data-testid=tab-io]', { state: 'hidden' });
  await cell.cmd('service on');
  const r = await call(page, 'POST', '/api/forces',
                       { group: 'line', point: 'conveyor_motor', value: true });
  assert.equal(r.status, 403, JSON.stringify(r));
  assert.equal(r.code, 'forbidden');
  assert.deepEqual((await call(page, 'GET', '/api/forces')).body, []);
  await cell.cmd('service off');
  await logout(page);
});

test('the IO page shows every point live, its connection, its camera and its axis', async () => {
  await login(page, 'service', 'service');
  await page.click('[data-testid=tab-io]');
  await page.waitForSelector('[data-connection="demo_plc"]:has-text("up")');
  const pressure = row('general.air_pressure');
  await pressure.waitFor();
  assert.deepEqual(await pressure.locator('td').evaluateAll((tds) => tds.slice(0, 8).map((t) => t.textContent)),
                   ['air_pressure', 'Air pressure', 'in', 'REAL', '0', 'bar', 'A1.30.01', 'good']);
  // A value set on the simulated PLC arrives without the page asking.
  const requests = [];
  const seen = (r) => requests.push(r.url());
  page.on('request', seen);
  await cell.cmd('sim general air_pressure 6.5');
  await page.waitForSelector('tr[data-point="general.air_pressure"] td.value:text-is("6.5")');
  page.off('request', seen);
  assert.deepEqual(requests, []);
  // Out of service mode nothing offers to force.
  assert.equal(await row('line.conveyor_motor').locator('td.force button').count(), 0);
  await page.click('[data-testid=grab-camera]');
  await page.waitForSelector('[data-hardware=camera] img[data-loaded=true]');
  const size = await page.locator('[data-hardware=camera] img').evaluate((i) => [i.naturalWidth, i.naturalHeight]);
  assert.deepEqual(size, [64, 48]);
  // The axis as its NC has it: PLCopen's state, where it stands, not homed yet.
  const axis = await page.locator('[data-testid=axis-gantry_x]').textContent();
  assert.match(axis, /disabled · 25 · 0\/s · override \d+ % · not homed/);
  // It moves, and the page follows without asking: powered, homed, on its way, there.
  page.on('request', seen);
  await cell.cmd('axis gantry_x power');
  await cell.cmd('axis gantry_x home 0');
  await page.waitForSelector('[data-testid=axis-gantry_x]:text-matches("standstill · 0 · 0/s · override [0-9]+ %$")');
  await cell.cmd('axis gantry_x move 40 20');
  await page.waitForSelector('[data-testid=axis-gantry_x]:text("discrete motion")');
  await page.waitForSelector('[data-testid=axis-gantry_x]:text-matches("standstill · 40 · 0/s")');
  page.off('request', seen);
  assert.deepEqual(requests, []);
});

test('forcing needs service mode; a real refusal names why', async () => {
  let r = await call(page, 'POST', '/api/forces', { group: 'line', point: 'conveyor_motor', value: true });
  assert.equal(r.status, 409);
  assert.equal(r.code, 'not_service_mode');
  await cell.cmd('service on');
  r = await call(page, 'POST', '/api/forces', { group: 'line', point: 'no_such_point', value: true });
  assert.equal(r.status, 404);
  r = await call(page, 'POST', '/api/forces', { group: 'line', point: 'conveyor_speed', value: 'fast' });
  assert.equal(r.status, 400);
  assert.equal(r.code, 'bad_value');
  r = await call(page, 'POST', '/api/forces', { group: 'line' });
  assert.equal(r.status, 400);
  r = await call(page, 'DELETE', '/api/forces/line/clamp');
  assert.equal(r.status, 404);
  assert.equal(r.code, 'not_forced');
});

test('a service user forces an output and a simulated input; they are shown and audited', async () => {
  await page.waitForSelector('[data-testid="force-line.conveyor_motor-1"]');
  await page.click('[data-testid="force-line.conveyor_motor-1"]');
  await page.waitForSelector('tr[data-point="line.conveyor_motor"][data-forced=true] td.value:text-is("true")');
  await page.fill('[data-testid="force-line.conveyor_speed-input"]', '250');
  await page.click('[data-testid="force-line.conveyor_speed-set"]');
  await page.waitForSelector('tr[data-point="line.conveyor_speed"][data-forced=true] td.value:text-is("250")');
  await page.click('[data-testid="force-line.board_present-1"]');
  await page.waitForSelector('tr[data-point="line.board_present"][data-forced=true] td.value:text-is("true")');
  await page.waitForSelector('[data-testid=force-banner]:visible');
  assert.match(await page.textContent('#force-text'), /3 IO points forced: .*line\.conveyor_motor = true \(service\)/);
  await page.locator('#view-io').evaluate((e) => { e.scrollTop = 0; });
  await shot(page, 'io-forced', 'io');
  // The banner is on every page.
  await page.click('#tab-line');
  await page.waitForSelector('[data-testid=force-banner]:visible');
  await page.click('[data-testid=tab-io]');
  const entries = await audit();
  const forced = entries.filter((e) => e.action === 'POST' && e.target === '/api/forces' && e.outcome === '200');
  assert.deepEqual(forced.map((e) => [e.who, e.detail]),
                   [['service', 'forced line.conveyor_motor = true'],
                    ['service', 'forced line.conveyor_speed = 250'],
                    ['service', 'forced line.board_present = true']]);
  // Released one by one from its row.
  await page.click('[data-testid="release-line.conveyor_speed"]');
  await page.waitForSelector('tr[data-point="line.conveyor_speed"][data-forced=false]');
  assert.ok((await audit()).some((e) => e.action === 'DELETE' && e.target === '/api/forces/line/conveyor_speed'
                                        && e.detail === 'released line.conveyor_speed'));
});

test('an emergency stop releases every force, and the release is audited', async () => {
  await cell.cmd('estop on');
  await page.waitForSelector('[data-testid=force-banner]', { state: 'hidden' });
  await page.waitForSelector('tr[data-point="line.conveyor_motor"][data-forced=false] td.value:text-is("false")');
  await page.waitForSelector('tr[data-point="line.board_present"][data-forced=false] td.value:text-is("false")');
  const released = (await audit()).filter((e) => e.action === 'RELEASE');
  assert.deepEqual(released.map((e) => [e.who, e.target, e.detail]).sort(),
                   [['cell', '/api/forces/line/board_present', 'emergency stop'],
                    ['cell', '/api/forces/line/conveyor_motor', 'emergency stop']]);
  // No force while the emergency stop is active.
  const r = await call(page, 'POST', '/api/forces', { group: 'line', point: 'clamp', value: true });
  assert.equal(r.status, 409);
  assert.equal(r.code, 'estop_active');
  await cell.cmd('estop off');
});

test('the end of service mode and the logout of whoever forced end forces', async () => {
  await page.click('[data-testid="force-line.clamp-1"]');
  await page.waitForSelector('[data-testid=force-banner]:visible');
  await cell.cmd('service off');
  await page.waitForSelector('[data-testid=force-banner]', { state: 'hidden' });
  await cell.cmd('service on');
  await page.click('[data-testid="force-line.clamp-1"]');
  await page.waitForSelector('tr[data-point="line.clamp"][data-forced=true]');
  await logout(page);
  await page.waitForSelector('[data-testid=force-banner]', { state: 'hidden' });
  assert.deepEqual((await call(page, 'GET', '/api/forces')).body, []);
});
