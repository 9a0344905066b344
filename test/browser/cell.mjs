// What the browser tests of the panel's pages share: the demo cell (the Erlang module
// cell_web_demo, driven through its standard input), Debian's headless chromium at
// 1024x768 with touch, logging in and out, screenshots. Every wait has a deadline;
// nothing sleeps.
import assert from 'node:assert/strict';
import { spawn } from 'node:child_process';
import { createInterface } from 'node:readline';
import { mkdtempSync, mkdirSync, readdirSync, rmSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { join } from 'node:path';
import { chromium } from 'playwright-core';

export const top = process.env.CELLRT_TOP;
export const WAIT = 15000;          // generous: the machine is shared with other builds

export class Cell {
  async start() {
    const libs = join(top, '_build', 'default', 'lib');
    const paths = readdirSync(libs).map((a) => join(libs, a, 'ebin'));
    paths.push(process.env.CELLRT_BROWSER_EBIN);
    // A root of its own: what another test file left is not seen here.
    this.root = mkdtempSync(join(process.env.CELLRT_BROWSER_ROOT ? join(process.env.CELLRT_BROWSER_ROOT, '..') : tmpdir(), 'root-'));
    this.proc = spawn('erl', ['-noshell', ...paths.flatMap((p) => ['-pa', p]),
                              '-eval', 'cell_web_demo:main()'],
                      { env: { ...process.env, CELLRT_ROOT: this.root },
                        stdio: ['pipe', 'pipe', 'inherit'] });
    this.waiters = [];
    this.lines = createInterface({ input: this.proc.stdout });
    this.lines.on('line', (line) => {
      const i = this.waiters.findIndex((w) => w.match(line));
      if (i >= 0) this.waiters.splice(i, 1)[0].resolve(line);
    });
    const first = await this.expect((l) => l.startsWith('PORT '), 60000);
    this.port = Number(first.split(' ')[1]);
    this.url = `http://127.0.0.1:${this.port}/`;
  }

  expect(match, ms = WAIT) {
    return new Promise((resolve, reject) => {
      const timer = setTimeout(() => reject(new Error('the cell did not answer in time')), ms);
      this.waiters.push({ match, resolve: (l) => { clearTimeout(timer); resolve(l); } });
    });
  }

  async cmd(text) {
    const answer = this.expect((l) => l.endsWith(' ' + text) && /^(OK|ERR) /.test(l));
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

// A browser on the cell's panel at 1024x768 with touch.
export async function open(cell) {
  const profile = mkdtempSync(join(tmpdir(), 'cellrt-chromium-'));
  const context = await chromium.launchPersistentContext(profile, {
    executablePath: '/usr/bin/chromium',
    headless: true,
    args: ['--no-sandbox', '--disable-gpu', '--disable-background-networking',
           '--disable-component-update', '--disable-sync', '--no-first-run'],
    viewport: { width: 1024, height: 768 },
    hasTouch: true,
    acceptDownloads: true,
  });
  const page = context.pages()[0] || await context.newPage();
  page.setDefaultTimeout(WAIT);
  await page.goto(cell.url);
  await page.waitForSelector('#link.up');
  return {
    page,
    async close() { await context.close(); rmSync(profile, { recursive: true, force: true }); },
  };
}

export async function login(page, user, password = user) {
  await page.click('#user-button');
  await page.fill('#login-user', user);
  await page.fill('#login-password', password);
  await page.click('#login-submit');
  await page.waitForSelector(`#user-button:has-text("${user} (")`);
}

export async function logout(page) {
  await page.click('#user-button');
  await page.click('[data-testid=logout]');
  await page.waitForSelector('#user-button:has-text("Log in")');
}

// A screenshot kept in docs/panel/ (the panel's pictures in the README) and one in
// artifacts/.
export async function shot(page, name, docs = false) {
  const artifacts = join(top, 'test', 'browser', 'artifacts');
  mkdirSync(artifacts, { recursive: true });
  await page.screenshot({ path: join(artifacts, `${name}.png`) });
  if (docs) await page.screenshot({ path: join(top, 'docs', 'panel', `${name}.png`) });
}

// What the page's own session may fetch, as JSON.
export const fetchJson = (page, path) =>
  page.evaluate((p) => fetch(p).then((r) => r.json()), path);
