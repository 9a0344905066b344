// The Products page: a product found by its serial and its history as a timeline —
// entry with its recipe, transfers, an error and the answer given, exit; the products
// in the cell followed live; anyone sees it.
import { test } from 'node:test';
import assert from 'node:assert/strict';
import { DemoCell, openPages, openPanel, login, shot, fetchJson } from './demo_cell.mjs';

// The demo cell without its links: every task takes products in from outside the
// cell and sends them out of it, so each product set and cleared enters and leaves.
const cell = new DemoCell({ main: 'cell_web_demo:main(#{links => false})' });
let page;

openPages(cell, async (p) => {
  page = p;
  await openPanel(page, cell);
});

test('an unknown serial is said to be unknown', async () => {
  await page.click('[data-testid=tab-products]');
  await page.fill('[data-testid=serial-input]', 'NO-SUCH-1');
  await page.click('[data-testid=serial-search]');
  await page.waitForSelector('[data-testid=product-not-found]:has-text("No product NO-SUCH-1 has been recorded")');
});

test('a product is followed live while in the cell, and its whole way is told after it left', async () => {
  await login(page, 'operator');
  await page.click('#tab-line');
  await page.click('[data-testid=cmd-start]');
  await page.waitForSelector('[data-task="router"][data-state="READY-IDLE-STARVED"]');
  await page.click('[data-testid=tab-products]');
  await cell.cmd('product router B-77');
  // In the cell: a button for it, brought by the websocket.
  await page.click('[data-testid=in-cell-B-77]');
  await page.waitForSelector('[data-testid=product-history][data-serial="B-77"] [data-kind=entry]');
  assert.match(await page.textContent('dd[data-fact=status]'), /in the cell at router/);
  // An error while it is there, answered by the operator.
  await cell.cmd('error router retry,reset');
  const alarm = (await fetchJson(page, '/api/alarms'))[0];
  await page.evaluate((id) => window.cellPanel.api('POST', `/api/alarms/${encodeURIComponent(id)}/answer`, { solution: 'retry' }), alarm.id);
  await page.waitForSelector('[data-testid=product-timeline] [data-event=alarm_answered]:has-text("operator answered retry")');
  await cell.cmd('product router none');
  await page.waitForSelector('[data-testid=product-timeline] [data-kind=exit]:has-text("left the cell through router, good")');
  // Found again by its serial: the timeline is its history as the API has it, in order.
  await page.fill('[data-testid=serial-input]', 'B-77');
  await page.click('[data-testid=serial-search]');
  await page.waitForSelector('[data-testid=product-timeline] [data-kind=exit]');
  const history = await fetchJson(page, '/api/products/B-77/history');
  const shown = await page.locator('[data-testid=product-timeline] li').evaluateAll((ls) => ls.map((l) => l.dataset.event));
  assert.deepEqual(shown, history.events.map((e) => e.event));
  for (const k of ['entry', 'transfer', 'error', 'answer', 'exit']) {
    assert.ok(await page.locator(`[data-testid=product-timeline] [data-kind=${k}]`).count() > 0, k);
  }
  assert.match(await page.textContent('dd[data-fact=recipe]'), /demo/);
  assert.match(await page.textContent('dd[data-fact=status]'), /left the cell good/);
  await shot(page, 'products', 'products');
  await page.click('#tab-line');
  await page.click('[data-testid=cmd-stop]');
});
