// The Settings page: a form made from each object's schema, a refused value shown at
// its field, revisions, differences and restore; only service and admin see it, and
// the panel's own object is an admin's.
import { test } from 'node:test';
import assert from 'node:assert/strict';
import { DemoCell, openPages, openPanel, login, logout, shot, fetchJson } from './demo_cell.mjs';

const cell = new DemoCell();
let page;

openPages(cell, async (p) => {
  page = p;
  await openPanel(page, cell);
});

test('anyone and an operator do not see the Settings tab', async () => {
  await page.waitForSelector('[data-testid=tab-settings]', { state: 'hidden' });
  await login(page, 'operator');
  await page.waitForSelector('[data-testid=tab-settings]', { state: 'hidden' });
  const status = await page.evaluate(() => fetch('/api/settings/machine', {
    method: 'PUT', headers: { 'content-type': 'application/json' }, body: '{"speed_override": 10}' }).then((r) => r.status));
  assert.ok(status === 403 || status === 401, String(status));
  await logout(page);
});

test('a service user changes a setting; a value out of range is shown at its field', async () => {
  await login(page, 'service');
  await page.click('[data-testid=tab-settings]');
  await page.click('[data-testid=settings-machine]');
  const field = page.locator('[data-testid="field-speed_override"]');
  await field.waitFor();
  assert.match(await field.textContent(), /1 to 100 %/);
  assert.match(await field.textContent(), /default 50/);
  // Out of range: refused, said at the field, nothing saved.
  await field.locator('input').fill('150');
  await page.evaluate(() => { for (const i of document.querySelectorAll('#view-settings input')) i.removeAttribute('max'); });
  await page.click('[data-testid=settings-save]');
  await page.waitForSelector('[data-testid="field-speed_override"].invalid [data-testid=field-error]:not(:empty)');
  assert.equal((await fetchJson(page, '/api/settings/machine')).values.speed_override, 50);
  // In range: saved as a new revision.
  await field.locator('input').fill('80');
  await page.click('[data-testid=settings-save]');
  await page.waitForSelector('[data-testid=toast]:has-text("machine saved")');
  assert.equal((await fetchJson(page, '/api/settings/machine')).values.speed_override, 80);
  await page.waitForSelector('[data-testid=settings-revisions] tbody tr:nth-child(2)');
  const first = await page.locator('[data-testid=settings-revisions] tbody tr').first().locator('td').nth(2).textContent();
  assert.equal(first, 'service');
  await shot(page, 'settings', 'settings');
});

test('the difference between two revisions, and a restore of the older', async () => {
  const revs = await fetchJson(page, '/api/settings/machine/revisions');
  const [now, before] = revs;
  await page.selectOption('[data-testid=diff-from]', String(before.rev));
  await page.selectOption('[data-testid=diff-to]', String(now.rev));
  await page.click('[data-testid=settings-diff-show]');
  const row = page.locator('[data-testid=settings-diff] tr[data-path="speed_override"]');
  await row.waitFor();
  assert.equal(await row.locator('td.old').textContent(), '50');
  assert.equal(await row.locator('td.new').textContent(), '80');
  page.once('dialog', (d) => d.accept());
  await page.click(`[data-testid=restore-${before.rev}]`);
  await page.waitForSelector(`[data-testid=toast]:has-text("restored to revision ${before.rev}")`);
  assert.equal((await fetchJson(page, '/api/settings/machine')).values.speed_override, 50);
  assert.equal(await page.inputValue('#set-speed_override'), '50');
  const after = await fetchJson(page, '/api/settings/machine/revisions');
  assert.equal(after.length, revs.length + 1);
  assert.equal(after[0].who, 'service');
});

