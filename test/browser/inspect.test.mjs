// End-to-end test of the operator panel as a message client of an inspection block
// (seed 004's Send Message logic): a cell with one block on a simulated PLC (the
// Erlang module cell_inspect_demo, driven through its standard input) and the page in
// Debian's headless chromium. The PLC sends a message; the page shows it with the
// answers it offers; an operator answers; the PLC reads MessageStatus and
// MessageResult. Every wait has a deadline; nothing sleeps.
import { test, before, after } from 'node:test';
import assert from 'node:assert/strict';
import { spawn } from 'node:child_process';
import { createInterface } from 'node:readline';
import { mkdtempSync, readdirSync, rmSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { join } from 'node:path';
import { chromium } from 'playwright-core';

const top = process.env.CELLRT_TOP;
const artifacts = join(top, 'test', 'browser', 'artifacts');
const WAIT = 15000;

class Cell {
  async start() {
    const libs = join(top, '_build', 'default', 'lib');
    const paths = readdirSync(libs).map((a) => join(libs, a, 'ebin'));
    paths.push(process.env.CELLRT_BROWSER_EBIN);
    this.root = mkdtempSync(join(tmpdir(), 'cellrt-inspect-'));
    this.proc = spawn('erl', ['-noshell', ...paths.flatMap((p) => ['-pa', p]),
                              '-eval', 'cell_inspect_demo:main()'],
                      { env: { ...process.env, CELLRT_ROOT: this.root },
                        stdio: ['pipe', 'pipe', 'inherit'] });
    this.waiters = [];
    this.lines = createInterface({ input: this.proc.stdout });
    this.lines.on('line', (line) => {
      const i = this.waiters.findIndex((w) => w.match(line));
      if (i >= 0) this.waiters.splice(i, 1)[0].resolve(line);
    });
    const first = await this.expect((l) => l.startsWith('PORT '), 60000);
    this.url = `http://127.0.0.1:${Number(first.split(' ')[1])}/`;
  }

  expect(match, ms = WAIT) {
    return new Promise((resolve, reject) => {
      const timer = setTimeout(() => reject(new Error('the cell did not answer in time')), ms);
      this.waiters.push({ match, resolve: (l) => { clearTimeout(timer); resolve(l); } });
    });
  }

  // A command; its answer comes once done (the demo waits with its own deadline).
  async cmd(text) {
    const answer = this.expect((l) => l.endsWith(' ' + text) && /^(OK|ERR) /.test(l), WAIT + 5000);
    this.proc.stdin.write(text + '\n');
    const line = await answer;
    assert.ok(line.startsWith('OK '), line);
  }

  async stop() {
    if (!this.proc) return;
    const exited = new Promise((resolve) => this.proc.once('exit', resolve));
    this.proc.stdin.end('quit\n');
    await exited;
    rmSync(this.root, { recursive: true, force: true });
  }
}

const cell = new Cell();
let context;
let page;
let profile;

before(async () => {
  await cell.start();
  profile = mkdtempSync(join(tmpdir(), 'cellrt-chromium-'));
  context = await chromium.launchPersistentContext(profile, {
    executablePath: '/usr/bin/chromium',
    headless: true,
    args: ['--no-sandbox', '--disable-gpu', '--disable-background-networking',
           '--disable-component-update', '--disable-sync', '--no-first-run'],
    viewport: { width: 1024, height: 768 },
    hasTouch: true,
  });
  page = context.pages()[0] || await context.newPage();
  page.setDefaultTimeout(WAIT);
});

after(async () => {
  if (context) await context.close();
  await cell.stop();
  if (profile) rmSync(profile, { recursive: true, force: true });
});

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
