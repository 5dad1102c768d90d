// vlff-view's protobuf channels decoded with the repository's .proto files
// (node/view/proto) by protobufjs, field by field, against what view_fixture
// wrote into the segments (a known map and an RGB-D frame, no learner):
// - the advertised FileDescriptorSets of /map/points, /map/grid and /camera/depth
//   define the same messages as those files (names, numbers, types, labels);
// - /map/points: the whole map in pieces of at most 1/8 of --max-queue-mb, every
//   occupied voxel once with its centre, colour, label and confidence; then a
//   change as its changed voxels; a subscriber that arrives after the change gets
//   the whole current map in pieces, then the next change;
// - /map/grid: per column the highest occupied voxel (label, confidence, colour,
//   elevation), free or unknown columns transparent, and after a change the new one;
// - /camera/depth: a RawImage 16UC1 of the frame's millimetres;
// - the JSON channels' foxglove messages (images, calibration, /tf, /log) name only
//   fields of the .proto files, with values their types take;
// - --record FILE: an existing FILE is refused (exit 1, the file untouched) unless
//   --force, and the recording holds /map/grid and /camera/depth with the same
//   schemas, decoded by the same files.
'use strict';
const assert = require('assert');
const { spawn } = require('child_process');
const fs = require('fs');
const os = require('os');
const path = require('path');
const { FoxgloveClient } = require('@foxglove/ws-protocol');
const WebSocket = require('ws');
const protobuf = require('protobufjs');
require('protobufjs/ext/descriptor');
const { McapIndexedReader } = require('@mcap/core');
const zstd = require('@foxglove/wasm-zstd');
const { prog, ok, plan } = require('./demo');

const fixture = process.env.VLFF_VIEW_FIXTURE;
const protoDir = `${process.env.VLFF_SOURCE_DIR}/node/view/proto`;
const FREE = 65534, UNKNOWN = 65535;
const dir = fs.mkdtempSync(path.join(os.tmpdir(), 'vlff-view-proto-'));
const tag = `vp${process.pid}`;
const names = { map: `/${tag}-map`, frames: `/${tag}-frames`, prompts: `/${tag}-prompts` };
const procs = [];
process.on('exit', () => {
  procs.forEach((p) => { if (p.exitCode === null) p.kill('SIGKILL'); });
  for (const n of Object.values(names)) try { fs.unlinkSync(`/dev/shm${n}`); } catch (e) { /* gone */ }
});
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

// The repository's .proto files, as any protobuf user loads them.
const root = new protobuf.Root();
root.resolvePath = (origin, target) => (target.startsWith('google/') ? target : `${protoDir}/${target}`);
root.loadSync(fs.readdirSync(`${protoDir}/foxglove`).map((f) => `foxglove/${f}`), { keepCase: true });
root.resolveAll();
const T = (name) => root.lookupType(name);

