// vlff-view's own page in headless Chromium against a running demo: served with a
// self-only Content-Security-Policy that it never violates, loading nothing from
// another origin; the voxels drawn where the map has them, in their prompts' colours
// (screenshot pixels); the voxel under the cursor as vlff-shm label names it; the
// status numbers as vlff-shm stat prints them; the camera and label images; a
// prompt set posted from the page's editor changing the node's prompts; and, from a
// second vlff-view without a token, the editor hidden and disabled.
'use strict';
const assert = require('assert');
const fs = require('fs');
const { spawn } = require('child_process');
const { chromium } = require('playwright-core');
const { start, shm, sleep, waitVersion, learnerOfStat, prog, ok, plan, check } = require('./demo');
const png = require('./png');

const TOKEN = 'page-test-token';

// Hue (degrees) of an sRGB colour after linearising: white light scales the linear
// channels alike, so shading keeps this hue while it changes the brightness.
function hue([r, g, b]) {
  const lin = (c) => { c /= 255; return c <= 0.04045 ? c / 12.92 : ((c + 0.055) / 1.055) ** 2.4; };
  [r, g, b] = [lin(r), lin(g), lin(b)];
  const mx = Math.max(r, g, b), mn = Math.min(r, g, b), d = mx - mn;
  if (d <= 1e-6) return NaN;
  const h = mx === r ? ((g - b) / d) % 6 : mx === g ? (b - r) / d + 2 : (r - g) / d + 4;
  return (h * 60 + 360) % 360;
}
const hexRgb = (hex) => [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16));
const hueDist = (a, b) => Math.min(Math.abs(a - b), 360 - Math.abs(a - b));
const statOf = (demo) => {
  const s = shm('stat', demo.names.map);
  return { version: /^version (\d+)$/m.exec(s)[1], generation: /^generation (\d+)$/m.exec(s)[1],
    dims: /^grid_dims (.*)$/m.exec(s)[1].split(' ').join(' x '), alive: /^writer_alive (.*)$/m.exec(s)[1],
    prompts: [...s.matchAll(/^prompt \d+ (.*)$/gm)].map((m) => m[1]) };
};

let plain = null; // the viewer without a token

// Polls fn in the page until it returns something true. Playwright's waitForFunction
// polls with new Function inside the page, which the page's Content-Security-Policy
// (no 'unsafe-eval') rightly refuses; evaluate() is no eval.
async function pageUntil(page, fn, ms = 30000) {
  const t0 = Date.now();
  while (!(await page.evaluate(fn))) {
    if (Date.now() - t0 > ms) throw new Error(`timed out after ${ms} ms: ${fn}`);
    await sleep(100);
  }
}

