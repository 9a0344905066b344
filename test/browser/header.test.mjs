// The header with every tab an admin sees: each page reachable at 1024x768 and
// 1280x800, the cell's name, state, request, link and user on one row above the tabs
// whatever their length; tabs that do not fit scroll sideways; the request hidden on
// narrow screens.
import { test } from 'node:test';
import assert from 'node:assert/strict';
import { DemoCell, openPages, openPanel, login, shot } from './demo_cell.mjs';

const cell = new DemoCell();
let page;
openPages(cell, async (p) => {
  page = p;
  await openPanel(page, cell);
});

const PAGES = ['line', 'log', 'users', 'machine', 'errors', 'io', 'settings', 'recipes',
               'statistics', 'products', 'audit', 'simulation'];

// The boxes of the header's items, and the size of the document.
const header = () => page.evaluate(() => {
  const box = (sel) => document.querySelector(sel).getBoundingClientRect().toJSON();
  return { name: box('#cell-name'), state: box('#cell-state'), request: box('#cell-request'),
           link: box('#link'), user: box('#user-button'), nav: box('nav.tabs'), bar: box('header.bar'),
           width: document.documentElement.scrollWidth, height: document.documentElement.scrollHeight };
});

// Every item of the first row is above the tabs, and none overlaps the next.
function oneRow(h, what) {
  const row = [h.name, h.state, h.request, h.link, h.user];
  for (const b of row) assert.ok(b.bottom <= h.nav.top, `${what}: ${JSON.stringify(b)} above ${h.nav.top}`);
  for (let i = 1; i < row.length; i++) {
    assert.ok(row[i - 1].right <= row[i].left + 0.5, `${what}: ${JSON.stringify(row)}`);
  }
}

test('an admin reaches every page from the tabs at 1024x768 and 1280x800', async () => {
  await login(page, 'admin');
  await cell.cmd('service on');
  await page.waitForSelector('#cell-request:has-text("service mode")');
  for (const [width, height] of [[1024, 768], [1280, 800]]) {
    await page.setViewportSize({ width, height });
    const shown = await page.locator('nav.tabs .tab:visible').evaluateAll((ts) => ts.map((t) => t.dataset.view));
    assert.deepEqual(shown, PAGES);
    for (const id of PAGES) {
      await page.click(`#tab-${id}`);
      await page.waitForSelector(`#view-${id}:not(.hidden)`);
      const tab = await page.locator(`#tab-${id}`).boundingBox();
      const h = await header();
      assert.ok(tab.x >= h.nav.left && tab.x + tab.width <= h.nav.right + 0.5, `${id} ${width}: ${JSON.stringify(tab)}`);
      assert.ok(tab.height >= 40, `${id}: ${JSON.stringify(tab)}`);
      assert.ok(h.width <= width && h.height <= height, `${id} ${width}: ${JSON.stringify(h)}`);
      oneRow(h, `${id} ${width}`);
    }
  }
  await page.setViewportSize({ width: 1024, height: 768 });
  await shot(page, 'header-1024');
});

test('a long name and request keep the header on two rows; the request is cut short, then hidden', async () => {
  const before = await header();
  const name = 'Inline router of the second line in hall B, north side';
  const r = await page.evaluate((n) => window.cellPanel.api('PUT', '/api/settings/machine', { cell_name: n }), name);
  assert.equal(r.values.cell_name, name);
  await page.evaluate(() => window.cellPanel.api('POST', '/api/cell/start'));
  await page.waitForSelector('#cell-request:has-text("request: start · service mode")');
  await page.waitForSelector(`#cell-name:has-text("${name}")`);
  const h = await header();
  assert.equal(h.bar.height, before.bar.height);
  oneRow(h, 'long');
  assert.equal(await page.getAttribute('#cell-request', 'title'), 'request: start · service mode');
  // A narrow window: the request is not shown, the tabs scroll to the one chosen.
  await page.setViewportSize({ width: 800, height: 600 });
  await page.waitForSelector('#cell-request', { state: 'hidden' });
  const nav = await page.evaluate(() => {
    const n = document.querySelector('nav.tabs');
    return { client: n.clientWidth, scroll: n.scrollWidth };
  });
  assert.ok(nav.scroll > nav.client, JSON.stringify(nav));
  await page.click('#tab-audit');
  await page.waitForSelector('#view-audit:not(.hidden)');
  const tab = await page.locator('#tab-audit').boundingBox();
  const h2 = await header();
  assert.ok(tab.x + tab.width <= h2.nav.right + 0.5, JSON.stringify([tab, h2.nav]));
  oneRow(h2, 'narrow');
  await page.setViewportSize({ width: 1024, height: 768 });
  await page.evaluate(() => window.cellPanel.api('POST', '/api/cell/stop'));
});