// Decodes bytes as message type t: the object with longs as numbers, enums as numbers.
function decode(t, bytes) {
  const u8 = new Uint8Array(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  return t.toObject(t.decode(u8), { longs: Number, enums: Number, defaults: true });
}

// A message type's fields as "rule type name = id" lines, the types by their
// last name part (a descriptor says ".foxglove.Pose", a .proto "foxglove.Pose").
function shape(t) {
  return t.fieldsArray.map((f) => `${f.repeated ? 'repeated ' : ''}${f.type.split('.').at(-1)} ${f.name} = ${f.id}`)
    .sort();
}

// Every message type a descriptor set defines against the .proto files.
function sameAsProtoFiles(b64) {
  const set = protobuf.descriptor.FileDescriptorSet.decode(Buffer.from(b64, 'base64'));
  const adv = protobuf.Root.fromDescriptor(set);
  let n = 0;
  for (const f of set.file) {
    for (const m of f.messageType) {
      const full = `${f.package}.${m.name}`;
      const mine = adv.lookupType(full), theirs = root.lookupType(full);
      assert.deepStrictEqual(shape(mine), shape(theirs), `${full}: the advertised fields are the .proto file's`);
      for (const e of mine.nestedArray.filter((x) => x instanceof protobuf.Enum)) {
        assert.deepStrictEqual(Object.entries(e.values), Object.entries(theirs.lookupEnum(e.name).values),
          `${full}.${e.name}'s values`);
      }
      n++;
    }
  }
  return n;
}

// A JSON foxglove message against its .proto type: every key a field of the type,
// nested messages likewise, Timestamps as Foxglove's {sec, nsec}; then the object
// (bytes as base64) taken by protobufjs' verify.
function jsonAgainst(t, o, where) {
  for (const [k, v] of Object.entries(o)) {
    const f = t.fields[k];
    assert.ok(f, `${where}.${k}: no field ${k} in ${t.fullName}`);
    f.resolve();
    if (f.resolvedType instanceof protobuf.Type) {
      if (f.resolvedType.fullName === '.google.protobuf.Timestamp') {
        assert.deepStrictEqual(Object.keys(v).sort(), ['nsec', 'sec'], `${where}.${k}: a Foxglove time`);
        o[k] = { seconds: v.sec, nanos: v.nsec };
      } else {
        for (const x of f.repeated ? v : [v]) jsonAgainst(f.resolvedType, x, `${where}.${k}`);
      }
    }
  }
  const err = t.verify(o);
  assert.strictEqual(err, null, `${where}: ${err}`);
}

function startFixture() {
  const p = spawn(fixture, [names.map, names.frames, dir], { stdio: ['pipe', 'pipe', 'inherit'] });
  procs.push(p);
  let text = '';
  const waits = [];
  p.stdout.on('data', (d) => {
    text += d;
    for (const w of waits.splice(0)) if (!w()) waits.push(w);
  });
  p.mapVersion = (v) => new Promise((resolve, reject) => {
    const t = setTimeout(() => reject(new Error(`view_fixture: no map ${v}`)), 30000);
    const w = () => (text.includes(`map ${v}\n`) ? (clearTimeout(t), resolve(), true) : false);
    if (!w()) waits.push(w);
  });
  return p;
}

function startView(args, log) {
  const p = spawn(prog.view, ['--port', '0', '--map', names.map, '--frames', names.frames, '--prompts', names.prompts,
    ...args], { stdio: ['ignore', 'pipe', fs.openSync(`${dir}/${log}`, 'w')] });
  procs.push(p);
  p.port = new Promise((resolve, reject) => {
    let text = '';
    p.stdout.on('data', (d) => {
      text += d;
      const m = /serving http:\/\/127\.0\.0\.1:(\d+)\//.exec(text);
      if (m) resolve(Number(m[1]));
    });
    p.on('exit', (code) => reject(new Error(`vlff-view exited ${code}: ${fs.readFileSync(`${dir}/${log}`)}`)));
  });
  p.port.catch(() => {}); // a run expected to fail is awaited through exited
  p.exited = new Promise((resolve) => p.on('exit', (code) => resolve(code)));
  return p;
}

const mapOf = (v) => JSON.parse(fs.readFileSync(`${dir}/map-${v}.json`, 'utf8'));

// A client subscribed to topics; msgs[topic] the decoded messages with their sizes.
async function client(port, topics) {
  const c = new FoxgloveClient({ ws: new WebSocket(`ws://127.0.0.1:${port}/`, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]) });
  const chans = {}, bySub = {}, msgs = {};
  let waiters = [];
  c.on('advertise', (cs) => {
    for (const ch of cs) {
      chans[ch.topic] = ch;
      if (topics.includes(ch.topic)) bySub[c.subscribe(ch.id)] = ch;
    }
  });
  c.on('message', ({ subscriptionId, data }) => {
    const ch = bySub[subscriptionId];
    const bytes = Buffer.from(data.buffer, data.byteOffset, data.byteLength);
    const m = ch.encoding === 'protobuf' ? decode(T(ch.schemaName), bytes) : JSON.parse(bytes.toString('utf8'));
    (msgs[ch.topic] = msgs[ch.topic] || []).push({ m, size: bytes.length });
    waiters = waiters.filter((w) => !w());
  });
  const until = (cond, ms, what) => new Promise((resolve, reject) => {
    if (cond()) return resolve();
    const t = setTimeout(() => reject(new Error(`timed out: ${what}`)), ms);
    waiters.push(() => { if (cond()) { clearTimeout(t); resolve(); return true; } return false; });
  });
  return { c, chans, msgs, until, close: () => c.close() };
}

