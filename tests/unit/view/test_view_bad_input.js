// vlff-view against bad clients: foreign or missing subprotocols, non-JSON and
// malformed requests, oversized messages, an eleventh client, a client that stops
// reading, wrong tokens, and HTTP requests it does not serve (other methods,
// malformed heads, unknown paths and path escapes, long targets, large heads, a head
// never finished, a flood). Each is refused with a reason and counted (HTTP ones by
// status in the status channel, their log lines rate-limited), and a well-behaved
// client beside them keeps its stream. The page's files come with a self-only
// Content-Security-Policy. Also the command line's refusals. Runs vlff-sim (camera
// frames) and vlff-view.
'use strict';
const assert = require('assert');
const fs = require('fs');
const os = require('os');
const path = require('path');
const net = require('net');
const { spawnSync } = require('child_process');
const WebSocket = require('ws');
const { start, sleep, prog, ok, plan, check } = require('./demo');

const PROTO = 'foxglove.websocket.v1';

// A client that records its text and binary messages and how it closed.
function connect(url, proto = PROTO) {
  return new Promise((resolve, reject) => {
    const ws = new WebSocket(url, proto === null ? [] : [proto]);
    const c = { ws, texts: [], bins: 0, closed: null, adv: null, status: null, statuses: 0 };
    ws.on('message', (d, bin) => {
      if (bin) {
        c.bins++;
        const ch = c.adv && c.adv.find((a) => a.id === d.readUInt32LE(1));
        if (ch && ch.topic === '/vlff/status') { c.status = JSON.parse(d.subarray(13).toString()); c.statuses++; }
        return;
      }
      const m = JSON.parse(d.toString());
      c.texts.push(m);
      if (m.op === 'advertise') c.adv = m.channels;
    });
    ws.on('close', (code, reason) => { c.closed = { code, reason: reason.toString() }; });
    ws.on('unexpected-response', (req, res) => {
      let body = '';
      res.on('data', (d) => { body += d; });
      res.on('end', () => reject(Object.assign(new Error(`HTTP ${res.statusCode}`), { status: res.statusCode, body,
        type: res.headers['content-type'] || '' })));
    });
    ws.on('error', reject);
    ws.on('open', () => resolve(c));
  });
}
// One HTTP exchange over a raw socket: what the server answers to exactly these
// bytes, up to its close.
function raw(bytes) {
  return new Promise((resolve, reject) => {
    const s = net.connect(demo_port, '127.0.0.1', () => s.write(Buffer.from(bytes, 'latin1')));
    const got = [];
    s.on('data', (d) => got.push(d));
    s.on('error', reject);
    s.on('close', () => {
      const text = Buffer.concat(got).toString('latin1'), cut = text.indexOf('\r\n\r\n');
      const head = cut < 0 ? text : text.slice(0, cut), m = /^HTTP\/1\.1 (\d{3}) (.*)/.exec(head);
      const headers = {};
      for (const l of head.split('\r\n').slice(1)) {
        const i = l.indexOf(':');
        headers[l.slice(0, i).toLowerCase()] = l.slice(i + 1).trim();
      }
      resolve({ text, head, headers, status: m ? Number(m[1]) : null, reason: m ? m[2] : '',
        body: cut < 0 ? '' : text.slice(cut + 4) });
    });
  });
}
let demo_port = 0;
const www = `${process.env.VLFF_BINARY_DIR}/node/view/www`;
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
  const run = (...a) => spawnSync(prog.view, a, { encoding: 'utf8', timeout: 10000 });
  let r = run('--version');
  assert.ok(r.status === 0 && /^vlff-view \d+\.\d+\.\d+$/m.test(r.stdout));
  r = run('--help');
  assert.ok(r.status === 0 && r.stdout.includes('--token-file') && r.stdout.includes('ws://'));
  for (const [args, msg, code] of [[['--bogus'], "unknown option '--bogus'"], [['--port', '70000'], 'not a number in 0..65535'],
    [['--image-hz', 'x'], '--image-hz'], [['--map', 'nope'], "must start with '/'"],
    [['--www', '/nonexistent'], 'no index.html'], [['extra'], 'unexpected argument'],
    [['--play-rate', '2'], '--play-rate without --play'], [['--record-level', '5'], '--record-level without --record'],
    [['--force'], '--force without --record'], [['--grid-hz', '0'], 'not a number in 0.1..10'],
    [['--grid-z', 'nan'], '--grid-z'],
    [['--token-file', '/nonexistent/t'], '/nonexistent/t', 1]]) {
    r = run(...args);
    assert.strictEqual(r.status, code || 2, args.join(' '));
    assert.ok(r.stderr.includes(msg), `${args.join(' ')}: ${r.stderr}`);
  }
  ok('command line: --version, --help; eleven bad arguments exit 2 (--play-rate, --record-level and --force without ' +
    'their mode among them), an unreadable token file 1, each with a reason');

  // A FIFO or a directory named as the token file: refused at once (a plain open of
  // a FIFO would wait for a writer forever), naming the file and what it is.
  const dir = fs.mkdtempSync(path.join(os.tmpdir(), 'vlff-view-token-'));
  const fifo = path.join(dir, 'token.fifo');
  assert.strictEqual(spawnSync('mkfifo', [fifo]).status, 0, 'mkfifo');
  for (const [file, what] of [[fifo, 'is a FIFO'], [dir, 'is a directory']]) {
    r = spawnSync(prog.view, ['--port', '0', '--token-file', file], { encoding: 'utf8', timeout: 10000 });
    assert.strictEqual(r.status, 1, `--token-file ${what}: status ${r.status} signal ${r.signal}`);
    assert.ok(r.stderr.includes(`--token-file ${file}: ${what}, expected a regular file`), r.stderr);
  }
  fs.rmSync(dir, { recursive: true, force: true });
  ok('a FIFO or a directory as --token-file is refused at once with exit 1, naming what it is');
}

