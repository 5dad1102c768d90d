// vlff-view against bad clients: foreign or missing subprotocols, non-JSON and
// malformed requests, oversized messages, an eleventh client, a client that stops
// reading, wrong tokens, path tricks and garbage over HTTP. Each is refused with a
// reason and counted, and a well-behaved client beside them keeps its stream.
// Also the command line's refusals. Runs vlff-sim (camera frames) and vlff-view.
'use strict';
const assert = require('assert');
const http = require('http');
const net = require('net');
const { spawnSync } = require('child_process');
const WebSocket = require('ws');
const { start, sleep, prog, ok, plan, check } = require('./demo');

const PROTO = 'foxglove.websocket.v1';

// A client that records its text and binary messages and how it closed.
function connect(url, proto = PROTO) {
  return new Promise((resolve, reject) => {
    const ws = new WebSocket(url, proto === null ? [] : [proto]);
    const c = { ws, texts: [], bins: 0, closed: null, adv: null };
    ws.on('message', (d, bin) => {
      if (bin) { c.bins++; return; }
      const m = JSON.parse(d.toString());
      c.texts.push(m);
      if (m.op === 'advertise') c.adv = m.channels;
    });
    ws.on('close', (code, reason) => { c.closed = { code, reason: reason.toString() }; });
    ws.on('unexpected-response', (req, res) => {
      let body = '';
      res.on('data', (d) => { body += d; });
      res.on('end', () => reject(Object.assign(new Error(`HTTP ${res.statusCode}`), { status: res.statusCode, body })));
    });
    ws.on('error', reject);
    ws.on('open', () => resolve(c));
  });
}
const lastStatus = (c) => c.texts.filter((m) => m.op === 'status').at(-1);
async function until(cond, ms, what) {
  const t0 = Date.now();
  while (!cond()) {
    if (Date.now() - t0 > ms) throw new Error(`timed out: ${what}`);
    await sleep(50);
  }
}
function subscribeAll(c) {
  c.ws.send(JSON.stringify({ op: 'subscribe', subscriptions: c.adv.map((ch) => ({ id: ch.id, channelId: ch.id })) }));
}

function cli() {
  const run = (...a) => spawnSync(prog.view, a, { encoding: 'utf8' });
  let r = run('--version');
  assert.ok(r.status === 0 && /^vlff-view \d+\.\d+\.\d+$/m.test(r.stdout));
  r = run('--help');
  assert.ok(r.status === 0 && r.stdout.includes('--token-file') && r.stdout.includes('ws://'));
  for (const [args, msg, code] of [[['--bogus'], "unknown option '--bogus'"], [['--port', '70000'], 'not a number in 0..65535'],
    [['--image-hz', 'x'], '--image-hz'], [['--map', 'nope'], "must start with '/'"],
    [['--www', '/nonexistent'], 'no index.html'], [['extra'], 'unexpected argument'],
    [['--token-file', '/nonexistent/t'], '/nonexistent/t', 1]]) {
    r = run(...args);
    assert.strictEqual(r.status, code || 2, args.join(' '));
    assert.ok(r.stderr.includes(msg), `${args.join(' ')}: ${r.stderr}`);
  }
  ok('command line: --version, --help; six bad arguments exit 2, an unreadable token file 1, each with a reason');
}

