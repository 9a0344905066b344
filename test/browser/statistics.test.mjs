// The Statistics page: charts whose numbers are the API's (time in each state per
// task, products out per hour, cycle times, OEE), for this shift, a day, a range;
// anyone sees it.
import { test } from 'node:test';
import assert from 'node:assert/strict';
import { DemoCell, openPages, openPanel, login, logout, call, shot, fetchJson } from './demo_cell.mjs';

// The demo cell without its links: every task takes products in from outside the
// cell and sends them out of it, so each product set and cleared enters and leaves.
const cell = new DemoCell({ main: 'cell_web_demo:main(#{links => false})' });
let page;

openPages(cell, async (p) => {
  page = p;
  await openPanel(page, cell);
});

// Charts brought by a click, once the cell's answer to it is drawn.
// Clicks, and answers the charts of the choice the click made (`query', a part of its
// query string): a refresh of the choice before may still be on its way.
async function charts(click, query) {
  const answer = page.waitForResponse((r) => r.url().includes('/api/statistics/charts?') &&
                                              r.url().includes(query));
  await page.click(click);
  const data = await (await answer).json();
  await page.waitForSelector('[data-testid=chart-states] svg');
  return data;
}

test('anyone sees the statistics page without logging in', async () => {
  await page.waitForSelector('[data-testid=tab-statistics]:visible');
  await page.click('[data-testid=tab-statistics]');
  await page.waitForSelector('[data-testid=chart-states]');
  await page.waitForSelector('[data-testid=oee-definitions]:has-text("Availability = run time ÷ planned time")');
});

test('a shift\'s charts show the numbers of /api/statistics', async () => {
  // The OEE measured against a cycle that fits the demo cell (its three products go
  // through in a fraction of a second), set as a service user sets it, so the
  // picture shows a believable figure rather than the default 60 s one.
  await login(page, 'service');
  assert.equal((await call(page, 'PUT', '/api/settings/oee', { ideal_cycle_s: 0.03 })).status, 200);
  await logout(page);
  await login(page, 'operator');
  await page.click('#tab-line');
  await page.click('[data-testid=cmd-start]');
  await page.waitForSelector('[data-task="router"][data-state="READY-IDLE-STARVED"]');
  await cell.cmd('event router unstarved');
  for (const serial of ['S-1', 'S-2', 'S-3']) {
    await cell.cmd(`product loader ${serial}`);
    await cell.cmd('product loader none');
  }
  await cell.cmd('event router work_start');
  await page.click('[data-testid=cmd-stop]');
  await page.waitForSelector('[data-task="router"][data-state="OFF"]');
  await cell.cmd('flush');
  await page.click('[data-testid=tab-statistics]');
  await charts('[data-testid=stats-shift]', 'period=shift');
  const api = await fetchJson(page, '/api/statistics?period=shift');
  const prod = api.production;
  // Every task's time in each state but OFF (the state they are all in, still
  // counting) is the API's to the millisecond.
  const bars = await page.locator('[data-testid=chart-states] rect[data-state]').evaluateAll((rs) =>
    rs.map((r) => ({ task: r.dataset.task, state: r.dataset.state, ms: Number(r.dataset.ms) })));
  const closed = bars.filter((b) => b.state !== 'off');
  assert.ok(closed.some((b) => b.task === 'router' && b.state === 'active'), JSON.stringify(bars));
  for (const b of closed) assert.equal(b.ms, prod.tasks[b.task].time_ms[b.state], `${b.task} ${b.state}`);
  for (const [task, t] of Object.entries(prod.tasks)) {
    for (const [state, ms] of Object.entries(t.time_ms)) {
      if (state !== 'off' && ms > 0) assert.ok(closed.some((b) => b.task === task && b.state === state), `${task} ${state}`);
    }
  }
  // Products out: the figures, the hours' bars and the cycle times.
  assert.equal(prod.cell.out, 3);
  assert.equal(await page.textContent('[data-testid=figure-out] .v'), String(prod.cell.out));
  assert.equal(await page.textContent('[data-testid=figure-good] .v'), String(prod.cell.good));
  const hours = await page.locator('[data-testid=chart-hourly] rect[data-out]').evaluateAll((rs) =>
    rs.map((r) => Number(r.dataset.out)));
  assert.equal(hours.reduce((a, b) => a + b, 0), prod.cell.out);
  const cycles = await page.locator('[data-testid=chart-cycles] rect[data-count]').evaluateAll((rs) =>
    rs.map((r) => Number(r.dataset.count)));
  assert.equal(cycles.reduce((a, b) => a + b, 0), prod.cell.cycle_ms.n);
  // OEE as the page defines it, from the API's numbers.
  const ideal = (await fetchJson(page, '/api/settings/oee')).values.ideal_cycle_s * 1000;
  const tasks = Object.values(prod.tasks);
  const get = (t, s) => t.time_ms[s] || 0;
  const planned = tasks.reduce((a, t) => a + Object.values(t.time_ms).reduce((x, y) => x + y, 0) - get(t, 'off'), 0) / tasks.length;
  const run = tasks.reduce((a, t) => a + Object.values(t.time_ms).reduce((x, y) => x + y, 0) - get(t, 'off') - get(t, 'down') - get(t, 'setup'), 0) / tasks.length;
  const factor = async (k) => Number(await page.getAttribute(`[data-testid=chart-oee] rect[data-factor=${k}]`, 'data-value'));
  const near = (a, b) => Math.abs(a - b) < 0.0001;
  assert.ok(near(await factor('availability'), run / planned));
  assert.ok(near(await factor('performance'), (ideal * prod.cell.out) / run));
  assert.ok(near(await factor('quality'), prod.cell.good / prod.cell.out));
  await shot(page, 'statistics', 'statistics');
});

test('a day and a range hold this shift', async () => {
  const day = await charts('[data-testid=stats-day-show]', 'day=');
  assert.equal(day.selection.kind, 'day');
  assert.equal(day.shifts.length, 1);
  await page.waitForSelector('[data-testid=stats-selection]:has-text("Day ")');
  // From an hour ago to now (the field empty).
  await page.fill('[data-testid=stats-from]', await page.evaluate(() => {
    const d = new Date(Date.now() - 3600000);
    const p = (n) => String(n).padStart(2, '0');
    return `${d.getFullYear()}-${p(d.getMonth() + 1)}-${p(d.getDate())}T${p(d.getHours())}:${p(d.getMinutes())}`;
  }));
  await page.fill('[data-testid=stats-to]', '');
  const range = await charts('[data-testid=stats-range-show]', 'from=');
  assert.equal(range.selection.kind, 'range');
  assert.equal(range.sum.cell.out, 3);
  assert.equal(await page.textContent('[data-testid=figure-out] .v'), '3');
});

test('a task\'s change on the websocket brings the charts again, with no click', async () => {
  await charts('[data-testid=stats-shift]', 'period=shift');
  const again = page.waitForResponse((r) => r.url().includes('/api/statistics/charts'));
  await page.evaluate(() => window.cellPanel.api('POST', '/api/cell/start'));
  const data = await (await again).json();
  assert.equal(data.selection.label, (await fetchJson(page, '/api/statistics?period=shift')).production.period);
  await page.evaluate(() => window.cellPanel.api('POST', '/api/cell/stop'));
});
