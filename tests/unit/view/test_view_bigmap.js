// A 1 M-voxel map opened over the Foxglove protocol at vlff-view's default
// --max-queue-mb and at --max-queue-mb 4 (issue 53's target), against view_fixture's
// "big" map (every voxel of a 128x128x64 block occupied, no learner):
// - a late client subscribed to /map/points alone (ws, subprotocol
//   foxglove.websocket.v1) receives every occupied voxel exactly once, each point
//   its voxel's centre, label, confidence and opacity, in pieces of at most 1 MiB,
//   and is not dropped;
// - a client subscribed to /map/points, /map/voxels and /map at once gets every
//   voxel once on each, without a drop, each channel in pieces of at most 1 MiB:
//   /map (JSON cubes, about 190 bytes a voxel), /map/voxels (about 14 bytes a
//   voxel: 13 MB, one message of it would not fit 4 MiB), numbered, the first full;
// - the same client of a second viewer with --max-queue-mb 4, below the whole
//   map's voxels alone, gets it too, in pieces of at most 512 KiB.
'use strict';
const assert = require('assert');
const { spawn } = require('child_process');
const fs = require('fs');
const os = require('os');
const path = require('path');
const { FoxgloveClient } = require('@foxglove/ws-protocol');
const WebSocket = require('ws');
const protobuf = require('protobufjs');
const { prog, ok, plan } = require('./demo');

const fixture = process.env.VLFF_VIEW_FIXTURE;
const protoDir = `${process.env.VLFF_SOURCE_DIR}/node/view/proto`;
const dir = fs.mkdtempSync(path.join(os.tmpdir(), 'vlff-view-big-'));
const tag = `vb${process.pid}`;
const names = { map: `/${tag}-map`, frames: `/${tag}-frames`, prompts: `/${tag}-prompts` };
const procs = [];
process.on('exit', () => {
  procs.forEach((p) => { if (p.exitCode === null) p.kill('SIGKILL'); });
  for (const n of Object.values(names)) try { fs.unlinkSync(`/dev/shm${n}`); } catch (e) { /* gone */ }
});

const root = new protobuf.Root();
root.resolvePath = (origin, target) => (target.startsWith('google/') ? target : `${protoDir}/${target}`);
root.loadSync(['foxglove/PointCloud.proto'], { keepCase: true });
root.resolveAll();
const PointCloud = root.lookupType('foxglove.PointCloud');

function startFixture() {
  const p = spawn(fixture, [names.map, names.frames, dir, 'big'], { stdio: ['pipe', 'pipe', 'inherit'] });
  procs.push(p);
  p.ready = new Promise((resolve, reject) => {
    let text = '';
    p.stdout.on('data', (d) => { text += d; if (text.includes('map 1\n')) resolve(); });
    p.on('exit', (code) => reject(new Error(`view_fixture exited ${code}`)));
  });
  return p;
}

function startView(args = [], log = 'view.log') {
  const p = spawn(prog.view, ['--port', '0', '--map', names.map, '--frames', names.frames, '--prompts', names.prompts,
    ...args],
    { stdio: ['ignore', 'pipe', fs.openSync(`${dir}/${log}`, 'w')] });
  procs.push(p);
  p.port = new Promise((resolve, reject) => {
    let text = '';
    p.stdout.on('data', (d) => {
      text += d;
      const m = /serving http:\/\/127\.0\.0\.1:(\d+)\//.exec(text);
      if (m) resolve(Number(m[1]));
    });
    p.on('exit', (code) => reject(new Error(`vlff-view exited ${code}`)));
  });
  p.exited = new Promise((resolve) => p.on('exit', (code) => resolve(code)));
  return p;
}

