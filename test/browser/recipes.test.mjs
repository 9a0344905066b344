// The Recipes page: a recipe's drawing drawn from its tree with the cut order, a
// recipe file uploaded, copied, renamed, deleted, a DXF drawing imported; only
// service and admin see the page.
import { test } from 'node:test';
import assert from 'node:assert/strict';
import { DemoCell, openPages, openPanel, login, logout, shot, fetchJson } from './demo_cell.mjs';

const cell = new DemoCell();
let page;

// A DXF of a 100 x 50 panel with a hole: four LINEs and a CIRCLE, and a TEXT the
// import leaves out.
const DXF = ['0', 'SECTION', '2', 'ENTITIES',
  ...[[0, 0, 100, 0], [100, 0, 100, 50], [100, 50, 0, 50], [0, 50, 0, 0]].flatMap(([a, b, c, d]) =>
    ['0', 'LINE', '8', 'Outline', '10', a, '20', b, '30', '0', '11', c, '21', d, '31', '0']),
  '0', 'CIRCLE', '8', 'Holes', '10', '50', '20', '25', '30', '0', '40', '5',
  '0', 'TEXT', '8', 'Notes', '10', '1', '20', '1', '30', '0', '40', '2', '1', 'hello',
  '0', 'ENDSEC', '0', 'EOF'].join('\n') + '\n';

openPages(cell, async (p) => {
  page = p;
  await cell.cmd('recipe Board');
  await openPanel(page, cell);
});

test('an operator does not see the Recipes page nor may change a recipe', async () => {
  await login(page, 'operator');
  await page.waitForSelector('[data-testid=tab-recipes]', { state: 'hidden' });
  const status = await page.evaluate(() => fetch('/api/recipes/Board', { method: 'DELETE' }).then((r) => r.status));
  assert.ok(status === 403 || status === 401, String(status));
  await logout(page);
});

test('a service user sees a recipe\'s drawing with its cuts numbered in their order', async () => {
  await login(page, 'service');
  await page.click('[data-testid=tab-recipes]');
  await page.click('[data-testid=recipe-list] tr[data-recipe="Board"]');
  const svg = page.locator('[data-testid=drawing-svg]');
  await svg.waitFor();
  // The outline, the fiducial and three cuts.
  assert.equal(await svg.getAttribute('data-primitives'), '5');
  assert.equal(await svg.locator('.type-Cut line').count(), 3);
  assert.equal(await svg.locator('.type-Fiducial').count(), 1);
  // Numbered 1, 2, 3 from left to right as their ExecOrder says, not as the tree lists them.
  const marks = await svg.locator('.exec-mark').evaluateAll((ms) => ms.map((m) => ({
    n: m.dataset.execOrder, x: Number(m.querySelector('circle').getAttribute('cx')) })));
  assert.deepEqual(marks.map((m) => m.n), ['1', '2', '3']);
  assert.deepEqual(marks.map((m) => m.x), [50, 120, 180]);
  await page.waitForSelector('figcaption:has-text("worked in order 1 → 2 → 3")');
  await shot(page, 'recipes', 'recipes');
});

test('a recipe file downloaded is uploaded again under a new name, copied, renamed, deleted', async () => {
  const bytes = await page.evaluate(() => fetch('/api/recipes/Board/file')
    .then((r) => r.arrayBuffer()).then((b) => Array.from(new Uint8Array(b))));
  const [download] = await Promise.all([page.waitForEvent('download'), page.click('[data-testid=recipe-download]')]);
  assert.equal(download.suggestedFilename(), 'Board.zprd');
  await page.fill('[data-testid=upload-name]', 'Board 2');
  await page.setInputFiles('[data-testid=recipe-file]',
    { name: 'Board.zprd', mimeType: 'application/zip', buffer: Buffer.from(bytes) });
  await page.waitForSelector('[data-testid=toast]:has-text("Board 2 uploaded")');
  await page.waitForSelector('[data-testid=recipe-title]:has-text("Board 2")');
  await page.waitForSelector('[data-testid=drawing-svg][data-primitives="5"]');
  // A file that is no recipe is refused and nothing is written.
  await page.fill('[data-testid=upload-name]', 'Junk');
  await page.setInputFiles('[data-testid=recipe-file]',
    { name: 'junk.zprd', mimeType: 'application/zip', buffer: Buffer.from('not a zip') });
  await page.waitForSelector('[data-testid=toast]:not(:has-text("uploaded"))');
  assert.equal((await fetchJson(page, '/api/recipes')).some((r) => r.name === 'Junk'), false);
  await page.fill('[data-testid=upload-name]', '');
  await page.fill('[data-testid=recipe-new-name]', 'Board 3');
  await page.click('[data-testid=recipe-copy]');
  await page.waitForSelector('[data-testid=recipe-list] tr[data-recipe="Board 3"]');
  await page.click('[data-testid=recipe-list] tr[data-recipe="Board 3"]');
  await page.fill('[data-testid=recipe-new-name]', 'Board 4');
  await page.click('[data-testid=recipe-rename]');
  await page.waitForSelector('[data-testid=recipe-list] tr[data-recipe="Board 4"]');
  await page.waitForSelector('[data-testid=recipe-list] tr[data-recipe="Board 3"]', { state: 'detached' });
  page.once('dialog', (d) => d.accept());
  await page.click('[data-testid=recipe-delete]');
  await page.waitForSelector('[data-testid=recipe-list] tr[data-recipe="Board 4"]', { state: 'detached' });
  const names = (await fetchJson(page, '/api/recipes')).map((r) => r.name).sort();
  assert.deepEqual(names, ['Board', 'Board 2']);
});

test('a DXF drawing becomes a recipe; what the import left out is said', async () => {
  await page.fill('[data-testid=upload-name]', 'Panel DXF');
  await page.setInputFiles('[data-testid=dxf-file]', { name: 'panel.dxf', mimeType: 'application/dxf', buffer: Buffer.from(DXF) });
  await page.waitForSelector('[data-testid=toast]:has-text("5 items imported from DXF; left out: 1 TEXT")');
  await page.waitForSelector('[data-testid=recipe-title]:has-text("Panel DXF")');
  const svg = page.locator('[data-testid=drawing-svg]');
  await page.waitForSelector('[data-testid=drawing-svg][data-primitives="5"]');
  assert.equal(await svg.locator('line').count(), 4);
  assert.equal(await svg.locator('circle').count(), 1);
  const tree = await fetchJson(page, '/api/recipes/Panel%20DXF/drawing');
  assert.equal(tree.children[0].attributes.ItemType, 'PanelDrawing');
  // Imported again without replace: refused, the recipe kept.
  await page.setInputFiles('[data-testid=dxf-file]', { name: 'Panel DXF.dxf', mimeType: 'application/dxf', buffer: Buffer.from(DXF) });
  await page.waitForSelector('[data-testid=toast]:has-text("exists")');
});