async function main() {
  // The learner at one core: on a 2-core machine the headless browser's
  // input and drawing need the other. --max-queue-mb 0.5: map pieces of at most
  // 64 KiB, so that the page draws /map/voxels from several pieces a version.
  const demo = await start({ token: TOKEN, cpuBudget: 1, viewArgs: ['--max-queue-mb', '0.5'] });
  const browser = await chromium.launch({ executablePath: process.env.VLFF_CHROMIUM || 'chromium',
    args: ['--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--no-sandbox'] });
  await check(demo, async () => {
    await waitVersion(demo, 2, 240000);
    const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
    const errors = [];
    page.on('pageerror', (e) => errors.push(e.message));
    page.on('console', (m) => { if (m.type() === 'error') errors.push(m.text()); });
    // every request the page makes, its WebSocket included, and every CSP violation
    const host = new URL(demo.url).host, requested = [], foreign = [];
    page.on('request', (r) => {
      const u = new URL(r.url());
      requested.push(u.pathname);
      if (u.protocol !== 'http:' || u.host !== host) foreign.push(r.url());
    });
    page.on('websocket', (w) => {
      const u = new URL(w.url());
      if (u.protocol !== 'ws:' || u.host !== host) foreign.push(w.url());
    });
    await page.addInitScript(() => {
      window.cspViolations = [];
      document.addEventListener('securitypolicyviolation',
        (e) => window.cspViolations.push(`${e.violatedDirective} ${e.blockedURI}`));
    });
    const resp = await page.goto(demo.url);
    const csp = resp.headers()['content-security-policy'] || '';
    assert.ok(/(^|; )default-src 'self'/.test(csp) && /script-src 'self'(;|$)/.test(csp) &&
      /connect-src 'self'/.test(csp) && !/unsafe|data:|\*/.test(csp), `the page's CSP: "${csp}"`);
    await pageUntil(page, () => document.body.dataset.version && document.querySelectorAll('#legend li').length, 60000);
    await pageUntil(page, () => document.getElementById('s-frames').textContent !== '-', 30000);
    for (const f of ['/', '/view.js', '/view.css', '/three/three.module.js', '/three/addons/OrbitControls.js'])
      assert.ok(requested.includes(f), `the page loaded ${f}: ${requested}`);
    assert.deepStrictEqual(foreign, [], 'requests to other origins');
    assert.deepStrictEqual(await page.evaluate(() => window.cspViolations), [], 'CSP violations');
    ok(`the page, served with a self-only CSP ("${csp.split(';')[0]}; ..."), loads three.js from the viewer ` +
      `(${requested.length} requests, all same-origin, no violation), connects and draws a map version`);

    // The voxels under their own screen points, drawn in their prompts' colours.
    // The learner is paused meanwhile: a software-rendered screenshot may take
    // longer than the map's publish period.
    // The node publishes what its first keyframes saw at once: wait for a map
    // with voxels enough to probe before pausing it.
    await pageUntil(page, () => window.vlff.map.vox.size >= 300, 60000);
    demo.pause();
    await sleep(1500);
    // the paused map put together from its pieces: as many voxels as the status counts occupied
    await pageUntil(page, () => window.vlff.map.vox.size === Number(document.getElementById('s-occupied').textContent),
      10000);
    let checked = 0, shot = null;
    for (let attempt = 0; attempt < 10; attempt++) {
      checked = 0;
      await page.mouse.move(0, 0);
      const probe = await page.evaluate(() => {
        window.vlff.render(); // the drawing buffer holds this version's mesh
        const out = [], keys = [...window.vlff.map.vox.keys()];
        // many candidates: most voxels of a small map hide behind others
        for (let n = 0; n < 4000 && out.length < 25; n++) {
          const idx = keys[Math.floor(Math.random() * keys.length)], s = window.vlff.screenOf(idx);
          const hit = window.vlff.pickAt(s.x, s.y);
          if (hit && hit.idx === idx && s.x > 5 && s.y > 40 && s.x < 930 && s.y < 795)
            out.push({ idx, x: Math.round(s.x), y: Math.round(s.y), label: hit.label, conf: hit.conf,
              prompt: hit.prompt, color: window.vlff.map.colors[hit.label] });
        }
        return { version: document.body.dataset.version, out };
      });
      shot = await page.screenshot();
      const now = await page.evaluate(() => document.body.dataset.version);
      if (now !== probe.version) continue; // a new version was drawn meanwhile
      const img = png.decode(shot);
      // Most probes must match: an edge pixel or the camera marker may cover a few.
      const misses = [];
      for (const v of probe.out) {
        const h = hue(img.pixel(v.x, v.y)), want = hue(hexRgb(v.color));
        if (hueDist(h, want) < 8) checked++;
        else misses.push(`(${v.x},${v.y}) voxel ${v.idx} hue ${h.toFixed(1)}, prompt ${v.prompt} ${v.color} hue ${want.toFixed(1)}`);
      }
      if (misses.length) console.log(`# ${misses.length} of ${probe.out.length} probes missed: ${misses.join("; ")}`);
      assert.ok(checked >= 0.8 * probe.out.length, `pixels not in their prompt's colour: ${misses.join('; ')}`);
      break;
    }
    demo.resume();
    assert.ok(checked >= 15, `enough visible voxels to check (${checked})`);
    if (process.env.VLFF_VIEW_SCREENSHOT) {
      // For docs/viewer.png: the page live again (writer alive, a label image),
      // not the frozen map the pixel checks need.
      await sleep(6000);
      fs.writeFileSync(process.env.VLFF_VIEW_SCREENSHOT, await page.screenshot());
    }
    ok(`${checked} voxels drawn at their screen points in their prompts' colours (screenshot pixels)`);

    // Hover: the page names the voxel vlff-shm label finds there. The learner is
    // paused again: on a loaded machine each try (pick, move, vlff-shm label) can
    // outlast a publish period, and ten tries all met a new version.
    demo.pause();
    await sleep(1500);
    let hovered = false;
    for (let attempt = 0; attempt < 10 && !hovered; attempt++) {
      const t = await page.evaluate(() => {
        const keys = [...window.vlff.map.vox.keys()];
        for (let n = 0; n < 400; n++) {
          const idx = keys[Math.floor(Math.random() * keys.length)], s = window.vlff.screenOf(idx);
          const h = window.vlff.pickAt(s.x, s.y);
          if (h && h.idx === idx && s.y > 40 && s.x < 930) {
            const m = window.vlff.map, [nx, ny] = m.dims;
            const c = [idx % nx, Math.floor(idx / nx) % ny, Math.floor(idx / (nx * ny))]
              .map((q, a) => (m.origin[a] + (q + 0.5) * m.voxel_size).toFixed(4));
            return { x: s.x, y: s.y, c, version: document.body.dataset.version };
          }
        }
        return null;
      });
      if (!t) continue;
      await page.mouse.move(t.x, t.y);
      const text = await page.textContent('#pick');
      const line = shm('label', demo.names.map, ...t.c);
      const m = /^label (\d+) confidence (\d+) prompt (.*) version (\d+)$/m.exec(line);
      if (m[4] !== t.version || (await page.evaluate(() => document.body.dataset.version)) !== t.version) continue;
      assert.ok(text.startsWith(`label ${m[1]} prompt ${m[3]} confidence ${m[2]} `), `page "${text}", vlff-shm "${line}"`);
      assert.ok(text.endsWith(` map version ${t.version}`), `page "${text}" at version ${t.version}`);
      hovered = true;
    }
    demo.resume();
    assert.ok(hovered, 'a hover at a stable version');
    ok('the voxel under the cursor: label, prompt and confidence as vlff-shm label gives them');
    // the pointer still: a new map version refreshes the text under it
    const hoverVersion = await page.evaluate(() => document.body.dataset.version);
    await page.evaluate((v) => { window.hoverVersion = Number(v); }, hoverVersion);
    await pageUntil(page, () => Number(document.body.dataset.version) > window.hoverVersion + 1, 60000);
    const [pickNow, versionNow] = await page.evaluate(() => [document.getElementById('pick').textContent,
      document.body.dataset.version]);
    assert.ok(pickNow === 'point at a voxel' || pickNow.endsWith(` map version ${versionNow}`),
      `the hover text "${pickNow}" at version ${versionNow}`);
    ok(`the hover text follows the map under a still pointer (version ${hoverVersion} to ${versionNow})`);

    // The learner paused: on a loaded machine the page can be versions behind a
    // node that publishes on; once it stops, the page must catch up and agree.
    demo.pause();
    let same = false, last = '';
    for (let attempt = 0; attempt < 60 && !same; attempt++) {
      const pageStat = await page.evaluate(() => ({
        version: document.getElementById('s-version').textContent, generation: document.getElementById('s-generation').textContent,
        dims: document.getElementById('s-dims').textContent, alive: document.getElementById('s-alive').textContent,
        prompts: [...document.querySelectorAll('#legend li')].map((li) => li.textContent) }));
      const st = statOf(demo);
      // the two are read a moment apart: compare again until they agree
      same = JSON.stringify(pageStat) === JSON.stringify(st);
      last = `page ${JSON.stringify(pageStat)}, vlff-shm stat ${JSON.stringify(st)}`;
      if (!same) await sleep(250);
    }
    demo.resume();
    assert.ok(same, `the page's status and vlff-shm stat: ${last}`);
    ok('status numbers and legend equal vlff-shm stat (version, generation, grid, writer alive, prompts)');

    // The learner's numbers in the panel, the learner paused so that the page and
    // vlff-shm stat show one status update.
    demo.pause();
    let learnerSame = false;
    last = '';
    for (let attempt = 0; attempt < 40 && !learnerSame; attempt++) {
      await sleep(250);
      const l = learnerOfStat(shm('stat', demo.names.map));
      const shown = await page.evaluate(() => {
        const t = (id) => document.getElementById(id).textContent;
        return { updates: document.body.dataset.learnerUpdates, state: t('l-state'), frames_in: t('l-frames_in'),
          frames_lost: t('l-frames_lost'), frames_refused: t('l-frames_refused'), keyframes: t('l-keyframes'),
          iterations: t('l-iterations'), iterations_per_s: t('l-iterations_per_s'), loss: t('l-loss'),
          terms: t('l-terms'), psnr: t('l-psnr'),
          refused: [...document.querySelectorAll('#refusals li')].map((li) => li.textContent) };
      });
      const show = (v) => (v === null ? '-' : String(v));
      const want = { updates: String(l.updates), state: l.state, frames_in: show(l.frames_in),
        frames_lost: show(l.frames_lost), frames_refused: show(l.frames_refused), keyframes: show(l.keyframes),
        iterations: show(l.iterations), iterations_per_s: show(l.iterations_per_s), loss: show(l.loss),
        terms: [l.loss_rgb, l.loss_depth, l.loss_feat].map(show).join(' | '), psnr: show(l.psnr),
        refused: l.refused.filter((r) => r.count).map((r) => `${r.reason}: ${r.count}`) };
      learnerSame = JSON.stringify(shown) === JSON.stringify(want);
      last = `page ${JSON.stringify(shown)}, vlff-shm stat ${JSON.stringify(want)}`;
      if (learnerSame) {
        assert.ok(l.frames_in > 0 && l.keyframes > 0 && l.iterations > 0, `a learning node: ${last}`);
        ok(`learner numbers equal vlff-shm stat (${l.frames_in} frames in, ${l.keyframes} keyframes, ` +
          `${l.iterations} iterations, ${l.iterations_per_s}/s, loss ${l.loss}, PSNR ${l.psnr})`);
      }
    }
    demo.resume();
    assert.ok(learnerSame, `the page's learner numbers and vlff-shm stat: ${last}`);

    // The label image is published when the node renders one, which on a loaded
    // host can come after the learner checks above: wait for both to be drawn.
    await pageUntil(page, () => ['image', 'labels'].every((id) => {
      const c = document.getElementById(id);
      return c.width !== 300 || c.height !== 150; // a canvas's size before its first image
    }), 60000);
    const imgs = await page.evaluate(() => ['image', 'labels'].map((id) => {
      const c = document.getElementById(id), d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
      let lit = 0;
      for (let i = 0; i < d.length; i += 4) lit += d[i] + d[i + 1] + d[i + 2] > 30;
      return { w: c.width, h: c.height, lit: lit / (d.length / 4) };
    }));
    assert.deepStrictEqual(imgs.map((i) => `${i.w}x${i.h}`), ['320x240', '160x120']);
    assert.ok(imgs[0].lit > 0.5 && imgs[1].lit > 0.2, JSON.stringify(imgs));
    ok('camera image and label image drawn beside each other');

    assert.ok(await page.isVisible('#editor'), 'the editor shows when a token is configured');
    assert.ok(await page.isEnabled('#editor button'), 'and can be used');
    // The learner paused for the clicks (the viewer answers them itself, and
    // the post waits in the mailbox): while the map changes, a software-rendered
    // page on a loaded 2-core machine can be too busy redrawing to take a
    // click within its 30 s.
    demo.pause();
    await page.fill('#prompts', 'chair\ntable\nwall');
    await page.fill('#token', 'not-the-token');
    await page.click('#editor button');
    await pageUntil(page, () => /wrong or missing token/.test(document.getElementById('msg').textContent));
    await page.fill('#token', TOKEN);
    try {
      await page.click('#editor button');
    } finally {
      demo.resume();
    }
    // the viewer answers "posted ... waiting for the learner's answer" at once and the
    // learner's acceptance when it comes: the page shows the last
    await pageUntil(page, () => /accepted by the learner/.test(document.getElementById('msg').textContent), 60000);
    const t0 = Date.now();
    while (statOf(demo).prompts.join() !== 'chair,table,wall') {
      assert.ok(Date.now() - t0 < 60000, `the node took the posted prompts: ${statOf(demo).prompts}`);
      await sleep(200);
    }
    await pageUntil(page, () => [...document.querySelectorAll('#legend li')].map((li) => li.textContent).join() ===
      'chair,table,wall', 30000);
    ok('a prompt set posted from the page (wrong token refused first) is accepted by the learner and becomes the map\'s prompts and legend');
    assert.deepStrictEqual(foreign, [], 'requests to other origins');
    assert.deepStrictEqual(await page.evaluate(() => window.cspViolations), [], 'CSP violations');
    assert.deepStrictEqual(errors, [], 'no errors in the page');

    // A second viewer on the same map without --token-file: no editor to use.
    // The first page closed and the learner paused (to the end): a second
    // software-rendered page beside a drawing one and a learning node on a
    // loaded 2-core machine did not answer isVisible within 30 s.
    await page.close();
    demo.pause();
    const port = await new Promise((resolve, reject) => {
      plain = spawn(prog.view, ['--port', '0', '--map', demo.names.map, '--frames', demo.names.frames,
        '--max-clients', '1'],
        { stdio: ['ignore', 'pipe', 'ignore'] });
      let text = '';
      plain.stdout.on('data', (d) => {
        text += d;
        const m = /serving http:\/\/127\.0\.0\.1:(\d+)\//.exec(text);
        if (m) resolve(Number(m[1]));
      });
      plain.on('exit', (code) => reject(new Error(`vlff-view without a token exited ${code}`)));
    });
    const page2 = await browser.newPage();
    await page2.goto(`http://127.0.0.1:${port}/`);
    await pageUntil(page2, () => document.body.dataset.version, 60000);
    assert.ok(!(await page2.isVisible('#editor')), 'no editor without a token');
    assert.ok(await page2.isDisabled('#editor button') && await page2.isDisabled('#prompts'), 'its fields disabled');
    ok('from a viewer without a token the prompt editor is hidden and disabled');
  }, async () => {
    await browser.close();
    if (plain && plain.exitCode === null) plain.kill('SIGINT');
  });
  plan();
}
main();