// A client of topics that reads as messages come: on(topic, bytes) per message;
// closed holds the close code and reason once the server closes it.
function client(port, topics, on) {
  const ws = new WebSocket(`ws://127.0.0.1:${port}/`, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
  const c = new FoxgloveClient({ ws });
  const bySub = {}, out = { closed: null, close: () => c.close() };
  ws.on('close', (code, reason) => { out.closed = { code, reason: String(reason) }; });
  c.on('advertise', (cs) => {
    for (const ch of cs) if (topics.includes(ch.topic)) bySub[c.subscribe(ch.id)] = ch;
  });
  c.on('message', ({ subscriptionId, data }) => {
    on(bySub[subscriptionId].topic, Buffer.from(data.buffer, data.byteOffset, data.byteLength));
  });
  return out;
}

// Waits for cond(), failing after ms or when the client was closed.
function until(cl, cond, ms, what) {
  return new Promise((resolve, reject) => {
    const t0 = Date.now();
    const look = () => {
      if (cond()) return resolve();
      if (cl.closed) return reject(new Error(`${what}: closed ${cl.closed.code} "${cl.closed.reason}"`));
      if (Date.now() - t0 > ms) return reject(new Error(`timed out: ${what}`));
      setTimeout(look, 20);
    };
    look();
  });
}

// Per voxel the number of times a point named it; every point checked against the map.
function pointsInto(seen, map, bytes, bound) {
  assert.ok(bytes.length <= bound, `a /map/points piece of ${bytes.length} bytes, above ${bound}`);
  const m = PointCloud.decode(new Uint8Array(bytes.buffer, bytes.byteOffset, bytes.byteLength));
  assert.strictEqual(m.point_stride, 20);
  const d = Buffer.from(m.data.buffer, m.data.byteOffset, m.data.byteLength);
  const [nx, ny, nz] = map.dims;
  for (let p = 0; p < d.length; p += 20) {
    const c = [d.readFloatLE(p), d.readFloatLE(p + 4), d.readFloatLE(p + 8)];
    const ijk = c.map((x, a) => Math.round((x - map.origin[a]) / map.voxel_size - 0.5));
    assert.ok(ijk.every((v, a) => v >= 0 && v < [nx, ny, nz][a]), `a point ${c} outside the map`);
    for (let a = 0; a < 3; a++) {
      assert.ok(Math.abs(c[a] - (map.origin[a] + (ijk[a] + 0.5) * map.voxel_size)) < 1e-4, `voxel centre ${c}`);
    }
    const idx = ijk[0] + nx * (ijk[1] + ny * ijk[2]);
    assert.deepStrictEqual([d.readUInt16LE(p + 16), d[p + 18], d[p + 15]], [map.labels[idx], map.confidence[idx], 255],
      `voxel ${ijk}: label, confidence, alpha`);
    seen[idx]++;
  }
}

// The voxels of a piece of a whole /map/voxels message (index, label, confidence
// triples), the piece numbered in a row, the first one full.
function voxelsInto(seen, map, bytes, bound, piece) {
  assert.ok(bytes.length <= bound, `a /map/voxels piece of ${bytes.length} bytes, above ${bound}`);
  const m = JSON.parse(bytes.toString('utf8'));
  assert.deepStrictEqual([m.piece, m.full], [piece, piece === 0], 'the pieces of a whole /map/voxels message');
  for (let i = 0; i < m.voxels.length; i += 3) {
    const idx = m.voxels[i];
    assert.deepStrictEqual([m.voxels[i + 1], m.voxels[i + 2]], [map.labels[idx], map.confidence[idx]], `voxel ${idx}`);
    seen[idx]++;
  }
  return m;
}

// The cubes of a /map piece (a SceneUpdate of brick entities), each its voxel's centre.
function cubesInto(seen, map, bytes, bound, first) {
  assert.ok(bytes.length <= bound, `a /map piece of ${bytes.length} bytes, above ${bound}`);
  const m = JSON.parse(bytes.toString('utf8'));
  // the first piece clears what an earlier map left; later ones only add bricks
  assert.deepStrictEqual(m.deletions.map((d) => d.type), first ? [1] : [], 'the deletions of a whole scene');
  const [nx, ny] = map.dims;
  for (const e of m.entities) {
    for (const c of e.cubes) {
      const p = [c.pose.position.x, c.pose.position.y, c.pose.position.z];
      const ijk = p.map((x, a) => Math.round((x - map.origin[a]) / map.voxel_size - 0.5));
      p.forEach((x, a) => assert.ok(Math.abs(x - (map.origin[a] + (ijk[a] + 0.5) * map.voxel_size)) < 1e-3, `cube ${p}`));
      seen[ijk[0] + nx * (ijk[1] + ny * ijk[2])]++;
    }
  }
}

// Every voxel of the map (all occupied) named once.
function once(seen, what) {
  let missing = 0, twice = 0;
  for (const s of seen) { if (s === 0) missing++; else if (s > 1) twice++; }
  assert.deepStrictEqual([missing, twice], [0, 0], `${what}: voxels missing, voxels more than once`);
}

// A client of /map/points, /map/voxels and /map at once gets every voxel exactly
// once on each, in pieces of at most bound bytes, and is not dropped.
async function threeChannels(port, map, bound, what) {
  const n = map.labels.length;
  const seenB = new Uint8Array(n), seenV = new Uint8Array(n), seenS = new Uint8Array(n);
  let gotB = 0, gotV = 0, gotS = 0, scenes = 0, voxelPieces = 0, occupied = -1, voxelBytes = 0, pieces = 0;
  const sum = (a) => a.reduce((s, x) => s + x, 0);
  const b = client(port, ['/map/points', '/map/voxels', '/map'], (topic, bytes) => {
    if (topic === '/map/points') { pointsInto(seenB, map, bytes, bound); gotB = sum(seenB); }
    else if (topic === '/map/voxels') {
      const m = voxelsInto(seenV, map, bytes, bound, voxelPieces++);
      [occupied, pieces] = [m.occupied, m.pieces];
      gotV = sum(seenV);
      voxelBytes += bytes.length;
    } else { cubesInto(seenS, map, bytes, bound, !scenes++); gotS = sum(seenS); }
  });
  await until(b, () => gotB >= n && gotV >= n && gotS >= n, 120000, `${what}: the whole map on the three map channels`);
  once(seenB, '/map/points beside /map/voxels and /map');
  once(seenV, '/map/voxels');
  once(seenS, '/map');
  assert.strictEqual(occupied, n, '/map/voxels counts the occupied voxels');
  assert.strictEqual(voxelPieces, pieces, 'as many /map/voxels pieces as each says');
  assert.strictEqual(b.closed, null, `${what}: the client of the three map channels still open`);
  ok(`${what}: /map/points, /map/voxels and /map together: every voxel once on each (/map in ${scenes} pieces, ` +
    `/map/voxels ${voxelBytes} bytes in ${voxelPieces} pieces, each of at most ${bound} bytes), no drop`);
  b.close();
}

async function main() {
  assert.ok(fixture, 'VLFF_VIEW_FIXTURE must name view_fixture (ctest sets it)');
  const fx = startFixture();
  await fx.ready;
  const map = JSON.parse(fs.readFileSync(`${dir}/map-1.json`, 'utf8'));
  const n = map.labels.length;
  assert.ok(n >= 1000000 && map.labels.every((l) => l < 65534), `${n} voxels, every one occupied`);
  const view = startView(); // the default --max-queue-mb
  const port = await view.port;
  const bound = 1048576;

  // the map is read before anyone subscribes: this client is a late one
  const seenA = new Uint8Array(n);
  let got = 0, pieces = 0;
  const a = client(port, ['/map/points'], (topic, bytes) => {
    pointsInto(seenA, map, bytes, bound);
    pieces++;
    got = seenA.reduce((s, x) => s + x, 0);
  });
  await until(a, () => got >= n, 60000, 'the whole map on /map/points');
  once(seenA, '/map/points');
  assert.strictEqual(a.closed, null, 'the /map/points client still open');
  ok(`/map/points at the default --max-queue-mb: ${n} occupied voxels to a late client, each once with its ` +
    `centre, label and confidence, in ${pieces} pieces of at most ${bound} bytes, no drop`);

  await threeChannels(port, map, bound, 'the default --max-queue-mb');
  // a second viewer with --max-queue-mb 4: the whole map's voxels alone (13 MB) exceed it
  const view4 = startView(['--max-queue-mb', '4'], 'view4.log');
  await threeChannels(await view4.port, map, (4 << 20) / 8, '--max-queue-mb 4');
  view4.kill('SIGINT');
  assert.strictEqual(await view4.exited, 0);
  a.close();
  fx.stdin.end();
  view.kill('SIGINT');
  assert.strictEqual(await view.exited, 0);
  plan();
  fs.rmSync(dir, { recursive: true, force: true });
}

main().catch((e) => {
  console.log(`not ok - ${e.stack}`);
  for (const l of ['view.log', 'view4.log']) try { console.log(fs.readFileSync(`${dir}/${l}`, 'utf8')); } catch (x) { /**/ }
  process.exit(1);
});
