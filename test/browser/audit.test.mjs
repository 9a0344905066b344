// The Audit page: only an admin sees it; the audit trail filtered by user, action
// and time.
import { test } from 'node:test';
import assert from 'node:assert/strict';
import { DemoCell, openPages, openPanel, login, logout, shot } from './demo_cell.mjs';

const cell = new DemoCell();
let page;

openPages(cell, async (p) => {
  page = p;
  await openPanel(page, cell);
});

test('an operator and a service user do not see the Audit page', async () => {
  for (const user of ['operator', 'service']) {
    await login(page, user);
    await page.waitForSelector('[data-testid=tab-audit]', { state: 'hidden' });
    await logout(page);
  }
});

// A search made, and its answer drawn (the rows of the one before are gone at once).
async function search() {
  await page.click('[data-testid=audit-search]');
  await page.waitForSelector('.audit-range:not(:has-text("searching"))');
}

test('an admin filters the audit trail by user, action and time', async () => {
  await login(page, 'operator');
  await page.click('[data-testid=cmd-start]');
  await page.click('[data-testid=cmd-stop]');
  await logout(page);
  await login(page, 'admin');
  await page.click('[data-testid=tab-audit]');
  await page.waitForSelector('[data-testid=audit-lines] tr');
  // By user: only the operator's.
  await page.fill('[data-testid=audit-who]', 'operator');
  await search();
  await page.waitForSelector('[data-testid=audit-lines] tr td.text:has-text("/api/cell/stop")');
  const who = await page.locator('[data-testid=audit-lines] td.who').allTextContents();
  assert.ok(who.length >= 2 && who.every((w) => w === 'operator'), who.join());
  // By action: the operator's POSTs are its logins and commands; no DELETE of it is left out.
  await page.selectOption('[data-testid=audit-action]', 'DELETE');
  await search();
  await page.waitForSelector('[data-testid=audit-lines] tr td.text:has-text("/api/cell/stop")', { state: 'detached' });
  const actions = await page.locator('[data-testid=audit-lines] td.action').allTextContents();
  assert.ok(actions.every((a) => a === 'DELETE'), actions.join());
  // By time: nothing before the cell began.
  await page.selectOption('[data-testid=audit-action]', '');
  await page.fill('[data-testid=audit-from]', '2001-01-01T00:00');
  await page.fill('[data-testid=audit-to]', '2001-01-02T00:00');
  await search();
  await page.waitForSelector('.audit-range:has-text("no entries")');
  assert.equal(await page.locator('[data-testid=audit-lines] tr').count(), 0);
  await page.fill('[data-testid=audit-who]', '');
  await page.fill('[data-testid=audit-to]', '');
  await page.fill('[data-testid=audit-from]', await page.evaluate(() => {
    const d = new Date(Date.now() - 3600000);
    const p = (n) => String(n).padStart(2, '0');
    return `${d.getFullYear()}-${p(d.getMonth() + 1)}-${p(d.getDate())}T${p(d.getHours())}:${p(d.getMinutes())}`;
  }));
  await search();
  await page.waitForSelector('[data-testid=audit-lines] tr td.text:has-text("/api/cell/stop")');
  await shot(page, 'audit', 'audit');
});
