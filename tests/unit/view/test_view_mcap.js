// vlff-view's recordings, checked by readers nobody here wrote: the demo (vlff-sim,
// vlff-node) recorded with --record while a Foxglove client (@foxglove/ws-protocol)
// watches, then the file read by @mcap/core's indexed reader (chunk CRCs, summary
// CRC; the data section's CRC computed here with @foxglove/crc), zstd chunks through
// @foxglove/wasm-zstd: every channel with the schema the live server advertised, every
// message valid against it, as many as the summary's statistics count, and what the live client got on each channel found in the
// file in the same order. A recorder killed with SIGKILL leaves a file @mcap/core's
// stream reader reads to its last whole chunk. Then --play serves the recording to
// a Foxglove client: the recorded channels, every message in the file's order with
// its bytes and publish time, no message before its recorded offset, and a late
// subscriber given the latest of its channel. --record DIR names a file per run.
// Seeking: with --record-map-s 2 the whole map is in the file every 2 s while the map
// changes, each time opening a chunk, and from any point the latest whole map before
// it with the changes after it is the map a reader playing from the start holds.
// Bad files on --play are refused with exit 1 and a reason.
'use strict';
const assert = require('assert');
const fs = require('fs');
const os = require('os');
const path = require('path');
const { spawn, spawnSync } = require('child_process');
const { FoxgloveClient } = require('@foxglove/ws-protocol');
const { McapIndexedReader, McapStreamReader } = require('@mcap/core');
const { crc32 } = require('@foxglove/crc');
const zstd = require('@foxglove/wasm-zstd');
const WebSocket = require('ws');
const protobuf = require('protobufjs');
require('protobufjs/ext/descriptor');
const published = require('@foxglove/schemas/jsonschema');
const { start, sleep, waitVersion, prog, ok, plan, check } = require('./demo');
const { validate } = require('./schema');

const td = new TextDecoder();
const decompressHandlers = { zstd: (buf, size) => zstd.decompress(buf, Number(size)) };

function readable(bytes) {
  return {
    size: async () => BigInt(bytes.length),
    read: async (offset, size) => bytes.subarray(Number(offset), Number(offset + size)),
  };
}

// A Foxglove client subscribed to every channel: what it got, per topic, in order.
function watch(url) {
  const client = new FoxgloveClient({ ws: new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]) });
  const w = { client, chans: {}, bySub: {}, got: {}, all: [], subscribeLate: null };
  client.on('advertise', (cs) => {
    for (const c of cs) {
      w.chans[c.topic] = c;
      if (!w.subscribeLate) w.bySub[client.subscribe(c.id)] = c;
    }
  });
  client.on('message', ({ subscriptionId, timestamp, data }) => {
    const c = w.bySub[subscriptionId];
    const bytes = Buffer.from(data.buffer, data.byteOffset, data.byteLength);
    const m = { topic: c.topic, timestamp, bytes, at: process.hrtime.bigint() };
    (w.got[c.topic] = w.got[c.topic] || []).push(m);
    w.all.push(m);
  });
  return w;
}

async function until(cond, ms, what) {
  const t0 = Date.now();
  while (!cond()) {
    if (Date.now() - t0 > ms) throw new Error(`timed out: ${what}`);
    await sleep(50);
  }
}

// A protobuf channel's message (/map/points, /map/grid, /camera/depth) decoded as
// Foxglove decodes it (protobufjs, from the channel's FileDescriptorSet), in the
// shape of its @foxglove/schemas JSON Schema.
const pbTypes = new Map();
function pointCloud(c, bytes) {
  if (!pbTypes.has(c.schema)) {
    const set = protobuf.descriptor.FileDescriptorSet.decode(Buffer.from(c.schema, 'base64'));
    pbTypes.set(c.schema, protobuf.Root.fromDescriptor(set).lookupType(c.schemaName));
  }
  const t = pbTypes.get(c.schema);
  const o = t.toObject(t.decode(bytes), { longs: Number, enums: Number, bytes: String, defaults: true });
  o.timestamp = { sec: o.timestamp.seconds, nsec: o.timestamp.nanos };
  return o;
}

