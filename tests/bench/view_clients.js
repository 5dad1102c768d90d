// scripts/bench view's clients: N Foxglove WebSocket connections in one process,
// each subscribed to every channel as Foxglove would be. For SECONDS it records,
// per map version, the latency from the version's publish (CLOCK_MONOTONIC, which
// process.hrtime also reads) to its voxel delta's arrival, and the bytes received.
// Then the N leave and, after LATE_GAP seconds with no subscriber, one more client
// subscribes to every channel: the age of its first message on each (now minus the
// message's log time, both wall-clock) says whether a new subscriber gets the latest
// or one kept from before. Also the camera image's bytes per frame against the raw
// RGB frame (its size from /camera/calibration).
// Prints one JSON line. Usage: node view_clients.js PORT N SECONDS
'use strict';
const WebSocket = require('ws');
const [port, n, secs] = process.argv.slice(2).map(Number);
const LATE_GAP = 3;
const lat = [], bytes = { map: 0, voxels: 0, points: 0, all: 0 }, image = { bytes: 0, n: 0, w: 0, h: 0 }, socks = [];
let versions = 0, closed = 0;
const td = new TextDecoder();
const t0 = process.hrtime.bigint();
for (let c = 0; c < n; c++) {
  const ws = new WebSocket(`ws://127.0.0.1:${port}/`, ['foxglove.websocket.v1']);
  socks.push(ws);
  const topics = {};
  ws.on('message', (d, bin) => {
    const now = process.hrtime.bigint();
    if (!bin) {
      const m = JSON.parse(d.toString());
      if (m.op === 'advertise') {
        m.channels.forEach((ch) => { topics[ch.id] = ch.topic; });
        ws.send(JSON.stringify({ op: 'subscribe', subscriptions: m.channels.map((ch) => ({ id: ch.id, channelId: ch.id })) }));
      }
      return;
    }
    const topic = topics[d.readUInt32LE(1)];
    if (c === 0 && now - t0 > 3000000000n) {
      bytes.all += d.length;
      if (topic === '/map' || topic === '/map/voxels') bytes.map += d.length;
      if (topic === '/map/voxels') bytes.voxels += d.length;
      if (topic === '/map/points') bytes.points += d.length;
      if (topic === '/camera/image') image.bytes += d.length - 13, image.n++;
      if (topic === '/camera/calibration' && !image.w) ({ width: image.w, height: image.h } = JSON.parse(d.subarray(13)));
    }
    if (topic === '/map/voxels') {
      const head = td.decode(d.subarray(13, 200));
      const full = /"full":true/.test(head), pub = BigInt(/"publish_mono_ns":(\d+)/.exec(head)[1]);
      const later = /"piece":[1-9]/.test(head); // a version in pieces counts once, at its first
      if (!full && !later && now - t0 > 3000000000n) { // after the clients' whole maps went out
        lat.push(Number(now - pub) / 1e6);
        if (c === 0) versions++;
      }
    }
  });
  ws.on('close', () => { closed++; });
}
// One client joining when nobody subscribes: per topic, its first message's age in s.
function late() {
  return new Promise((resolve) => {
    const ws = new WebSocket(`ws://127.0.0.1:${port}/`, ['foxglove.websocket.v1']);
    const topics = {}, age = {};
    let want = 0;
    const done = () => { ws.close(); resolve(age); };
    const timer = setTimeout(done, 5000);
    ws.on('message', (d, bin) => {
      if (!bin) {
        const m = JSON.parse(d.toString());
        if (m.op === 'advertise') {
          want = m.channels.length;
          m.channels.forEach((ch) => { topics[ch.id] = ch.topic; });
          ws.send(JSON.stringify({ op: 'subscribe', subscriptions: m.channels.map((ch) => ({ id: ch.id, channelId: ch.id })) }));
        }
        return;
      }
      const topic = topics[d.readUInt32LE(1)], now = BigInt(Date.now()) * 1000000n;
      if (!(topic in age)) age[topic] = Number(now - d.readBigUInt64LE(5)) / 1e9;
      if (Object.keys(age).length === want) { clearTimeout(timer); done(); }
    });
  });
}

setTimeout(async () => {
  socks.forEach((ws) => ws.close());
  lat.sort((a, b) => a - b);
  const q = (p) => (lat.length ? lat[Math.min(lat.length - 1, Math.floor(p * lat.length))] : NaN);
  const res = { clients: n, closed, versions, p50: q(0.5), p99: q(0.99), max: lat.at(-1),
    bytes_per_update_map: versions ? bytes.map / versions : 0, bytes_per_update_voxels: versions ? bytes.voxels / versions : 0,
    bytes_per_update_points: versions ? bytes.points / versions : 0, bytes_per_update_all: versions ? bytes.all / versions : 0,
    image_bytes: image.n ? image.bytes / image.n : NaN, image_raw_bytes: image.w * image.h * 3 || NaN,
    secs: Number(process.hrtime.bigint() - t0) / 1e9 };
  await new Promise((r) => setTimeout(r, LATE_GAP * 1000));
  res.first_age = await late();
  // /log carries events, not a periodic state: its latest line is as old as the last event
  res.first_age_max = Math.max(...Object.entries(res.first_age).filter(([t]) => t !== '/log').map(([, a]) => a));
  console.log(JSON.stringify(res));
  process.exit(0);
}, secs * 1000);
