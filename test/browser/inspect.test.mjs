// End-to-end test of the operator panel as a message client of an inspection block
// (seed 004's Send Message logic): a cell with one block on a simulated PLC (the
// Erlang module cell_inspect_demo, driven through its standard input) and the page in
// Debian's headless chromium. The PLC sends a message; the page shows it with the
// answers it offers; an operator answers; the PLC reads MessageStatus and
// MessageResult. Every wait has a deadline; nothing sleeps.
import { test } from 'node:test';
import assert from 'node:assert/strict';
import { join } from 'node:path';
import { DemoCell, openPages, artifacts, WAIT } from './demo_cell.mjs';

// A command's answer comes once done (the demo waits with its own deadline).
const cell = new DemoCell({ main: 'cell_inspect_demo:main()', cmdWait: WAIT + 5000 });
let page;
openPages(cell, (p) => { page = p; });

const shot = (name) => page.screenshot({ path: join(artifacts, `${name}.png`) });
const message = (id) => page.locator(`.plc-message[data-block="line1"]`, { hasText: id });

async function login(user, password) {
  await page.click('#user-button');
  await page.fill('#login-user', user);
  await page.fill('#login-password', password);
  await page.click('#login-submit');
  await page.waitForSelector(`#user-button:has-text("${user} (${user})")`);
}

test('a PLC message shows on the panel; without a login it cannot be answered', async () => {
  await page.goto(cell.url);
  await page.waitForSelector('#link.up');
  await cell.cmd('send 7');
  const item = message('Is the label on the left side?');
  await item.waitFor();
  assert.deepEqual(await item.locator('button').allTextContents(), ['Yes', 'No']);
  for (const b of await item.locator('button').all()) assert.equal(await b.isDisabled(), true);
  await cell.cmd('await message_status 1');
  await shot('inspect-01-message');
});

test('an operator answers Yes: the PLC reads AffirmativeResponse', async () => {
  await login('operator', 'operator');
  const item = message('Is the label on the left side?');
  await item.locator('button[data-answer=yes]').click();
  await item.waitFor({ state: 'detached' });
  await page.waitForSelector('[data-testid=plc-messages]', { state: 'hidden' });
  await cell.cmd('await message_status 5');
});

test('a text answer goes to MessageResult, within the length the PLC holds', async () => {
  await cell.cmd('send 8');
  const item = message('Batch number of the glue');
  await item.waitFor();
  const input = item.locator('[data-testid=plc-answer-text]');
  assert.equal(await input.getAttribute('maxlength'), '48');
  await input.fill('LOT 4711');
  await shot('inspect-02-text');
  await item.locator('button[data-answer=text]').click();
  await item.waitFor({ state: 'detached' });
  await cell.cmd('await message_result LOT 4711');
  await cell.cmd('await message_status 5');
});

test('Cancel answers a text question negatively: NegativeResponse', async () => {
  await cell.cmd('send 8');
  const item = message('Batch number of the glue');
  assert.deepEqual(await item.locator('button').allTextContents(), ['OK', 'Cancel']);
  await item.locator('button[data-answer=no]').click();
  await item.waitFor({ state: 'detached' });
  await cell.cmd('await message_status 6');
});

test('the last panel page closing is the last client leaving: NoAvailableClients', async () => {
  await cell.cmd('send 7');
  await message('Is the label on the left side?').waitFor();
  await page.goto('about:blank');
  await cell.cmd('await message_status 3');
});