// Messages of the file in order: { topic, log, pub, bytes }.
async function readIndexed(bytes) {
  const r = await McapIndexedReader.Initialize({ readable: readable(bytes), decompressHandlers });
  const out = [];
  for await (const m of r.readMessages({ validateCrcs: true })) {
    out.push({ topic: r.channelsById.get(m.channelId).topic, log: m.logTime, pub: m.publishTime,
      bytes: Buffer.from(m.data), seq: m.sequence });
  }
  return { r, msgs: out };
}

function exited(p) {
  return new Promise((resolve) => { if (p.exitCode !== null) resolve(p.exitCode); else p.once('exit', resolve); });
}

function viewProc(args, log, fileLimitKb = 0) {
  const out = fs.openSync(log, 'w');
  const p = fileLimitKb
    ? spawn('bash', ['-c', `ulimit -f ${fileLimitKb}; exec "$0" "$@"`, prog.view, '--port', '0', ...args],
      { stdio: ['ignore', 'pipe', out] })
    : spawn(prog.view, ['--port', '0', ...args], { stdio: ['ignore', 'pipe', out] });
  process.on('exit', () => { if (p.exitCode === null) p.kill('SIGKILL'); });
  let text = '';
  p.stdout.on('data', (d) => { text += d; });
  p.text = () => text;
  p.port = new Promise((resolve, reject) => {
    p.stdout.on('data', () => {
      const m = /serving http:\/\/127\.0\.0\.1:(\d+)\//.exec(text);
      if (m) resolve(Number(m[1]));
    });
    p.on('exit', (code) => reject(new Error(`vlff-view exited ${code}: ${fs.readFileSync(log, 'utf8')}`)));
  });
  return p;
}

