// The Machine page: the picture of the cell drawn from its spec alone (zones in flow
// order, lanes, links), each task in its IPC-2541 colour with its product, the phase
// of each handshake link, the beacon and the shift's counters, all live.
import { test } from 'node:test';
import assert from 'node:assert/strict';
import { DemoCell, openPages, login, shot } from './demo_cell.mjs';

const cell = new DemoCell();
let page;
openPages(cell, (p) => { page = p; });

const node = (id) => page.locator(`[data-testid=machine-svg] g.node[data-node="${id}"]`);

test('anyone sees the picture of the cell, drawn from its spec', async () => {
  await page.goto(cell.url);
  await page.click('[data-testid=tab-machine]');
  for (const id of ['loader', 'router', 'unloader']) {
    await page.waitForSelector(`g.node[data-node="${id}"][data-state="OFF"]`);
  }
  const zones = await page.locator('[data-testid=machine-svg] text.zone').allTextContents();
  assert.deepEqual(zones, ['Loading', 'Routing', 'Unloading']);
  // In flow order from left to right, linked by their handshakes.
  const xs = [];
  for (const id of ['loader', 'router', 'unloader']) xs.push((await node(id).boundingBox()).x);
  assert.ok(xs[0] < xs[1] && xs[1] < xs[2], JSON.stringify(xs));
  for (const l of ['load_route', 'route_unload']) {
    // A straight arrow has no height: attached, not "visible".
    await page.waitForSelector(`g.link[data-link="${l}"][data-phase="idle"]`, { state: 'attached' });
  }
  assert.equal(await page.locator('[data-testid=beacon] .lamp').count(), 4);
  assert.equal(await page.textContent('[data-counter="in"]'), '0');
  // OFF is grey.
  assert.equal(await node('router').locator('rect').evaluate((r) => getComputedStyle(r).fill),
               'rgb(154, 160, 166)');
});

test('states, products and link phases change live, in the IPC-2541 colours', async () => {
  await login(page, 'operator', 'operator');
  await page.click('[data-testid=tab-machine]');
  const requests = [];
  const seen = (r) => requests.push(r.url());
  await page.click('#tab-line');
  await page.click('[data-testid=cmd-start]');
  await page.click('[data-testid=tab-machine]');
  await page.waitForSelector('g.node[data-node="router"][data-state="READY-IDLE-STARVED"]');
  page.on('request', seen);
  await cell.cmd('event router unstarved');
  await cell.cmd('product router P-2001');
  await cell.cmd('event router work_start');
  await page.waitForSelector('g.node[data-node="router"][data-state="READY-PROCESSING-EXECUTING"]');
  await page.waitForSelector('g.node[data-node="router"] [data-testid=node-serial]:text-is("P-2001")');
  const fill = (id) => node(id).locator('rect').evaluate((r) => getComputedStyle(r).fill);
  assert.equal(await fill('router'), 'rgb(30, 158, 58)');      // EXECUTING green
  assert.equal(await fill('loader'), 'rgb(242, 201, 76)');     // STARVED yellow
  // The loader offers its product to the router: the link shows it.
  await cell.cmd('product loader P-2002');
  await cell.cmd('offer loader load_route');
  await page.waitForSelector('g.link[data-link="load_route"][data-phase="offered"]', { state: 'attached' });
  assert.deepEqual(await page.locator('[data-testid=machine-svg] text.phase[data-link="load_route"]').allTextContents(),
                   ['offered', 'P-2002']);
  await page.waitForSelector('g.node[data-node="loader"][data-state="READY-IDLE-BLOCKED"]');
  // The counters follow the items that came in.
  await page.waitForSelector('[data-counter="in"]:text-is("2")');
  page.off('request', seen);
  // Only the layout read again after a snapshot would be a request: none came.
  assert.deepEqual(requests, []);
  await shot(page, 'machine', 'line');
});

test('task cards break names between words, never inside one', async () => {
  await page.click('#tab-line');
  const style = await page.locator('[data-task="router"] .id')
    .evaluate((e) => [getComputedStyle(e).overflowWrap, getComputedStyle(e).wordBreak]);
  assert.deepEqual(style, ['normal', 'normal']);
  // Each card's name on one line at 1024x768.
  for (const id of ['loader', 'router', 'unloader']) {
    const lines = await page.locator(`[data-task="${id}"] .id`).evaluate((e) => {
      const r = document.createRange();
      r.selectNodeContents(e);
      return new Set([...r.getClientRects()].map((x) => Math.round(x.top))).size;
    });
    assert.equal(lines, 1, id);
  }
});

test('the Machine and Errors pages fit 1024x768 and 1280x800 touch panels', async () => {
  for (const [width, height] of [[1024, 768], [1280, 800]]) {
    await page.setViewportSize({ width, height });
    for (const tab of ['machine', 'errors']) {
      await page.click(`[data-testid=tab-${tab}]`);
      await page.waitForSelector(`#view-${tab}:not(.hidden)`);
      const size = await page.evaluate(() => ({
        width: document.documentElement.scrollWidth, height: document.documentElement.scrollHeight,
      }));
      assert.ok(size.width <= width && size.height <= height, `${tab} ${JSON.stringify(size)}`);
      const box = await page.locator(`[data-testid=tab-${tab}]`).boundingBox();
      assert.ok(box.height >= 40, JSON.stringify(box));
    }
    await page.click('[data-testid=tab-machine]');
    const svg = await page.locator('[data-testid=machine-svg]').boundingBox();
    assert.ok(svg.width > width / 2, `the picture is ${svg.width} wide`);
  }
  await page.setViewportSize({ width: 1024, height: 768 });
});
