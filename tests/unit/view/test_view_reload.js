// The page's reload after a refused connection backs off, in headless Chromium
// against a vlff-view alone (no segments needed) whose one client slot
// (--max-clients 1) another client holds: each refused load (503) schedules the
// next after 3 s, then 6 s (the page reloads itself after the first), doubling up to
// 60 s and staying there; once a slot is free the page connects and the wait
// starts over at 3 s.
'use strict';
const assert = require('assert');
const { spawn } = require('child_process');
const fs = require('fs');
const os = require('os');
const path = require('path');
const WebSocket = require('ws');
const { chromium } = require('playwright-core');
const { prog, ok, plan, sleep, viewPort } = require('./demo');

const dir = fs.mkdtempSync(path.join(os.tmpdir(), 'vlff-view-reload-'));
const tag = `vr${process.pid}`;
let view = null, browser = null;
process.on('exit', () => { if (view && view.exitCode === null) view.kill('SIGKILL'); });

async function pageUntil(page, fn, ms, what) {
  const t0 = Date.now();
  for (;;) {
    const v = await page.evaluate(fn).catch(() => null); // null while a reload replaces the document
    if (v) return v;
    if (Date.now() - t0 > ms) throw new Error(`timed out after ${ms} ms: ${what}`);
    await sleep(100);
  }
}

const conn = () => document.getElementById('conn').textContent;
const waitText = (page, re, what) => pageUntil(page, `(${conn})().match(${re}) ? (${conn})() : null`, 30000, what);

async function main() {
  view = spawn(prog.view, ['--port', '0', '--max-clients', '1', '--map', `/${tag}-map`, '--frames', '',
    '--prompts', `/${tag}-prompts`], { stdio: ['ignore', 'pipe', fs.openSync(`${dir}/view.log`, 'w')] });
  const port = await viewPort(view, `${dir}/view.log`);
  const url = `http://127.0.0.1:${port}/`;
  // the one slot, held
  const holder = new WebSocket(`ws://127.0.0.1:${port}/`, ['foxglove.websocket.v1']);
  await new Promise((resolve, reject) => { holder.on('open', resolve); holder.on('error', reject); });

  browser = await chromium.launch({ executablePath: process.env.VLFF_CHROMIUM || 'chromium',
    args: ['--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--no-sandbox'] });
  const page = await browser.newPage();
  const loads = [];
  page.on('load', () => loads.push(Date.now()));
  await page.goto(url);
  const first = await waitText(page, /reconnecting in 3 s$/, 'the first refusal');
  assert.strictEqual(await page.evaluate(() => sessionStorage.getItem('vlff-view-retry-s')), '3');
  // the page reloads itself, no sooner than the wait it named
  const second = await waitText(page, /reconnecting in 6 s$/, 'the reload and the second refusal');
  assert.ok(loads.length >= 2, `${loads.length} loads`);
  assert.ok(loads[1] - loads[0] >= 2900, `reloaded ${loads[1] - loads[0]} ms after the first load`);
  ok(`refused twice: "${first}", then after the reload "${second}"`);

  // a page that has waited 32 s waits 60 s next, and 60 s again after that
  const waits = [];
  for (const last of ['32', '60']) {
    await page.evaluate((v) => sessionStorage.setItem('vlff-view-retry-s', v), last);
    await page.reload();
    waits.push(await waitText(page, /reconnecting in \d+ s$/, `a refusal after a wait of ${last} s`));
  }
  assert.match(waits[0], /in 60 s$/);
  assert.match(waits[1], /in 60 s$/);
  ok(`the wait doubles up to 60 s and stays there: ${waits.map((w) => w.replace(/.*in /, '')).join(', ')}`);

  // the slot free: the page connects, and the wait starts over
  holder.close();
  await new Promise((r) => holder.on('close', r));
  for (let i = 0; ; i++) {
    await page.reload();
    const text = await pageUntil(page, `(${conn})().match(/^live$|reconnecting/) ? (${conn})() : null`, 30000,
      'a connection or a refusal');
    if (text === 'live') break;
    // the viewer frees the slot when it sees the holder's close: a refusal before
    // then is answered with another reload
    assert.ok(i < 20, `still refused: ${text}`);
    await sleep(200);
  }
  assert.strictEqual(await page.evaluate(() => sessionStorage.getItem('vlff-view-retry-s')), null);
  ok('with a slot free the page connects ("live") and forgets the wait');
  plan();
}

main().then(async () => {
  await browser.close();
  view.kill('SIGINT');
  fs.rmSync(dir, { recursive: true, force: true });
}).catch(async (e) => {
  console.log(`not ok - ${e.stack}`);
  try { console.log(fs.readFileSync(`${dir}/view.log`, 'utf8')); } catch (x) { /* none */ }
  if (browser) await browser.close();
  process.exit(1);
});
