// scripts/bench view's clients: N Foxglove WebSocket connections in one process,
// each subscribed to every channel as Foxglove would be. For SECONDS it records,
// per map version, the latency from the version's publish (CLOCK_MONOTONIC, which
// process.hrtime also reads) to its voxel delta's arrival, and the bytes received.
// Prints one JSON line. Usage: node view_clients.js PORT N SECONDS
'use strict';
const WebSocket = require('ws');
const [port, n, secs] = process.argv.slice(2).map(Number);
const lat = [], bytes = { map: 0, voxels: 0, all: 0 };
let versions = 0, closed = 0;
const td = new TextDecoder();
const t0 = process.hrtime.bigint();
for (let c = 0; c < n; c++) {
  const ws = new WebSocket(`ws://127.0.0.1:${port}/`, ['foxglove.websocket.v1']);
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
    }
    if (topic === '/map/voxels') {
      const head = td.decode(d.subarray(13, 200));
      const full = /"full":true/.test(head), pub = BigInt(/"publish_mono_ns":(\d+)/.exec(head)[1]);
      if (!full && now - t0 > 3000000000n) { // after the clients' whole maps went out
        lat.push(Number(now - pub) / 1e6);
        if (c === 0) versions++;
      }
    }
  });
  ws.on('close', () => { closed++; });
}
setTimeout(() => {
  lat.sort((a, b) => a - b);
  const q = (p) => (lat.length ? lat[Math.min(lat.length - 1, Math.floor(p * lat.length))] : NaN);
  console.log(JSON.stringify({ clients: n, closed, versions, p50: q(0.5), p99: q(0.99), max: lat.at(-1),
    bytes_per_update_map: versions ? bytes.map / versions : 0, bytes_per_update_voxels: versions ? bytes.voxels / versions : 0, bytes_per_update_all: versions ? bytes.all / versions : 0,
    secs: Number(process.hrtime.bigint() - t0) / 1e9 }));
  process.exit(0);
}, secs * 1000);
