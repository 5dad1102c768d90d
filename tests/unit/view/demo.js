// Starts what the viewer's tests run against, as scripts/demo does: vlff-sim
// streaming the synthetic room, vlff-node learning it (unless withNode is false)
// and vlff-view on a free port, all on segment names of their own. stop() ends them.
'use strict';
const { execFile, spawn, spawnSync } = require('child_process');
const fs = require('fs');
const os = require('os');
const path = require('path');

const bin = process.env.VLFF_BINARY_DIR;
const src = process.env.VLFF_SOURCE_DIR;
if (!bin || !src) throw new Error('VLFF_BINARY_DIR and VLFF_SOURCE_DIR must be set (ctest sets them)');
const emu = (process.env.VLFF_EMULATOR || '').split(' ').filter(Boolean);
const prog = { sim: `${bin}/node/sim/vlff-sim`, node: `${bin}/node/vlff-node`, view: `${bin}/node/view/vlff-view`,
  shm: `${bin}/shm/vlff-shm` };

function run(exe, args, log) {
  const out = fs.openSync(log, 'w');
  const argv = [...emu, exe, ...args];
  return spawn(argv[0], argv.slice(1), { stdio: ['ignore', 'pipe', out] });
}

// vlff-shm CLI, synchronously: its stdout.
function shm(...args) {
  const r = spawnSync(prog.shm, args, { encoding: 'utf8' });
  if (r.status !== 0) throw new Error(`vlff-shm ${args.join(' ')}: ${r.stderr}`);
  return r.stdout;
}

// vlff-shm CLI without blocking the event loop (a blocked client stops reading its
// socket, and the viewer would rightly drop it as too slow): its stdout.
function shmAsync(...args) {
  return new Promise((resolve, reject) => {
    execFile(prog.shm, args, { encoding: 'utf8' }, (err, stdout, stderr) => {
      if (err) reject(new Error(`vlff-shm ${args.join(' ')}: ${stderr}`)); else resolve(stdout);
    });
  });
}

const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

// cpuBudget: the node's node.cpu_budget (cores), so that a browser beside it
// on a small machine gets the rest.
// The port a vlff-view started with --port 0 serves on, from its stdout;
// rejects, with its log, if it exits first.
function viewPort(view, log) {
  return new Promise((resolve, reject) => {
    let text = '', port = 0;
    view.stdout.on('data', (d) => {
      text += d;
      const m = /serving http:\/\/127\.0\.0\.1:(\d+)\//.exec(text);
      if (m && !port) resolve(port = Number(m[1]));
    });
    // an exit after it served is the test's own (its log may be gone by then)
    view.on('exit', (code) => port || reject(new Error(`vlff-view exited ${code}: ${fs.readFileSync(log)}`)));
  });
}

async function start({ withNode = true, viewArgs = [], token = null, cpuBudget = 0 } = {}) {
  const dir = fs.mkdtempSync(path.join(os.tmpdir(), 'vlff-view-test-'));
  const tag = `vt${process.pid}`;
  const names = { frames: `/${tag}-frames`, map: `/${tag}-map`, prompts: `/${tag}-prompts` };
  const cfg = fs.readFileSync(`${src}/configs/demo-sim.yaml`, 'utf8')
    .replace(/\/tmp\/vlff-demo\/state/g, `${dir}/state`).replace(/\/vlff-demo-/g, `/${tag}-`)
    .replace(/^node:\n/m, cpuBudget > 0 ? `node:\n  cpu_budget: ${cpuBudget}\n` : 'node:\n');
  fs.writeFileSync(`${dir}/cfg.yaml`, cfg);
  const procs = [];
  procs.push(run(prog.sim, ['--config', `${dir}/cfg.yaml`, '--quiet'], `${dir}/sim.log`));
  const node = withNode ? run(prog.node, ['--config', `${dir}/cfg.yaml`], `${dir}/node.log`) : null;
  if (node) procs.push(node);
  const args = ['--port', '0', '--map', names.map, '--frames', names.frames, '--prompts', names.prompts, ...viewArgs];
  if (token) {
    fs.writeFileSync(`${dir}/token`, `${token}\n`, { mode: 0o600 });
    args.push('--token-file', `${dir}/token`);
  }
  const view = run(prog.view, args, `${dir}/view.log`);
  procs.push(view);
  // however this test ends, it leaves no program running
  process.on('exit', () => procs.forEach((p) => { if (p.exitCode === null) { p.kill('SIGCONT'); p.kill('SIGKILL'); } }));
  const port = await viewPort(view, `${dir}/view.log`);
  const demo = {
    dir, names, port, view, url: `http://127.0.0.1:${port}/`, ws: `ws://127.0.0.1:${port}/`,
    // Freezes the learner (SIGSTOP) so that the map holds one version; resume() goes on.
    pause: () => node.kill('SIGSTOP'),
    resume: () => node.kill('SIGCONT'),
    log: (p) => fs.readFileSync(`${dir}/${p}.log`, 'utf8'),
    async stop(keep = false) {
      if (node && node.exitCode === null) node.kill('SIGCONT');
      for (const p of procs.reverse()) {
        if (p.exitCode === null) {
          p.kill('SIGINT');
          await new Promise((r) => { p.once('exit', r); setTimeout(r, 10000); });
        }
      }
      demo.viewExit = view.exitCode; // 0 after a clean SIGINT (a sanitizer's report makes it non-zero)
      if (!keep) fs.rmSync(dir, { recursive: true, force: true });
      for (const n of Object.values(names).concat([`/${tag}-poses`, `/${tag}-features`])) {
        try { fs.unlinkSync(`/dev/shm${n}`); } catch (e) { /* never created */ }
      }
    },
  };
  return demo;
}

