// What the browser tests of the panel share: a demo cell (an Erlang module's main/0,
// cell_web_demo by default, driven through its standard input, each command answered
// once the cell has taken it), Debian's headless chromium at 1024x768 with touch,
// logging in and out, screenshots, the REST API as the page calls it. Every wait has
// a deadline; nothing sleeps.
import { before, after } from 'node:test';
import assert from 'node:assert/strict';
import { spawn } from 'node:child_process';
import { createInterface } from 'node:readline';
import { mkdtempSync, readdirSync, rmSync, mkdirSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { join } from 'node:path';
import { chromium } from 'playwright-core';

export const top = process.env.CELLRT_TOP;
export const artifacts = join(top, 'test', 'browser', 'artifacts');
export const docs = join(top, 'docs', 'panel');
export const WAIT = 15000;          // generous: the machine is shared with other builds

// main: the demo's entry point; root: its cell root folder (default a new temporary
// one, removed at the end); cmdWait: how long a command may take.
export class DemoCell {
  constructor({ main = 'cell_web_demo:main()', root, cmdWait = WAIT } = {}) {
    this.main = main;
    this.fixedRoot = root;
    this.cmdWait = cmdWait;
  }

  async start() {
    const libs = join(top, '_build', 'default', 'lib');
    const paths = readdirSync(libs).map((a) => join(libs, a, 'ebin'));
    paths.push(process.env.CELLRT_BROWSER_EBIN);
    this.root = this.fixedRoot || mkdtempSync(join(tmpdir(), 'cellrt-pages-'));
    this.proc = spawn('erl', ['-noshell', ...paths.flatMap((p) => ['-pa', p]),
                              '-eval', this.main],
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
    const answer = this.expect((l) => l.endsWith(' ' + text) && /^(OK|ERR) /.test(l), this.cmdWait);
    this.proc.stdin.write(text + '\n');
    const line = await answer;
    assert.ok(line.startsWith('OK '), line);
  }

  async stop() {
    if (!this.proc) return;
    const exited = new Promise((resolve) => this.proc.once('exit', resolve));
    this.proc.stdin.end('quit\n');
    await exited;
    if (!this.fixedRoot) rmSync(this.root, { recursive: true, force: true });
  }
}

// The cell started and a browser opened before the file's tests, both closed after;
// `ready(page)' is given the page (and awaited, when it returns a promise).
export function openPages(cell, ready) {
  let b;
  before(async () => {
    await cell.start();
    b = await browser();
    await ready(b.page);
  });
  after(async () => {
    if (b) await b.close();
    await cell.stop();
  });
}

// A browser with one page, and how to close it.
export async function browser() {
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
  const close = async () => {
    await context.close();
    rmSync(profile, { recursive: true, force: true });
  };
  return { context, page, close };
}

// The cell's panel loaded in the page, connected live.
export async function openPanel(page, cell) {
  await page.goto(cell.url);
  await page.waitForSelector('#link.up');
}

// A user logs in (the demo accounts' passwords are their names).
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

// A screenshot in the run's artifacts/; with docName, the page's picture in
// docs/panel/ too, but only when CELLRT_PANEL_PICTURES=1 (the pictures the README
// shows are taken on purpose, a test run leaves the checkout as it was).
const panelPictures = process.env.CELLRT_PANEL_PICTURES === '1';

export async function shot(page, name, docName) {
  mkdirSync(artifacts, { recursive: true });
  await page.screenshot({ path: join(artifacts, `${name}.png`) });
  if (docName && panelPictures) {
    mkdirSync(docs, { recursive: true });
    await page.screenshot({ path: join(docs, `${docName}.png`) });
  }
}

// A REST call from the page, as the page makes it (session cookie, CSRF token):
// {status, body}.
export function call(page, method, path, body) {
  return page.evaluate(async ([m, p, b]) => {
    try {
      return { status: 200, body: await window.cellPanel.api(m, p, b) };
    } catch (e) {
      return { status: e.status, code: e.code, message: e.message };
    }
  }, [method, path, body]);
}

// What the page's own session may fetch, as JSON.
export const fetchJson = (page, path) =>
  page.evaluate((p) => fetch(p).then((r) => r.json()), path);