// Point cloud messages applied to a map of voxel index -> [label, confidence];
// every point checked against the fixture's grid geometry and the pieces' bound.
function applyPoints(held, list, map, bound) {
  const [nx, ny] = map.dims;
  for (const { m, size } of list) {
    assert.ok(size <= bound, `a /map/points piece of ${size} bytes, above ${bound}`);
    assert.strictEqual(m.frame_id, 'world');
    assert.strictEqual(m.point_stride, 20);
    assert.deepStrictEqual(m.fields.map((f) => `${f.name}@${f.offset}:${f.type}`), ['x@0:7', 'y@4:7', 'z@8:7',
      'red@12:1', 'green@13:1', 'blue@14:1', 'alpha@15:1', 'label@16:3', 'confidence@18:1']);
    const d = Buffer.from(m.data);
    for (let p = 0; p < d.length; p += 20) {
      const c = [0, 1, 2].map((a) => d.readFloatLE(p + 4 * a));
      const ijk = c.map((x, a) => Math.round((x - map.origin[a]) / map.voxel_size - 0.5));
      const idx = ijk[0] + nx * (ijk[1] + ny * ijk[2]);
      for (let a = 0; a < 3; a++) {
        assert.ok(Math.abs(c[a] - (map.origin[a] + (ijk[a] + 0.5) * map.voxel_size)) < 1e-5, `voxel centre ${c}`);
      }
      const label = d.readUInt16LE(p + 16), alpha = d[p + 15];
      if (label >= FREE) { assert.strictEqual(alpha, 0, 'a freed voxel transparent'); held.delete(idx); }
      else { assert.strictEqual(alpha, 255, 'an occupied voxel opaque'); held.set(idx, [label, d[p + 18]]); }
    }
  }
}

function occupiedOf(map) {
  const out = new Map();
  map.labels.forEach((l, i) => { if (l < FREE) out.set(i, [l, map.confidence[i]]); });
  return out;
}

// The grid a map gives: per column the highest occupied voxel.
function checkGrid(g, map) {
  const [nx, ny, nz] = map.dims, vs = map.voxel_size;
  assert.strictEqual(g.frame_id, 'world');
  assert.strictEqual(g.column_count, nx);
  assert.deepStrictEqual([g.cell_size.x, g.cell_size.y], [vs, vs]);
  assert.deepStrictEqual([g.pose.position.x, g.pose.position.y, g.pose.position.z], map.origin);
  assert.deepStrictEqual([g.pose.orientation.x, g.pose.orientation.y, g.pose.orientation.z, g.pose.orientation.w],
    [0, 0, 0, 1]);
  assert.strictEqual(g.cell_stride, 12);
  assert.strictEqual(g.row_stride, 12 * nx);
  assert.deepStrictEqual(g.fields.map((f) => `${f.name}@${f.offset}:${f.type}`), ['red@0:1', 'green@1:1',
    'blue@2:1', 'alpha@3:1', 'label@4:3', 'confidence@6:1', 'elevation@8:7']);
  const d = Buffer.from(g.data);
  assert.strictEqual(d.length, 12 * nx * ny);
  const colour = new Map();
  for (let j = 0; j < ny; j++) {
    for (let i = 0; i < nx; i++) {
      let want = UNKNOWN, conf = 0, elev = 0;
      for (let k = nz - 1; k >= 0; k--) {
        const idx = i + nx * (j + ny * k), l = map.labels[idx];
        if (l < FREE) { want = l; conf = map.confidence[idx]; elev = (k + 1) * vs; break; }
        if (l === FREE) want = FREE;
      }
      const p = 12 * (i + nx * j);
      const got = [d.readUInt16LE(p + 4), d[p + 6], d[p + 3]];
      assert.deepStrictEqual(got, [want, conf, want < FREE ? 255 : 0], `grid cell (${i}, ${j})`);
      assert.ok(Math.abs(d.readFloatLE(p + 8) - elev) < 1e-5, `cell (${i}, ${j}) elevation`);
      if (want < FREE) {
        const rgb = d.subarray(p, p + 3).toString('hex');
        assert.strictEqual(colour.get(want) ?? rgb, rgb, `label ${want} in one colour`);
        colour.set(want, rgb);
      }
    }
  }
  return colour.size;
}

function checkDepth(m) {
  const f = JSON.parse(fs.readFileSync(`${dir}/frame.json`, 'utf8'));
  assert.strictEqual(m.frame_id, 'camera');
  assert.deepStrictEqual([m.width, m.height, m.encoding, m.step], [f.width, f.height, '16UC1', 2 * f.width]);
  const d = Buffer.from(m.data);
  assert.strictEqual(d.length, 2 * f.width * f.height);
  for (let i = 0; i < f.depth_mm.length; i++) assert.strictEqual(d.readUInt16LE(2 * i), f.depth_mm[i], `pixel ${i}`);
}