async function main() {
  await zstd.isLoaded;
  const tmp = fs.mkdtempSync(path.join(os.tmpdir(), 'vlff-view-mcap-'));
  process.on('exit', () => fs.rmSync(tmp, { recursive: true, force: true }));
  const file = path.join(tmp, 'run.mcap'), killed = path.join(tmp, 'killed.mcap'), full = path.join(tmp, 'full.mcap');
  const RECORD_MAP_S = 2;
  // --max-queue-mb 0.5: map pieces of at most 64 KiB, so that the whole maps are recorded in several
  const demo = await start({ viewArgs: ['--record', file, '--record-map-s', String(RECORD_MAP_S), '--max-queue-mb', '0.5'] });
  let live, advertised, killedLog, fullExit, fullLimitKb;
  await check(demo, async () => {
    live = watch(demo.ws);
    await waitVersion(demo, 2, 240000);
    await until(() => Object.keys(live.got).length >= 6, 30000, 'messages on six channels');
    // a second recorder on the same segments, killed without a chance to close its file
    const k = viewProc(['--map', demo.names.map, '--frames', demo.names.frames, '--prompts', demo.names.prompts,
      '--record', killed], path.join(tmp, 'killed.log'));
    await k.port;
    await sleep(3500);
    k.kill('SIGKILL');
    await exited(k);
    killedLog = fs.readFileSync(path.join(tmp, 'killed.log'), 'utf8');
    // a recorder whose file reaches the size limit (ulimit -f: a few KiB past what
    // the killed one wrote in 3.5 s): the recording stops with a line, the viewer
    // serves on and exits 1
    fullLimitKb = Math.ceil(fs.statSync(killed).size / 1024) + 8;
    const f = viewProc(['--map', demo.names.map, '--frames', demo.names.frames, '--prompts', demo.names.prompts,
      '--record', full], path.join(tmp, 'full.log'), fullLimitKb);
    const fport = await f.port;
    await until(() => /recording stopped: .*full\.mcap: write failed .*File too large/.test(
      fs.readFileSync(path.join(tmp, 'full.log'), 'utf8')), 60000, 'the recording stopped at the size limit');
    const fc = watch(`ws://127.0.0.1:${fport}/`);
    await until(() => fc.got['/vlff/status'], 10000, 'the viewer serves on after its recording stopped');
    fc.client.close();
    f.kill('SIGINT');
    fullExit = await exited(f);
    advertised = live.chans;
    live.client.close();
  });
  assert.strictEqual(demo.viewExit, 0, 'the recorder ends cleanly on SIGINT');

  // ---- the recording, read by @mcap/core
  const bytes = fs.readFileSync(file);
  const { r, msgs } = await readIndexed(bytes);
  assert.ok(/^vlff-view \d+\.\d+\.\d+$/.test(r.header.library), r.header.library);
  const topics = [...r.channelsById.values()].map((c) => c.topic).sort();
  assert.deepStrictEqual(topics, Object.keys(advertised).sort(), 'every channel the server advertised is recorded');
  for (const c of r.channelsById.values()) {
    const a = advertised[c.topic], s = r.schemasById.get(c.schemaId);
    assert.strictEqual(c.messageEncoding, a.encoding);
    assert.strictEqual(s.name, a.schemaName);
    assert.strictEqual(s.encoding, a.schemaEncoding);
    // a protobuf schema: the FileDescriptorSet's bytes, advertised in base64
    const text = s.encoding === 'protobuf' ? Buffer.from(s.data).toString('base64') : td.decode(s.data);
    assert.strictEqual(text, a.schema, `${c.topic}: the schema the live server advertises`);
  }
  ok(`${topics.length} channels recorded with the live server's schemas (${topics.join(', ')})`);

  assert.ok(r.statistics, 'a statistics record');
  assert.strictEqual(BigInt(msgs.length), r.statistics.messageCount, 'every message the statistics count is read');
  assert.ok(r.chunkIndexes.length > 2 && r.chunkIndexes.every((ci) => ci.compression === 'zstd'),
    `${r.chunkIndexes.length} zstd chunks`);
  assert.strictEqual(r.dataSectionCrc, crc32(bytes.subarray(0, Number(r.dataEndOffset))), 'the data section CRC');
  const byTopic = {};
  for (const m of msgs) (byTopic[m.topic] = byTopic[m.topic] || []).push(m);
  const bad = [];
  for (let i = 0; i < msgs.length; i++) {
    const m = msgs[i], c = advertised[m.topic];
    if (i && m.log < msgs[i - 1].log) bad.push(`message ${i} goes back in log time`);
    const errs = c.encoding === 'protobuf' ? validate(published[c.schemaName.slice(9)], pointCloud(c, m.bytes), '$', [], true)
      : validate(JSON.parse(c.schema), JSON.parse(td.decode(m.bytes)));
    if (errs.length) bad.push(`${m.topic}: ${errs.slice(0, 2).join('; ')}`);
  }
  assert.deepStrictEqual(bad.slice(0, 5), []);
  for (const t of ['/map', '/map/voxels', '/camera/image', '/vlff/status', '/tf']) {
    assert.ok((byTopic[t] || []).length > 0, `messages on ${t}`);
  }
  ok(`@mcap/core reads ${msgs.length} messages in ${r.chunkIndexes.length} chunks with their CRCs (chunks, ` +
    'summary, data section), as many as the statistics count, each valid against its channel\'s schema');

  // ---- seeking: the whole map at most RECORD_MAP_S before any change, opening its chunk
  // A whole map is recorded at one log time on the three map channels (the voxels,
  // the points, the scene, each in its pieces), its first /map/voxels piece full:
  // a reader seeking finds that piece and reads every map channel from its log time.
  const MAPS = ['/map', '/map/voxels', '/map/points'];
  const parsed = (m) => JSON.parse(td.decode(m.bytes));
  const wholeLogs = new Map(); // log time of a whole map -> its first /map/voxels piece
  for (const m of msgs) if (m.topic === '/map/voxels' && parsed(m).full) wholeLogs.set(m.log, parsed(m));
  // a /map/points message as voxels: index -> label,conf (freed ones transparent), in geometry g
  const pointsOf = (m, g) => {
    const d = Buffer.from(pointCloud(advertised['/map/points'], m.bytes).data, 'base64'), out = [];
    for (let p = 0; p < d.length; p += 20) {
      const ijk = [0, 1, 2].map((a) => Math.round((d.readFloatLE(p + 4 * a) - g.origin[a]) / g.voxel_size - 0.5));
      out.push([ijk[0] + g.dims[0] * (ijk[1] + g.dims[1] * ijk[2]), d[p + 15] === 255, `${d.readUInt16LE(p + 16)},${d[p + 18]}`]);
    }
    return out;
  };
  {
    const state = () => ({ bricks: new Map(), voxels: new Map(), points: new Map() });
    const keyOf = { '/map': 'bricks', '/map/voxels': 'voxels', '/map/points': 'points' };
    let geometry = null;
    const isWhole = (m, j) => (m.topic === '/map' ? j.deletions.some((d) => d.type === 1)
      : m.topic === '/map/voxels' ? j.full : wholeLogs.has(m.log));
    // a /map message replaces bricks by id (type 1 deletes all first); a /map/voxels
    // message sets voxels (full: all occupied ones, after forgetting the rest); a
    // /map/points message sets its points' voxels (transparent: no longer occupied),
    // the first piece of a whole map after forgetting the rest
    const apply = (st, m, j) => {
      if (m.topic === '/map') {
        for (const d of j.deletions) if (d.type === 1) st.bricks.clear(); else st.bricks.delete(d.id);
        for (const e of j.entities) st.bricks.set(e.id, JSON.stringify(e.cubes));
      } else if (m.topic === '/map/voxels') {
        if (j.full) st.voxels.clear();
        for (let i = 0; i < j.voxels.length; i += 3) {
          const [idx, label, conf] = j.voxels.slice(i, i + 3);
          if (label <= 0xfffd) st.voxels.set(idx, `${label},${conf}`); else st.voxels.delete(idx);
        }
      } else {
        if (j.wholeFirst) st.points.clear();
        for (const [idx, occupied, v] of j.points) if (occupied) st.points.set(idx, v); else st.points.delete(idx);
      }
    };
    const same = (a, b) => a.size === b.size && [...a].every(([k, x]) => b.get(k) === x);
    const replay = state(), seek = { bricks: null, voxels: null, points: null }, lastWhole = {}, late = {};
    const lastLog = {}, wholes = { bricks: 0, voxels: 0, points: 0 };
    let compared = 0, deltas = 0, maxGap = 0;
    const bad = [];
    for (const m of msgs) {
      if (!MAPS.includes(m.topic)) continue;
      const key = keyOf[m.topic];
      let j;
      if (m.topic === '/map/points') {
        if (!geometry) { bad.push('/map/points before any /map/voxels'); continue; }
        j = { points: pointsOf(m, geometry) };
      } else {
        j = parsed(m);
        if (m.topic === '/map/voxels') geometry = j;
      }
      // the later pieces of a message (one log time) go with its first
      const piece = m.log === lastLog[key];
      lastLog[key] = m.log;
      if (m.topic === '/map/points') j.wholeFirst = !piece && isWhole(m, j);
      apply(replay, m, j);
      if (piece) {
        if (m.topic !== '/map/points' && isWhole(m, j)) bad.push(`${m.topic} at log time ${m.log}: a later piece is full`);
      } else if (isWhole(m, j)) {
        seek[key] = new Map();
        lastWhole[key] = m.log;
        late[key] = null;
        wholes[key]++;
      } else {
        deltas++;
        // a change more than RECORD_MAP_S after the latest whole map is followed by one at once
        if (late[key]) bad.push(`${m.topic}: ${late[key]} and no whole map follows it`);
        if (lastWhole[key] === undefined) bad.push(`${m.topic}: a change before any whole map`);
        const gap = Number(m.log - lastWhole[key]) / 1e9;
        if (gap > RECORD_MAP_S) late[key] = `a change ${gap.toFixed(2)} s after the latest whole map`;
        else maxGap = Math.max(maxGap, gap);
      }
      if (!seek[key]) continue;
      apply({ [key]: seek[key] }, m, j);
      // from this point: the latest whole map and the changes since are what the replay holds
      if (!same(seek[key], replay[key])) bad.push(`${m.topic} at log time ${m.log}: seeking gives another map`);
      compared++;
    }
    assert.deepStrictEqual(bad.slice(0, 3), []);
    assert.ok(wholes.bricks >= 3 && deltas > wholes.bricks, `${wholes.bricks} whole maps and ${deltas} changes on the map's channels`);
    assert.deepStrictEqual([wholes.voxels, wholes.points], [wholes.bricks, wholes.bricks],
      'a whole map on each map channel each time');
    // each whole map is the first message of its chunk (the voxels, then the points and the scene)
    const sr = new McapStreamReader({ decompressHandlers, validateCrcs: true, includeChunks: true });
    sr.append(bytes);
    let prev = null, opening = 0;
    const chanTopic = new Map();
    for (let rec; (rec = sr.nextRecord()); prev = rec) {
      if (rec.type === 'Channel') chanTopic.set(rec.id, rec.topic);
      if (rec.type !== 'Message' || chanTopic.get(rec.channelId) !== '/map/voxels') continue;
      if (!JSON.parse(td.decode(rec.data)).full) continue;
      assert.strictEqual(prev.type, 'Chunk', 'a whole map opens its chunk');
      opening++;
    }
    assert.strictEqual(opening, wholes.bricks, 'as many whole voxel maps as whole scenes');
    ok(`seeking: ${wholes.bricks} whole maps on each of /map, /map/voxels and /map/points, each opening its chunk; ` +
      `a change more than ${RECORD_MAP_S} s after the latest (--record-map-s ${RECORD_MAP_S}) followed by one at ` +
      `once, the others at most ${maxGap.toFixed(2)} s after it; at each of ${compared} points on the map's ` +
      `channels the latest whole map and the ${deltas} changes after it give the map a reader playing from the start holds`);
  }

  // The last whole /map/points map of a version the live client was sent, read alone
  // (its pieces, from its log time): the occupied voxels the live client held at
  // that version on /map/voxels, each with its label and confidence.
  {
    const liveAt = new Map(), live1 = new Map(); // version -> the live client's voxels after it
    for (const m of live.got['/map/voxels']) {
      const j = JSON.parse(td.decode(m.bytes));
      if (j.full) live1.clear();
      for (let i = 0; i < j.voxels.length; i += 3) {
        if (j.voxels[i + 1] <= 0xfffd) live1.set(j.voxels[i], `${j.voxels[i + 1]},${j.voxels[i + 2]}`);
        else live1.delete(j.voxels[i]);
      }
      if (j.piece + 1 === j.pieces) liveAt.set(j.version, new Map(live1));
    }
    const last = [...wholeLogs].filter(([, g]) => liveAt.has(g.version)).pop();
    assert.ok(last, 'a whole map of a version the live client got');
    const [log, g] = last, pts = new Map();
    let pieces = 0;
    for (const m of msgs) {
      if (m.topic !== '/map/points' || m.log !== log) continue;
      pieces++;
      for (const [idx, occupied, v] of pointsOf(m, g)) {
        assert.ok(occupied && !pts.has(idx), `voxel ${idx}: a whole map's point, opaque, once`);
        pts.set(idx, v);
      }
    }
    const want = liveAt.get(g.version);
    assert.ok(want.size > 0 && pieces > 0, `${pieces} pieces, ${want.size} voxels`);
    assert.ok(pts.size === want.size && [...want].every(([k, x]) => pts.get(k) === x), `the whole /map/points of version ${g.version}: ${pts.size} points, the live client ` +
      `held ${want.size} voxels`);
    ok(`a reader starting at the recording's last whole /map/points (version ${g.version}, ${pieces} piece(s)) ` +
      `holds the ${pts.size} occupied voxels, labels and confidences the live client held at that version`);
  }

  // what the live client got after its first (built for it) message on each channel
  // is a run of the recording, in order, but for the whole maps only the recording has
  // (the pieces of the map channels at a whole map's log time)
  let skipped = 0;
  for (const [t, got] of Object.entries(live.got)) {
    const recMsgs = byTopic[t], rec = recMsgs.map((m) => m.bytes), later = got.slice(1).map((m) => m.bytes);
    const recordedOnly = (i) => MAPS.includes(t) && wholeLogs.has(recMsgs[i].log);
    // a map channel's whole map to a subscriber may come in several pieces
    while (MAPS.includes(t) && later.length && !rec.some((b) => b.equals(later[0]))) later.shift();
    if (!later.length) continue;
    let at = rec.findIndex((b) => b.equals(later[0]));
    assert.ok(at >= 0, `${t}: the live client's second message is in the recording`);
    for (let i = 1; i < later.length; i++) {
      at++;
      for (; rec[at] && !rec[at].equals(later[i]) && recordedOnly(at); at++) skipped++;
      assert.ok(rec[at] && rec[at].equals(later[i]), `${t}: live message ${i + 1} is recorded in order`);
    }
  }
  ok(`every message the live client got on its ${Object.keys(live.got).length} channels is in the recording, in ` +
    `the order it came (${skipped} pieces of whole maps of the recording's own between them)`);

  // ---- a recorder killed with SIGKILL
  const kb = fs.readFileSync(killed);
  const sr = new McapStreamReader({ decompressHandlers, validateCrcs: true });
  sr.append(kb);
  const kinds = {};
  for (let rec; (rec = sr.nextRecord());) kinds[rec.type] = (kinds[rec.type] || 0) + 1;
  assert.ok(kinds.Header === 1 && kinds.Channel >= 7 && kinds.Schema >= 1 && kinds.Message > 0, JSON.stringify(kinds));
  assert.ok(!kinds.Footer && !sr.done(), 'no footer: the recorder was killed');
  assert.ok(sr.bytesRemaining() < 4 << 20, `${sr.bytesRemaining()} bytes left over: at most the chunk being written`);
  await assert.rejects(McapIndexedReader.Initialize({ readable: readable(kb), decompressHandlers }));
  ok(`a recorder killed by SIGKILL after 3.5 s: @mcap/core's stream reader reads its ${kinds.Message} messages in ` +
    `${kinds.Chunk || 'its'} whole chunks (${sr.bytesRemaining()} bytes of an unfinished one left), the index is lost`);

  // ---- playback
  const RATE = 4n; // played four times as fast as recorded
  const player = viewProc(['--play', file, '--play-rate', String(RATE)], path.join(tmp, 'play.log'));
  const port = await player.port;
  assert.ok(player.text().includes(`${msgs.length} messages on ${topics.length} channels`), player.text());
  const pl = watch(`ws://127.0.0.1:${port}/`);
  await until(() => pl.all.length >= msgs.length, 120000, `all ${msgs.length} messages played`);
  for (const c of Object.values(pl.chans)) {
    const a = advertised[c.topic];
    assert.ok(a && c.encoding === a.encoding && c.schemaName === a.schemaName && c.schema === a.schema &&
      c.schemaEncoding === a.schemaEncoding, `${c.topic} advertised as recorded`);
  }
  assert.strictEqual(Object.keys(pl.chans).length, topics.length);
  const late = [];
  for (let i = 0; i < msgs.length; i++) {
    const f = msgs[i], g = pl.all[i];
    assert.ok(g.topic === f.topic && g.bytes.equals(f.bytes), `played message ${i} is the file's (${g.topic}, ${f.topic})`);
    assert.strictEqual(g.timestamp, f.pub, `played message ${i} carries its publish time`);
    // never before its offset in the recording at that rate (the first one's delivery may lag by 0.25 s)
    const due = (f.log - msgs[0].log) / RATE, got = g.at - pl.all[0].at;
    if (got + 250000000n < due) late.push(`message ${i} after ${got} ns, due at ${due} ns`);
  }
  assert.deepStrictEqual(late.slice(0, 3), []);
  const span = Number(msgs.at(-1).log - msgs[0].log) / 1e9, took = Number(pl.all.at(-1).at - pl.all[0].at) / 1e9;
  ok(`--play --play-rate ${RATE} serves the ${topics.length} recorded channels and all ${msgs.length} messages in ` +
    `the file's order with their bytes and publish times, none ahead of its recorded offset at that rate (recorded ` +
    `over ${span.toFixed(1)} s, played over ${took.toFixed(1)} s)`);

  // a subscriber after the end gets the latest message of each channel
  const after = watch(`ws://127.0.0.1:${port}/`);
  await until(() => Object.keys(after.got).length === Object.keys(byTopic).length, 10000, 'a late subscriber');
  for (const [t, got] of Object.entries(after.got)) {
    assert.ok(got[0].bytes.equals(byTopic[t].at(-1).bytes), `${t}: the late subscriber's first is the last played`);
  }
  ok('a subscriber after the playback gets the last message played on each channel');
  after.client.close();
  pl.client.close();
  player.kill('SIGINT');
  assert.strictEqual(await exited(player), 0);

  // ---- the recording stopped by the size limit: its whole chunks read
  assert.strictEqual(fullExit, 1, 'a recording that stopped on an error: exit status 1');
  const fb = fs.readFileSync(full);
  assert.ok(fb.length <= fullLimitKb * 1024, `${fb.length} bytes`);
  const fr = new McapStreamReader({ decompressHandlers, validateCrcs: true });
  fr.append(fb);
  let fmsgs = 0;
  for (let rec; (rec = fr.nextRecord());) if (rec.type === 'Message') fmsgs++;
  assert.ok(fmsgs > 0 && !fr.done(), `${fmsgs} messages`);
  ok(`a recording stopped by the file size limit (${fullLimitKb} KiB): one log line, the viewer serves on and exits 1; ` +
    `@mcap/core reads the ${fmsgs} messages of its whole chunks`);

  // ---- the killed recorder's file plays, with a warning
  const kp = viewProc(['--play', killed], path.join(tmp, 'kplay.log'));
  await kp.port;
  kp.kill('SIGINT');
  assert.strictEqual(await exited(kp), 0);
  assert.ok(/ends at byte \d+ without its summary/.test(fs.readFileSync(path.join(tmp, 'kplay.log'), 'utf8')));
  assert.ok(kp.text().includes(`${kinds.Message} messages`), `${kp.text()} (${kinds.Message} in the file)`);
  ok(`--play of the killed recorder's file serves its ${kinds.Message} messages and warns that its summary is lost`);

  // ---- --record DIR: a file of its own per run
  const rdir = path.join(tmp, 'runs');
  fs.mkdirSync(rdir);
  const rp = viewProc(['--map', `/vlff-none-${process.pid}`, '--frames', '', '--record', rdir],
    path.join(tmp, 'dir.log'));
  await rp.port;
  await sleep(1500);
  rp.kill('SIGINT');
  assert.strictEqual(await exited(rp), 0);
  const runs = fs.readdirSync(rdir);
  assert.ok(runs.length === 1 && /^vlff-view-\d{8}-\d{6}\.mcap$/.test(runs[0]), runs.join());
  const { msgs: dm } = await readIndexed(fs.readFileSync(path.join(rdir, runs[0])));
  const dlog = dm.filter((m) => m.topic === '/log').map((m) => JSON.parse(td.decode(m.bytes)).message);
  assert.ok(dm.some((m) => m.topic === '/vlff/status') && dm.every((m) => ['/vlff/status', '/log'].includes(m.topic)),
    dm.map((m) => m.topic).join());
  assert.deepStrictEqual(dlog, [`map segment /vlff-none-${process.pid} not there yet`]);
  ok(`--record DIR writes ${runs[0]} there, read by @mcap/core (without a map: status and the /log line ` +
    `"${dlog[0]}")`);
  // a run whose start second names an earlier run's file (a restart within the
  // second, a clock set back) writes a file of its own beside it
  fs.rmSync(path.join(rdir, runs[0]));
  const pad = (v) => String(v).padStart(2, '0');
  const taken = [];
  for (let k = -1; k < 60; k++) { // the seconds the run may start in on a loaded host
    const d = new Date(Date.now() + k * 1000);
    const name = `vlff-view-${d.getFullYear()}${pad(d.getMonth() + 1)}${pad(d.getDate())}-` +
      `${pad(d.getHours())}${pad(d.getMinutes())}${pad(d.getSeconds())}.mcap`;
    fs.writeFileSync(path.join(rdir, name), 'an earlier run');
    taken.push(name);
  }
  const rp2 = viewProc(['--map', `/vlff-none-${process.pid}`, '--frames', '', '--record', rdir],
    path.join(tmp, 'dir2.log'));
  await rp2.port;
  rp2.kill('SIGINT');
  assert.strictEqual(await exited(rp2), 0);
  for (const t of taken) assert.strictEqual(fs.readFileSync(path.join(rdir, t), 'utf8'), 'an earlier run', t);
  const runs2 = fs.readdirSync(rdir).filter((f) => !taken.includes(f));
  assert.ok(runs2.length === 1 && /^vlff-view-\d{8}-\d{6}-2\.mcap$/.test(runs2[0]), runs2.join());
  ok(`--record DIR beside an earlier run's file of the same second writes ${runs2[0]}, the earlier one kept`);

  // ---- bad files on --play
  const bad1 = (name, data) => { const p = path.join(tmp, name); fs.writeFileSync(p, data); return p; };
  const flipped = Buffer.from(bytes);
  const ci = r.chunkIndexes[1];
  flipped[Number(ci.chunkStartOffset + ci.chunkLength) - 40] ^= 0x10; // inside the second chunk's records
  const fifo = path.join(tmp, 'fifo');
  spawnSync('mkfifo', [fifo]);
  const sparse = path.join(tmp, 'huge.mcap');
  fs.writeFileSync(sparse, bytes.subarray(0, 64));
  fs.truncateSync(sparse, 4 * 2 ** 30 + 1);
  const cases = [
    [path.join(tmp, 'none.mcap'), 'No such file'],
    [tmp, 'is a directory'],
    [fifo, 'is a FIFO'],
    [bad1('empty.mcap', ''), 'not an MCAP file'],
    [bad1('text.mcap', 'hello, this is not a recording\n'), 'not an MCAP file'],
    [bad1('head.mcap', bytes.subarray(0, 12)), 'not a whole header'],
    [bad1('flipped.mcap', flipped), 'chunk'],
    [bad1('nomsg.mcap', bytes.subarray(0, Number(r.chunkIndexes[0].chunkStartOffset))), 'holds no message'],
    [sparse, 'bytes'],
  ];
  for (const [p, what] of cases) {
    const res = spawnSync(prog.view, ['--port', '0', '--play', p], { encoding: 'utf8', timeout: 20000 });
    assert.strictEqual(res.status, 1, `--play ${path.basename(p)}: status ${res.status} signal ${res.signal}`);
    assert.ok(res.stderr.includes('--play') && res.stderr.includes(what), `${path.basename(p)}: ${res.stderr}`);
  }
  ok(`${cases.length} bad files on --play (missing, directory, FIFO, empty, text, cut header, flipped chunk byte, ` +
    'no message, 4 GiB) exit 1 naming what is wrong');
  assert.ok(!/recording stopped/.test(killedLog));
  plan();
}

main().catch((e) => { console.log(`not ok - ${e.stack}`); process.exit(1); });