async function main() {
  cli();
  const started = Date.now();
  const demo = await start({ withNode: false, token: 'secret-token-1', viewArgs: ['--max-queue-mb', '1',
    '--image-hz', '20'] });
  const up = Date.now(); // the viewer started between `started` and now
  demo_port = demo.port;
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
      assert.ok(/^text\/plain/.test(e.type) && !/<html|error\.css/i.test(e.body), `a plain sentence: ${e.type} ${e.body}`);
    }
    // 1.5 s after the viewer was surely up, so that a stamp from its start is at
    // least that (counted from `started`, a slow start under load left it below 1)
    while (Date.now() - up < 1500) await sleep(100);
    const r400 = await raw(`GET / HTTP/1.1\r\nHost: 127.0.0.1:${demo_port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n` +
      'Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol:  bogus.v2 \r\n\r\n');
    assert.strictEqual(r400.status, 400, r400.text);
    assert.strictEqual(r400.body, `unknown or missing WebSocket subprotocol "bogus.v2"; this server speaks ${PROTO}\n`);
    const elapsed = (Date.now() - started) / 1000;
    await until(() => /refused 127\.0\.0\.1: unknown or missing WebSocket subprotocol "bogus\.v2"/.test(demo.log('view')),
      5000, 'the refusal logged');
    const vlog = demo.log('view');
    assert.ok(!/could not be handed/.test(vlog), `no misleading line after a refusal: ${vlog}`);
    // the stamps count from the viewer's start: its first warning is not at 0
    const stamp = Number(/\[ *([0-9.]+)\] W vlff-view: refused 127\.0\.0\.1: unknown or missing WebSocket subprotocol "bogus\.v2"/.exec(vlog)[1]);
    assert.ok(stamp >= 1 && stamp <= elapsed + 1, `the refusal stamped ${stamp} s, ${elapsed} s after the start`);
    ok('a foreign or missing subprotocol gets HTTP 400 with a plain sentence naming foxglove.websocket.v1; ' +
      `logged once, stamped ${stamp} s from the viewer's start`);

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
    await until(() => many.every((m) => m.closed), 5000, 'the clients closed');
    ok('with ten clients connected an eleventh gets HTTP 503 "too many clients (10)"');

    // A client that subscribes to the camera and stops reading while it sends requests
    // that each earn a thousand status errors (compressed images alone would take a
    // minute to fill the kernel's socket buffers and then 1 MiB): its queue
    // passes 1 MiB and it is dropped; the good client's stream goes on. A closed
    // client's slot is free once the relayed connection behind it is gone too,
    // a moment after its close handshake: a 503 before then is tried again.
    let slow = null;
    for (const t0 = Date.now(); !slow; await new Promise((r) => setTimeout(r, 50))) {
      slow = await connect(demo.ws).catch((err) => {
        if (err.status !== 503 || Date.now() - t0 > 5000) throw err;
        return null;
      });
    }
    await until(() => slow.adv, 5000, 'advertise');
    slow.ws._socket.pause();
    subscribeAll(slow);
    const noisy = JSON.stringify({ op: 'subscribe', subscriptions: new Array(1000).fill(7) });
    for (let i = 0; i < 100; i++) slow.ws.send(noisy);
    const before = good.bins;
    await until(() => /dropped: too slow/.test(demo.log('view')), 30000, 'the slow client dropped');
    // it reads again: what was queued for it is gone, a close frame with the reason comes
    slow.ws._socket.resume();
    await until(() => slow.closed, 15000, 'the slow client gets its close frame');
    assert.strictEqual(slow.closed.code, 1013, JSON.stringify(slow.closed));
    assert.ok(/^too slow: \d+ bytes unsent, above --max-queue-mb \(1048576 bytes\)$/.test(slow.closed.reason),
      JSON.stringify(slow.closed));
    await until(() => good.bins > before + 20, 20000, 'the good client still receives');
    ok(`a client that stops reading is dropped as too slow, closed with 1013 "${slow.closed.reason}"; ` +
      'the others keep receiving');

    // HTTP requests the viewer does not serve: each gets its status and a sentence
    // from the viewer, is counted by status in the status channel, and the good
    // client's stream goes on meanwhile.
    const counts = () => ({ ...good.status.viewer.http_refused });
    const freshStatus = async () => {
      const n = good.statuses;
      await until(() => good.statuses > n, 5000, 'a status message');
      return good.status;
    };
    const base = (await freshStatus()).viewer.http_refused;
    const slowHead = raw('GET / HTTP/1.1\r\nHost: x\r\n'); // never finished: 408 after 5 s
    const long = 'a'.repeat(3000);
    const cases = [
      ['POST / HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\n\r\n', 405, 'method POST is not allowed'],
      ['DELETE /index.html HTTP/1.1\r\n\r\n', 405, 'GET and HEAD'],
      ['BREW /index.html HTTP/1.1\r\n\r\n', 405, 'method BREW'],
      ['\x00\xff garbage \r\n\r\n\r\n', 400, 'does not start with a method'],
      ['GET / HTTP/1.1\r\nno colon here\r\n\r\n', 400, 'is not "Name: value"'],
      ['GET / HTTP/1.1\nHost: x\n\n', 400, 'CRLF'],
      ['GET / HTTP/1.1\r\nUpgrade: h2c\r\n\r\n', 400, 'only an upgrade to WebSocket'],
      ['GET / HTTP/1.1\r\nContent-Length: 5\r\n\r\nhello', 400, 'carries no body'],
      ['GET / HTTP/2.0\r\n\r\n', 505, 'HTTP/2.0 is not supported'],
      ['GET /nope.html HTTP/1.1\r\n\r\n', 404, '/nope.html is not a file of this page'],
      ['GET /../../../../etc/passwd HTTP/1.1\r\n\r\n', 404, 'not a file of this page'],
      ['GET /%2e%2e/%2e%2e/etc/passwd HTTP/1.1\r\n\r\n', 404, 'not a file of this page'],
      ['GET /three HTTP/1.1\r\n\r\n', 404, 'not a file of this page'],
      ['GET /nope HTTP/1.1\r\nUpgrade: websocket\r\n\r\n', 404, 'served at /'],
      ['HEAD /nope.html HTTP/1.1\r\n\r\n', 404, ''],
      [`GET /${long} HTTP/1.1\r\n\r\n`, 414, 'the request target is 3001 bytes, the limit is 2048'],
      [`GET /${long.repeat(40)}`, 414, 'request line is longer than'],
      [`GET / HTTP/1.1\r\nX-Pad: ${long.repeat(4)}\r\n\r\n`, 431, 'longer than 8192 bytes'],
      [`GET / HTTP/1.1\r\n${'X-A: b\r\n'.repeat(100)}\r\n`, 431, 'more than 64 header lines'],
    ];
    const tally = {};
    for (const [req, status, why] of cases) {
      const r = await raw(req);
      assert.strictEqual(r.status, status, `${JSON.stringify(req.slice(0, 60))}: ${r.text.slice(0, 200)}`);
      assert.ok(r.reason.length > 0 && r.head.includes('Connection: close'), r.head);
      if (status === 405) assert.ok(r.head.includes('Allow: GET, HEAD'), r.head);
      if (req.startsWith('HEAD')) assert.strictEqual(r.body, '', 'a HEAD answer has no body');
      else assert.ok(r.body.includes(why), `${JSON.stringify(req.slice(0, 60))}: body ${r.body}`);
      tally[status] = (tally[status] || 0) + 1;
    }
    const before408 = good.bins;
    const t408 = await slowHead;
    assert.strictEqual(t408.status, 408, t408.text);
    assert.ok(t408.body.includes('no complete request head within 5 s'));
    tally[408] = 1;
    assert.ok(good.bins > before408 + 5 && good.closed === null, 'the good client received all along');
    ok(`${cases.length + 1} bad HTTP requests answered 400, 404, 405, 408, 414, 431, 505 with a reason each`);

    // A flood of malformed requests: all answered and counted, the log keeps five lines
    // of them, the good client keeps its stream.
    const flood = 300, floodBins = good.bins;
    for (let i = 0; i < flood; i += 30) {
      const batch = [];
      for (let k = 0; k < 30; k++) batch.push(raw('GET / HTTP/1.1\r\nbad header line\r\n\r\n'));
      for (const r of await Promise.all(batch)) assert.strictEqual(r.status, 400);
    }
    tally[400] += flood;
    await until(() => good.bins > floodBins + 5 && good.closed === null, 10000, 'the good client after the flood');
    let now = null;
    await until(() => {
      now = counts();
      return Object.keys(tally).every((k) => now[k] - base[k] === tally[k]);
    }, 10000, `the status counts ${JSON.stringify(tally)} more refusals than ${JSON.stringify(base)}`);
    for (const k of Object.keys(now)) if (!tally[k]) assert.strictEqual(now[k], base[k], `HTTP ${k} counted`);
    const logged = (demo.log('view').match(/is not "Name: value" \[HTTP 400/g) || []).length;
    assert.ok(logged <= 5, `${logged} log lines for ${flood + 1} malformed header lines`);
    ok(`a flood of ${flood} malformed requests: each answered 400 and counted (status: ${JSON.stringify(now)}), ` +
      `${logged} logged, the good client's stream uninterrupted`);

    // The page's files: GET and HEAD with the Content-Security-Policy.
    for (const [method, path, type] of [['GET', '/', 'text/html'], ['GET', '/view.js', 'text/javascript'],
      ['GET', '/three/three.module.js', 'text/javascript'], ['HEAD', '/view.css', 'text/css']]) {
      const r = await raw(`${method} ${path} HTTP/1.1\r\nHost: 127.0.0.1:${demo_port}\r\n\r\n`);
      assert.strictEqual(r.status, 200, `${method} ${path}: ${r.head}`);
      assert.ok(r.headers['content-type'].startsWith(type), r.head);
      const csp = r.headers['content-security-policy'] || '';
      assert.ok(/(^|; )default-src 'self'/.test(csp) && /script-src 'self'(;|$)/.test(csp) && !csp.includes('unsafe'),
        `${path}: CSP "${csp}"`);
      assert.strictEqual(r.headers['x-content-type-options'], 'nosniff');
      assert.strictEqual(Number(r.headers['content-length']), method === 'HEAD' ? fs.statSync(`${www}${path}`).size
        : Buffer.byteLength(r.body, 'latin1'));
      if (method === 'HEAD') assert.strictEqual(r.body, '');
      if (path === '/') assert.ok(r.body.includes('src="view.js"'));
    }
    ok('the page\'s files are served (GET and HEAD) with a self-only Content-Security-Policy');
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