test('a change waits for the next Start, and the page says so until it is in force', async () => {
  const cmd = (c) => page.evaluate((x) => window.cellPanel.api('POST', `/api/cell/${x}`), c);
  await cmd('start');
  await page.click('[data-testid=settings-machine]');
  await page.fill('#set-speed_override', '70');
  await page.click('[data-testid=settings-save]');
  await page.waitForSelector('[data-testid=settings-pending]:visible');
  await page.waitForSelector('[data-testid=settings-machine] .pending');
  // The cell started again (the websocket tells the page): in force, no longer waiting.
  await cmd('stop');
  await cmd('start');
  await page.waitForSelector('[data-testid=settings-pending]', { state: 'hidden' });
  await page.waitForSelector('[data-testid=settings-machine] .pending', { state: 'detached' });
  assert.equal((await fetchJson(page, '/api/settings/machine')).in_force.speed_override, 70);
  await cmd('stop');
});

test('a list field: a row added; a wrong entry is shown at the list, then the plan saved', async () => {
  await page.click('[data-testid=settings-statistics]');
  const field = page.locator('[data-testid="field-shifts"]');
  await field.waitFor();
  assert.equal(await field.locator('input').count(), 3);
  await field.locator('button:has-text("Add")').click();
  await field.locator('input').nth(3).fill('25:00');
  await page.click('[data-testid=settings-save]');
  await page.waitForSelector('[data-testid="field-shifts"].invalid [data-testid=field-error]:not(:empty)');
  assert.deepEqual((await fetchJson(page, '/api/settings/statistics')).values.shifts, ['06:00', '14:00', '22:00']);
  await field.locator('input').nth(3).fill('23:00');
  await page.click('[data-testid=settings-save]');
  await page.waitForSelector('[data-testid=toast]:has-text("statistics saved")');
  assert.deepEqual((await fetchJson(page, '/api/settings/statistics')).values.shifts, ['06:00', '14:00', '22:00', '23:00']);
  // Removed again: the row's Remove, then Save.
  await page.locator('[data-testid="field-shifts"] .list-row').nth(3).locator('button').click();
  await page.click('[data-testid=settings-save]');
  await page.waitForSelector('[data-testid=toast]:has-text("statistics saved")');
  assert.deepEqual((await fetchJson(page, '/api/settings/statistics')).values.shifts, ['06:00', '14:00', '22:00']);
});

test('the panel\'s own settings are an admin\'s: a service user sees them read-only', async () => {
  await page.click('[data-testid=settings-web]');
  await page.waitForSelector('[data-testid=settings-form] h2:has-text("web")');
  assert.equal(await page.isDisabled('[data-testid=settings-save]'), true);
  await logout(page);
  await page.waitForSelector('[data-testid=tab-settings]', { state: 'hidden' });
  await login(page, 'admin');
  await page.click('[data-testid=tab-settings]');
  await page.click('[data-testid=settings-web]');
  await page.waitForSelector('[data-testid=settings-form] h2:has-text("web")');
  assert.equal(await page.isDisabled('[data-testid=settings-save]'), false);
  await page.fill('#set-idle_minutes', '45');
  await page.click('[data-testid=settings-save]');
  await page.waitForSelector('[data-testid=toast]:has-text("web saved")');
  assert.equal((await fetchJson(page, '/api/settings/web')).values.idle_minutes, 45);
});

test('each page fits 1024x768 and 1280x800 touch panels, its buttons touch-sized', async () => {
  for (const [width, height] of [[1024, 768], [1280, 800]]) {
    await page.setViewportSize({ width, height });
    for (const id of ['settings', 'recipes', 'statistics', 'products', 'audit']) {
      await page.click(`[data-testid=tab-${id}]`);
      await page.waitForSelector(`#view-${id}:not(.hidden)`);
      const size = await page.evaluate(() => ({
        width: document.documentElement.scrollWidth, height: document.documentElement.scrollHeight }));
      assert.ok(size.width <= width && size.height <= height, `${id} ${width}: ${JSON.stringify(size)}`);
      // (A button the page replaced between the query and the measure is not on screen.)
      const small = await page.locator(`#view-${id} button:visible`).evaluateAll((bs) =>
        bs.filter((b) => b.isConnected).map((b) => ({ text: b.textContent, ...b.getBoundingClientRect().toJSON() }))
          .filter((b) => b.height < 40 || b.width < 40));
      assert.deepEqual(small, [], `${id} ${width}`);
    }
  }
  await page.setViewportSize({ width: 1024, height: 768 });
});
