// The Errors page: the active errors with their own solutions, and the history of
// answers (who answered what, when), filterable.
import { test } from 'node:test';
import assert from 'node:assert/strict';
import { DemoCell, openPages, login, shot } from './demo_cell.mjs';

const cell = new DemoCell();
let page;
openPages(cell, (p) => { page = p; });

const active = () => page.locator('[data-testid=errors-active] .alarm');
const history = () => page.locator('[data-testid=history] tr[data-id]');

test('only an operator or higher sees the Errors page', async () => {
  await page.goto(cell.url);
  await page.waitForSelector('#link.up');
  await page.waitForSelector('[data-testid=tab-errors]', { state: 'hidden' });
  await login(page, 'operator', 'operator');
  await page.waitForSelector('[data-testid=tab-errors]:visible');
});

test('an operator answers errors there and finds every answer in the history', async () => {
  await page.click('#tab-line');
  await page.click('[data-testid=cmd-start]');
  await page.waitForSelector('[data-task="router"][data-state="READY-IDLE-STARVED"]');
  await page.click('[data-testid=tab-errors]');
  await page.waitForSelector('[data-testid=errors-active]:has-text("No errors")');
  await cell.cmd('error router retry,reset');
  await active().first().waitFor();
  assert.deepEqual(await active().first().locator('button').allTextContents(), ['Retry', 'Reset']);
  await active().first().locator('button[data-solution=retry]').click();
  await active().first().waitFor({ state: 'detached' });
  await page.waitForSelector('[data-testid=history] tr[data-id]:has(td.what:text-is("retry"))');
  await cell.cmd('error loader reset');
  await active().first().waitFor();
  await active().first().locator('button[data-solution=reset]').click();
  await page.waitForSelector('[data-testid=history] tr[data-id]:has(td.what:text-is("reset"))');
  await cell.cmd('warning unloader low_boxes Boxes running low');
  await active().first().waitFor();
  await shot(page, 'errors', 'errors');
  const rows = await history().evaluateAll((trs) => trs.map((tr) =>
    [...tr.querySelectorAll('td')].slice(1).map((td) => td.textContent)));
  assert.deepEqual(rows, [['loader', 'Board jammed', 'reset', 'operator'],
                          ['router', 'Board jammed', 'retry', 'operator']]);
  // Filtered by task, by answer, by who.
  await page.selectOption('[data-testid=history-filters] select[name=task]', 'router');
  await page.waitForFunction(() => document.querySelectorAll('[data-testid=history] tr[data-id]').length === 1);
  assert.equal(await history().locator('td.what').textContent(), 'retry');
  await page.selectOption('[data-testid=history-filters] select[name=task]', '');
  await page.selectOption('[data-testid=history-filters] select[name=what]', 'reset');
  await page.waitForFunction(() => document.querySelectorAll('[data-testid=history] tr[data-id]').length === 1);
  assert.equal(await history().locator('td.source').textContent(), 'loader');
  await page.selectOption('[data-testid=history-filters] select[name=what]', '');
  await page.fill('[data-testid=history-filters] input[name=who]', 'nobody');
  await page.waitForSelector('[data-testid=history]:has-text("Nothing matches the filter.")');
  await page.fill('[data-testid=history-filters] input[name=who]', '');
  await page.waitForFunction(() => document.querySelectorAll('[data-testid=history] tr[data-id]').length === 2);
  // The warning is closed with its only button, and the history says so.
  await active().first().locator('button[data-solution=close]').click();
  await page.waitForFunction(() => document.querySelectorAll('[data-testid=history] tr[data-id]').length === 3);
});