async function main() {
  assert.ok(fixture, 'VLFF_VIEW_FIXTURE must name view_fixture (ctest sets it)');
  const fx = startFixture();
  await fx.mapVersion(1);
  // 0.25 MiB: /map/points pieces of at most 32 KiB, the whole map of about 95 kB in several
  const view = startView(['--max-queue-mb', '0.25', '--grid-hz', '10'], 'view.log');
  const port = await view.port;
  const bound = (0.25 * 1048576) / 8;
  const a = await client(port, ['/map/points', '/map/grid', '/camera/depth', '/camera/image', '/camera/calibration',
    '/tf', '/log']);
  await a.until(() => ['/map/points', '/map/grid', '/camera/depth'].every((t) => a.chans[t]), 10000, 'advertise');
  let types = 0;
  for (const [t, name] of [['/map/points', 'foxglove.PointCloud'], ['/map/grid', 'foxglove.Grid'],
    ['/camera/depth', 'foxglove.RawImage']]) {
    const c = a.chans[t];
    assert.deepStrictEqual([c.encoding, c.schemaEncoding, c.schemaName], ['protobuf', 'protobuf', name]);
    types += sameAsProtoFiles(c.schema);
  }
  ok(`the descriptors of /map/points, /map/grid and /camera/depth define ${types} messages as node/view/proto does`);

  const map1 = mapOf(1), want1 = occupiedOf(map1), held = new Map();
  await a.until(() => (a.msgs['/map/points'] || []).length * 1 && (() => {
    held.clear();
    applyPoints(held, a.msgs['/map/points'], map1, bound);
    return held.size === want1.size;
  })(), 20000, 'the whole map on /map/points');
  const pieces = a.msgs['/map/points'].length;
  assert.ok(pieces >= 3, `the whole map in ${pieces} pieces`);
  assert.deepStrictEqual([...held].sort((x, y) => x[0] - y[0]), [...want1].sort((x, y) => x[0] - y[0]));
  ok(`/map/points: the whole map, ${want1.size} voxels in ${pieces} pieces of at most ${bound} bytes, each point ` +
    'its voxel\'s centre, label and confidence');

  await a.until(() => (a.msgs['/map/grid'] || []).length > 0, 10000, '/map/grid');
  const labelsSeen = checkGrid(a.msgs['/map/grid'].at(-1).m, map1);
  ok(`/map/grid: every cell the highest occupied voxel of its column (${labelsSeen} labels), free and unknown ` +
    'columns transparent');

  await a.until(() => (a.msgs['/camera/depth'] || []).length > 0, 10000, '/camera/depth');
  checkDepth(a.msgs['/camera/depth'][0].m);
  ok('/camera/depth: a RawImage 16UC1 of the frame\'s millimetres, pixel by pixel');

  await a.until(() => ['/camera/image', '/camera/calibration', '/tf', '/log'].every((t) => (a.msgs[t] || []).length),
    10000, 'the JSON channels');
  const jsonTypes = { '/camera/image': 'foxglove.CompressedImage', '/camera/calibration': 'foxglove.CameraCalibration',
    '/tf': 'foxglove.FrameTransform', '/log': 'foxglove.Log' };
  for (const [t, name] of Object.entries(jsonTypes)) {
    assert.strictEqual(a.chans[t].schemaName, name);
    for (const { m } of a.msgs[t]) jsonAgainst(T(name), m, t);
  }
  ok('the JSON channels\' messages name only fields of the .proto files, with values of their types');

  // a change: its voxels alone on /map/points, a new grid
  const before = a.msgs['/map/points'].length, gridsBefore = a.msgs['/map/grid'].length;
  fx.stdin.write('change\n');
  await fx.mapVersion(2);
  const map2 = mapOf(2), want2 = occupiedOf(map2);
  const changed = map2.labels.filter((l, i) => l !== map1.labels[i] || map2.confidence[i] !== map1.confidence[i])
    .length;
  await a.until(() => {
    applyPoints(held, a.msgs['/map/points'].slice(before), map2, bound);
    a.msgs['/map/points'].splice(before);
    return held.size === want2.size;
  }, 20000, 'the change on /map/points');
  assert.deepStrictEqual([...held].sort((x, y) => x[0] - y[0]), [...want2].sort((x, y) => x[0] - y[0]));
  ok(`/map/points after a change of ${changed} voxels: the client's map is the new one`);
  await a.until(() => {
    const gs = a.msgs['/map/grid'].slice(gridsBefore);
    try { return gs.length && checkGrid(gs.at(-1).m, map2); } catch (e) { return false; }
  }, 10000, 'a new grid');
  checkGrid(a.msgs['/map/grid'].at(-1).m, map2);
  ok('/map/grid after the change: the new map\'s columns');

  // a subscriber arriving now: the whole current map in pieces, then the next change
  const b = await client(port, ['/map/points']);
  const heldB = new Map();
  await b.until(() => {
    heldB.clear();
    applyPoints(heldB, b.msgs['/map/points'] || [], map2, bound);
    return heldB.size === want2.size;
  }, 20000, 'the late subscriber\'s whole map');
  const late = b.msgs['/map/points'].length;
  assert.ok(late >= 3, `the late subscriber's whole map in ${late} pieces`);
  assert.deepStrictEqual([...heldB].sort((x, y) => x[0] - y[0]), [...want2].sort((x, y) => x[0] - y[0]));
  fx.stdin.write('change\n');
  await fx.mapVersion(3);
  const map3 = mapOf(3), want3 = occupiedOf(map3);
  await b.until(() => {
    applyPoints(heldB, b.msgs['/map/points'].slice(late), map3, bound);
    b.msgs['/map/points'].splice(late);
    return heldB.size === want3.size;
  }, 20000, 'the late subscriber\'s next change');
  assert.deepStrictEqual([...heldB].sort((x, y) => x[0] - y[0]), [...want3].sort((x, y) => x[0] - y[0]));
  ok(`a subscriber of /map/points after the change: the whole current map in ${late} pieces, then the next change`);
  a.close();
  b.close();

  // --record FILE: refused over an existing file, taken with --force
  const rec = `${dir}/run.mcap`;
  fs.writeFileSync(rec, 'an earlier run\n');
  const refused = startView(['--record', rec], 'refused.log');
  const code = await refused.exited;
  const log = fs.readFileSync(`${dir}/refused.log`, 'utf8');
  assert.strictEqual(code, 1, `exit status ${code}: ${log}`);
  assert.match(log, /--record .*run\.mcap: the file exists; pass --force/);
  assert.strictEqual(fs.readFileSync(rec, 'utf8'), 'an earlier run\n', 'the earlier file untouched');
  ok('--record over an existing file: exit 1 with the reason, the file untouched');

  const recorder = startView(['--record', rec, '--force', '--grid-hz', '10'], 'rec.log');
  const rport = await recorder.port;
  // the first grid and depth image go into the recording with the first polls
  const rc = await client(rport, ['/map/grid']);
  await rc.until(() => (rc.msgs['/map/grid'] || []).length > 0, 10000, 'the recorder\'s grid');
  fx.stdin.write('change\n');
  await fx.mapVersion(4);
  await sleep(1500);
  rc.close();
  recorder.kill('SIGINT');
  assert.strictEqual(await recorder.exited, 0);
  const bytes = fs.readFileSync(rec);
  await zstd.isLoaded;
  const r = await McapIndexedReader.Initialize({
    readable: { size: async () => BigInt(bytes.length),
      read: async (o, s) => bytes.subarray(Number(o), Number(o + s)) },
    decompressHandlers: { zstd: (buf, size) => zstd.decompress(buf, Number(size)) } });
  const seen = {};
  for await (const m of r.readMessages({ validateCrcs: true })) {
    const ch = r.channelsById.get(m.channelId);
    if (ch.messageEncoding !== 'protobuf') continue;
    const s = r.schemasById.get(ch.schemaId);
    sameAsProtoFiles(Buffer.from(s.data).toString('base64'));
    const o = decode(T(s.name), Buffer.from(m.data));
    (seen[ch.topic] = seen[ch.topic] || []).push(o);
  }
  assert.ok(seen['/camera/depth'] && seen['/map/grid'], `recorded: ${Object.keys(seen)}`);
  checkDepth(seen['/camera/depth'][0]);
  checkGrid(seen['/map/grid'].at(-1), mapOf(4));
  ok(`--record --force replaced it: /camera/depth (${seen['/camera/depth'].length}) and /map/grid ` +
    `(${seen['/map/grid'].length}) recorded with their descriptors, decoded by node/view/proto, the last grid the map's`);

  fx.stdin.end();
  view.kill('SIGINT');
  assert.strictEqual(await view.exited, 0);
  plan();
  fs.rmSync(dir, { recursive: true, force: true });
}

main().catch((e) => {
  console.log(`not ok - ${e.stack}`);
  for (const l of ['view.log', 'rec.log']) try { console.log(fs.readFileSync(`${dir}/${l}`, 'utf8')); } catch (x) { /**/ }
  process.exit(1);
});