async function main() {
  cli();
  const demo = await start({ withNode: false, token: 'secret-token-1', viewArgs: ['--max-queue-mb', '1',
    '--image-hz', '20'] });
  const log = await check(demo, async () => {
    const good = await connect(demo.ws);
    await until(() => good.adv, 5000, 'advertise');
    subscribeAll(good);
    await until(() => good.bins > 2, 20000, 'the good client gets messages');
    const info = good.texts.find((m) => m.op === 'serverInfo');
    assert.deepStrictEqual(info.capabilities, ['clientPublish'], 'a token enables clientPublish');

    for (const proto of ['bogus.v1', null]) {
      const e = await connect(demo.ws, proto).then(() => null, (err) => err);
      assert.ok(e && e.status === 400 && e.body.includes(PROTO), `subprotocol ${proto}: ${e && e.status} ${e && e.body}`);
    }
    ok('a foreign or missing subprotocol gets HTTP 400 naming foxglove.websocket.v1');

    const c = await connect(demo.ws);
    await until(() => c.adv, 5000, 'advertise');
    const requests = [
      ['not json at all', 'not JSON'], ['[1,2,3]', 'no "op"'], ['{"op":42}', 'no "op"'],
      ['{"op":"getParameters","parameterNames":[]}', 'not supported'],
      ['{"op":"subscribe"}', '"subscriptions" must be an array'],
      ['{"op":"subscribe","subscriptions":[{"id":1,"channelId":99}]}', 'no channel 99'],
      ['{"op":"subscribe","subscriptions":[{"id":-1,"channelId":1}]}', 'outside 0..4294967295'],
      ['{"op":"subscribe","subscriptions":[{"id":"a","channelId":1}]}', '"id" must be an integer'],
      ['{"op":"subscribe","subscriptions":[7]}', 'is not an object'],
      ['{"op":"unsubscribe","subscriptionIds":[12345]}', 'not a subscription'],
      ['{"op":"advertise","channels":[{"id":1,"topic":"/evil","encoding":"json","schemaName":"x"}]}', 'only topic'],
    ];
    for (const [req, want] of requests) {
      const n = c.texts.length;
      c.ws.send(req);
      await until(() => c.texts.length > n, 5000, `reply to ${req}`);
      const s = lastStatus(c);
      assert.ok(s && s.level === 2 && s.message.includes(want), `${req}: ${JSON.stringify(s)}`);
    }
    const bin = (bytes) => { const n = c.texts.length; c.ws.send(Buffer.from(bytes)); return n; };
    let n = bin([1, 2]);
    await until(() => c.texts.length > n, 5000, 'short binary');
    assert.ok(lastStatus(c).message.includes('shorter than its 5-byte header'));
    n = bin([1, 9, 0, 0, 0, 123]);
    await until(() => c.texts.length > n, 5000, 'unadvertised channel');
    assert.ok(lastStatus(c).message.includes('not advertised'));
    c.ws.send(JSON.stringify({ op: 'advertise', channels: [{ id: 3, topic: '/vlff/prompts', encoding: 'json',
      schemaName: 'vlff.PromptSet' }] }));
    const post = (body) => {
      const b = Buffer.from(JSON.stringify(body)), m = Buffer.alloc(5 + b.length);
      m[0] = 1; m.writeUInt32LE(3, 1); b.copy(m, 5);
      const k = c.texts.length; c.ws.send(m); return k;
    };
    for (const [body, want] of [[{ token: 'wrong-token-1', prompts: ['a'] }, 'wrong or missing token'],
      [{ prompts: ['a'] }, 'wrong or missing token'],
      [{ token: 'secret-token-1', prompts: [] }, '1..32 prompts'],
      [{ token: 'secret-token-1', prompts: ['x'.repeat(64)] }, 'shorter than 64'],
      [{ token: 'secret-token-1', prompts: [1] }, 'non-empty string'],
      [{ token: 'secret-token-1', prompts: ['chair'] }, 'mailbox']]) {
      n = post(body);
      await until(() => c.texts.length > n, 5000, JSON.stringify(body));
      assert.ok(lastStatus(c).message.includes(want), `${JSON.stringify(body)}: ${lastStatus(c).message}`);
    }
    assert.strictEqual(c.closed, null, 'bad requests leave the connection open');
    c.ws.send(JSON.stringify({ op: 'subscribe', subscriptions: [{ id: 5, channelId: 6 }] }));
    await until(() => c.bins > 0, 5000, 'a valid subscribe after the bad ones');
    ok(`${requests.length + 8} malformed requests and posts each answered by a status error; the connection stays`);

    const big = await connect(demo.ws);
    big.ws.send('x'.repeat(100 * 1024));
    await until(() => big.closed, 5000, 'oversized message closes');
    assert.strictEqual(big.closed.code, 1009);
    assert.ok(big.closed.reason.includes('larger than 65536 bytes'), big.closed.reason);
    ok('a 100 KiB message closes that connection with 1009 and a reason');

    const many = [];
    for (let i = 0; many.length + 2 < 10; i++) many.push(await connect(demo.ws));
    const e = await connect(demo.ws).then(() => null, (err) => err);
    assert.ok(e && e.status === 503 && e.body.includes('too many clients (10)'), `11th client: ${e && e.status}`);
    many.forEach((m) => m.ws.close());
    ok('with ten clients connected an eleventh gets HTTP 503 "too many clients (10)"');

    // A client that subscribes to the camera at 20 Hz and stops reading: its queue
    // passes 1 MiB and it is dropped; the good client's stream goes on.
    const slow = await connect(demo.ws);
    await until(() => slow.adv, 5000, 'advertise');
    slow.ws._socket.pause();
    subscribeAll(slow);
    const before = good.bins;
    await until(() => /dropped: too slow/.test(demo.log('view')), 30000, 'the slow client dropped');
    await until(() => good.bins > before + 20, 20000, 'the good client still receives');
    ok('a client that stops reading is dropped as too slow; the others keep receiving');

    for (const p of ['/../../../../etc/passwd', '/%2e%2e/%2e%2e/etc/passwd', '/nope.html']) {
      const st = await new Promise((resolve) => http.get({ host: '127.0.0.1', port: demo.port, path: p },
        (res) => { res.resume(); resolve(res.statusCode); }).on('error', () => resolve('error')));
      assert.notStrictEqual(st, 200, `${p} must not be served`);
    }
    const page = await new Promise((resolve) => http.get(demo.url, (res) => {
      let b = ''; res.on('data', (d) => { b += d; }); res.on('end', () => resolve([res.statusCode, b]));
    }));
    assert.ok(page[0] === 200 && page[1].includes('three/three.module.js'));
    await new Promise((resolve) => {
      const s = net.connect(demo.port, '127.0.0.1', () => s.end('\x00\xff garbage \r\n\r\n\r\n'));
      s.on('close', resolve); s.on('error', resolve); s.resume();
    });
    const after = good.bins;
    await until(() => good.bins > after + 2 && good.closed === null, 10000, 'good client after garbage');
    ok('path escapes and unknown files are not served, garbage over TCP is dropped, the page is');

    const status = await new Promise((resolve) => {
      const t = setInterval(() => {
        const s = demo.log('view');
        if (s) { clearInterval(t); resolve(s); }
      }, 100);
    });
    assert.ok(/refused 127\.0\.0\.1: unknown or missing WebSocket subprotocol/.test(status));
    good.ws.close();
  });
  assert.strictEqual(demo.viewExit, 0, `vlff-view exits 0 on SIGINT: ${log.slice(-2000)}`);
  ok('vlff-view stops cleanly on SIGINT after all that');
  plan();
}
main();