// Waits until the map segment has reached at least version v.
async function waitVersion(demo, v, timeoutMs) {
  const t0 = Date.now();
  for (;;) {
    try {
      const m = /^version (\d+)$/m.exec(shm('stat', demo.names.map));
      if (m && Number(m[1]) >= v) return Number(m[1]);
    } catch (e) { /* not created yet */ }
    if (Date.now() - t0 > timeoutMs) throw new Error(`map version ${v} not reached in ${timeoutMs} ms`);
    await sleep(200);
  }
}

// The learner's status block as `vlff-shm stat` prints it, in the shape of the
// status channel's "learner" object (without its age); null when none was set.
function learnerOfStat(stat) {
  if (/^status none$/m.test(stat)) return null;
  const line = (k) => {
    const m = new RegExp(`^${k} (.*)$`, 'm').exec(stat);
    if (!m) throw new Error(`vlff-shm stat prints no ${k}: ${stat}`);
    return m[1];
  };
  const num = (k) => { const v = line(k); return /nan/i.test(v) ? null : Number(v); };
  const out = { state: line('state'), state_code: num('state_code'), error_flags: parseInt(line('error_flags'), 16),
    updates: num('status_updates'), frames_in: num('frames_in'), frames_lost: num('frames_lost'),
    frames_refused: num('frames_refused'),
    refused: [...stat.matchAll(/^refused (\d+) (.*)$/gm)].map((m) => ({ reason: m[2], count: Number(m[1]) })) };
  for (const k of ['keyframes', 'keyframes_evicted', 'iterations', 'iterations_per_s', 'fps_in', 'loss', 'loss_rgb',
    'loss_depth', 'loss_feat', 'psnr', 'cpu_budget', 'cpu_used', 'frame_to_map_ms_p50', 'frame_to_map_ms_p99',
    'publish_interval_s', 'label_flips', 'label_flips_refresh', 'label_flips_total', 'label_flip_frac',
    'mem_keyframes_mb', 'mem_keyframes_limit_mb', 'mem_evidence_mb', 'mem_evidence_limit_mb', 'mem_field_mb',
    'mem_rss_mb', 'keyframes_paged', 'keyframes_paged_out', 'keyframes_paged_in', 'keyframes_dropped',
    'evidence_paged', 'evidence_paged_out', 'evidence_paged_in', 'evidence_dropped', 'box_growths', 'box_refused',
    'keyframes_page_mb', 'keyframes_page_limit_mb']) out[k] = num(k);
  for (const k of ['box_lo', 'box_hi']) out[k] = line(k).split(' ').map(Number);
  return out;
}

// TAP lines: ok() numbers and prints each check passed, plan() the count at the end.
let passed = 0;
const ok = (what) => { passed++; console.log(`ok ${passed} - ${what}`); };
const plan = () => console.log(`1..${passed}`);

// Runs the async checks against demo. A failure prints TAP's "not ok" with the
// viewer's log, runs close(), stops the demo keeping its logs and exits 1;
// otherwise close() runs and the demo is stopped. Returns the viewer's log as it
// was before the stop.
async function check(demo, checks, close = async () => {}) {
  try {
    await checks();
  } catch (e) {
    console.log(`not ok - ${e.stack}`);
    console.log(demo.log('view'));
    await close();
    await demo.stop(true);
    console.log(`logs kept in ${demo.dir}`);
    process.exit(1);
  }
  await close();
  const log = demo.log('view');
  await demo.stop();
  return log;
}

module.exports = { start, viewPort, shm, shmAsync, sleep, waitVersion, learnerOfStat, prog, ok, plan, check };
