// vlff-view as Foxglove sees it: the @foxglove/ws-protocol client connects to a
// running demo (vlff-sim + vlff-node + vlff-view), subscribes to every channel,
// checks every message against the schema its channel advertised and, for the
// foxglove.* channels, the advertised schema and every message against Foxglove's
// published one (the npm package @foxglove/schemas: field names, types, required
// fields, no field it does not name), and checks the voxels it was sent (a whole
// map, then deltas) against `vlff-shm label` at the same points and map version.
'use strict';
const assert = require('assert');
const { FoxgloveClient } = require('@foxglove/ws-protocol');
const published = require('@foxglove/schemas/jsonschema');
const WebSocket = require('ws');
const { start, shm, shmAsync, sleep, waitVersion, learnerOfStat, ok, plan, check } = require('./demo');
const { validate, sameFields } = require('./schema');

// Foxglove's published JSON Schema for a schema name "foxglove.X", or undefined.
const publishedOf = (name) => (name.startsWith('foxglove.') ? published[name.slice(9)] : undefined);

const FREE = 65534;
const png = require('./png');

// A baseline or progressive JPEG's size from its start-of-frame segment.
function jpegSize(b) {
  assert.ok(b[0] === 0xff && b[1] === 0xd8 && b.at(-2) === 0xff && b.at(-1) === 0xd9, 'a whole JPEG (SOI ... EOI)');
  for (let p = 2; p + 9 < b.length;) {
    assert.strictEqual(b[p], 0xff, `a JPEG marker at ${p}`);
    const m = b[p + 1], len = b.readUInt16BE(p + 2);
    if (m >= 0xc0 && m <= 0xc2) return { height: b.readUInt16BE(p + 5), width: b.readUInt16BE(p + 7) };
    p += 2 + len;
  }
  throw new Error('no start-of-frame segment in the JPEG');
}

async function main() {
  const demo = await start();
  await check(demo, async () => {
    await waitVersion(demo, 2, 240000);
    const client = new FoxgloveClient({ ws: new WebSocket(demo.ws, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]) });
    const chans = {}, bySub = {}, got = {};
    const voxels = new Map(), checkedPublished = {};
    const scene = new Map();
    let grid = null, voxelVersion = 0, voxelT = 0n, sceneT = 0n, fullSeen = 0, deltaSeen = 0, bad = [];
    let serverInfo = null, waiters = [];
    const td = new TextDecoder();
    client.on('serverInfo', (i) => { serverInfo = i; });
    client.on('advertise', (cs) => {
      for (const c of cs) {
        chans[c.topic] = c;
        bySub[client.subscribe(c.id)] = c;
      }
    });
    client.on('message', ({ subscriptionId, timestamp, data }) => {
      const c = bySub[subscriptionId], msg = JSON.parse(td.decode(data));
      const errs = validate(JSON.parse(c.schema), msg);
      if (errs.length) bad.push(`${c.topic}: ${errs.slice(0, 3).join('; ')}`);
      const pub = publishedOf(c.schemaName);
      if (pub) {
        const perrs = validate(pub, msg, '$', [], true);
        if (perrs.length) bad.push(`${c.topic} against @foxglove/schemas: ${perrs.slice(0, 3).join('; ')}`);
        checkedPublished[c.schemaName] = (checkedPublished[c.schemaName] || 0) + 1;
      }
      (got[c.topic] = got[c.topic] || []).push(msg);
      if (c.topic === '/map/voxels') {
        if (msg.full) { voxels.clear(); fullSeen++; } else deltaSeen++;
        grid = msg;
        for (let n = 0; n < msg.voxels.length; n += 3) {
          if (msg.voxels[n + 1] >= FREE) voxels.delete(msg.voxels[n]);
          else voxels.set(msg.voxels[n], [msg.voxels[n + 1], msg.voxels[n + 2]]);
        }
        assert.strictEqual(voxels.size, msg.occupied, `v${msg.version}: client holds as many voxels as the map`);
        voxelVersion = msg.version;
        voxelT = timestamp;
      } else if (c.topic === '/map') {
        for (const d of msg.deletions) { if (d.type === 1) scene.clear(); else scene.delete(d.id); }
        for (const e of msg.entities) scene.set(e.id, e);
        sceneT = timestamp;
      }
      waiters = waiters.filter((w) => !w());
    });
    const until = (cond, ms, what) => new Promise((resolve, reject) => {
      if (cond()) return resolve();
      const t = setTimeout(() => reject(new Error(`timed out: ${what}`)), ms);
      waiters.push(() => { if (cond()) { clearTimeout(t); resolve(); return true; } return false; });
    });

    await until(() => serverInfo && Object.keys(chans).length === 8, 10000, 'serverInfo and advertise');
    assert.deepStrictEqual(Object.keys(chans).sort(),
      ['/camera/calibration', '/camera/image', '/camera/labels', '/log', '/map', '/map/voxels', '/tf', '/vlff/status']);
    for (const c of Object.values(chans)) {
      assert.strictEqual(c.encoding, 'json');
      assert.strictEqual(c.schemaEncoding, 'jsonschema');
      assert.strictEqual(JSON.parse(c.schema).title, c.schemaName);
    }
    assert.strictEqual(chans['/map'].schemaName, 'foxglove.SceneUpdate');
    assert.strictEqual(chans['/camera/image'].schemaName, 'foxglove.CompressedImage');
    assert.strictEqual(chans['/camera/labels'].schemaName, 'foxglove.CompressedImage');
    assert.strictEqual(chans['/camera/calibration'].schemaName, 'foxglove.CameraCalibration');
    assert.strictEqual(chans['/tf'].schemaName, 'foxglove.FrameTransform');
    assert.deepStrictEqual(serverInfo.capabilities, [], 'no clientPublish without a token');
    assert.strictEqual(chans['/log'].schemaName, 'foxglove.Log');
    ok('serverInfo and eight channels advertised with JSON schemas');
    const foxgloveChannels = Object.values(chans).filter((c) => c.schemaName.startsWith('foxglove.'));
    for (const c of foxgloveChannels) {
      const pub = publishedOf(c.schemaName);
      assert.ok(pub && pub.title === c.schemaName, `${c.schemaName} is a schema of @foxglove/schemas`);
      assert.deepStrictEqual(sameFields(JSON.parse(c.schema), pub), [],
        `${c.topic}: the advertised ${c.schemaName} against @foxglove/schemas`);
    }
    ok(`${foxgloveChannels.map((c) => `${c.topic} (${c.schemaName})`).join(', ')}: advertised schemas have the ` +
      'field names, types and required fields of @foxglove/schemas');

    await until(() => fullSeen >= 1 && deltaSeen >= 2 && ['/camera/image', '/camera/labels', '/camera/calibration',
      '/tf', '/vlff/status', '/log']
      .every((t) => got[t]), 120000, 'a whole map, two deltas and every channel');
    assert.deepStrictEqual(bad, [], 'every message matches its advertised schema and the published one');
    for (const n of ['foxglove.SceneUpdate', 'foxglove.CompressedImage', 'foxglove.CameraCalibration',
      'foxglove.FrameTransform', 'foxglove.Log'])
      assert.ok(checkedPublished[n] > 0, `messages checked against ${n}`);
    ok(`every channel delivered, ${Object.values(got).reduce((a, l) => a + l.length, 0)} messages match their schemas; ` +
      `against @foxglove/schemas: ${JSON.stringify(checkedPublished)}`);

    // The voxels the client holds against vlff-shm label at the same version. The
    // learner is paused meanwhile (a loaded machine may need longer than its publish
    // period for the comparison); the viewer goes on serving.
    demo.pause();
    await sleep(1500);
    let checked = 0;
    for (let attempt = 0; attempt < 20 && !checked; attempt++) {
      const v = voxelVersion, [nx, ny] = grid.dims, s = grid.voxel_size;
      const occupied = [...voxels.keys()];
      const picks = [];
      for (let n = 0; n < 40; n++) picks.push(occupied[Math.floor(Math.random() * occupied.length)]);
      for (let n = 0; n < 20; n++) picks.push(Math.floor(Math.random() * nx * ny * grid.dims[2]));
      const rows = [];
      for (const idx of picks) {
        const ijk = [idx % nx, Math.floor(idx / nx) % ny, Math.floor(idx / (nx * ny))];
        const p = ijk.map((c, a) => (grid.origin[a] + (c + 0.5) * s).toFixed(4));
        const out = await shmAsync('label', demo.names.map, ...p);
        const m = /^label (\d+) confidence (\d+) prompt (.*) version (\d+)$/m.exec(out);
        rows.push({ idx, label: Number(m[1]), conf: Number(m[2]), prompt: m[3], version: Number(m[4]) });
        if (Number(m[4]) !== v) break;
      }
      // the node published meanwhile: compare again at the next version
      if (rows.some((r) => r.version !== v) || voxelVersion !== v) {
        await until(() => voxelVersion > v, 10000, 'the next version');
        continue;
      }
      for (const r of rows) {
        const mine = voxels.get(r.idx);
        if (r.label >= FREE) assert.strictEqual(mine, undefined, `voxel ${r.idx}: free/unknown in the map`);
        else {
          assert.deepStrictEqual(mine, [r.label, r.conf], `voxel ${r.idx} at version ${v}`);
          assert.strictEqual(grid.prompts[r.label], r.prompt);
        }
        checked++;
      }
    }
    assert.ok(checked >= 60, 'a version stayed long enough to compare');
    ok(`${checked} voxels (label, confidence, prompt) equal vlff-shm label's at the same version`);

    // The scene (Foxglove's cubes) holds the same voxels in the prompts' colours.
    await until(() => sceneT === voxelT, 10000, 'scene and voxels of one version');
    const centres = new Map();
    for (const [idx, [label]] of voxels) {
      const [nx, ny] = grid.dims, ijk = [idx % nx, Math.floor(idx / nx) % ny, Math.floor(idx / (nx * ny))];
      centres.set(ijk.map((c, a) => (grid.origin[a] + (c + 0.5) * grid.voxel_size).toFixed(3)).join(), label);
    }
    let cubes = 0;
    for (const e of scene.values()) {
      for (const c of e.cubes) {
        const key = [c.pose.position.x, c.pose.position.y, c.pose.position.z].map((x) => x.toFixed(3)).join();
        assert.ok(centres.has(key), `cube at ${key} is an occupied voxel`);
        const hex = '#' + [c.color.r, c.color.g, c.color.b].map((x) => Math.round(x * 255).toString(16).padStart(2, '0')).join('');
        assert.strictEqual(hex, grid.colors[centres.get(key)], `cube at ${key} in its prompt's colour`);
        cubes++;
      }
    }
    assert.strictEqual(cubes, voxels.size);
    ok(`the scene's ${scene.size} brick entities hold ${cubes} cubes, one per occupied voxel, in prompt colours`);
    // The learner's own status, still paused: the status channel carries the block
    // vlff-shm stat reads (the same update), every number equal.
    const before = got['/vlff/status'].length;
    await until(() => got['/vlff/status'].length > before, 10000, 'a status message during the pause');
    const learner = { ...got['/vlff/status'].at(-1).learner }, fromStat = learnerOfStat(shm('stat', demo.names.map));
    assert.ok(learner.age_s >= 0);
    delete learner.age_s;
    assert.deepStrictEqual(learner, fromStat, 'the status channel\'s learner and vlff-shm stat');
    assert.ok(learner.frames_in > 0 && learner.keyframes > 0 && learner.iterations > 0 && learner.iterations_per_s > 0,
      `a learning node: ${JSON.stringify(learner)}`);
    assert.strictEqual(learner.frames_refused, learner.refused.reduce((a, r) => a + r.count, 0));
    assert.ok(learner.refused.some((r) => r.reason === 'no pose'), 'the reasons travel with their names');
    ok(`learner status (${learner.frames_in} frames in, ${learner.keyframes} keyframes, ${learner.iterations} ` +
      `iterations, loss ${learner.loss}, PSNR ${learner.psnr}) equals vlff-shm stat's`);
    demo.resume();
    const resumed = voxelVersion;
    await until(() => voxelVersion > resumed && got['/vlff/status'].at(-1).map.writer_alive, 30000, 'the learner again');

    const st = got['/vlff/status'].at(-1), stat = shm('stat', demo.names.map);
    const prompts = [...stat.matchAll(/^prompt \d+ (.*)$/gm)].map((m) => m[1]);
    assert.deepStrictEqual(st.map.prompts, prompts);
    assert.deepStrictEqual(grid.prompts, prompts);
    assert.strictEqual(st.map.dims.join(' '), /^grid_dims (.*)$/m.exec(stat)[1]);
    assert.strictEqual(st.map.generation, Number(/^generation (\d+)$/m.exec(stat)[1]));
    assert.ok(st.frames.attached && st.frames.head > 0 && st.map.writer_alive);
    ok('status: prompts, grid, generation as vlff-shm stat says; frames arriving');

    // /log: lines of the kinds logch.c makes, from vlff-view or vlff-node
    const kinds = [/^map segment \/\S+ (attached|not there yet|gone)/, /^frame ring \/\S+ (attached|gone)$/,
      /^the map's writer (stopped|is alive again)/, /^learner state \S+/, /^error flags 0x[0-9a-f]+: /,
      /^\d+ frames? (refused|lost): .+ \(\d+ in all\)$/];
    for (const m of got['/log']) {
      assert.ok(['vlff-view', 'vlff-node'].includes(m.name) && [2, 3, 4].includes(m.level) &&
        kinds.some((k) => k.test(m.message)), `a /log line of a known kind: ${JSON.stringify(m)}`);
    }
    ok(`/log: ${got['/log'].length} foxglove.Log lines (${got['/log'].map((m) => m.message).slice(0, 3).join('; ')})`);

    const im = got['/camera/image'].at(-1), li = got['/camera/labels'].at(-1);
    assert.strictEqual(`${im.format} ${im.frame_id}`, 'jpeg camera');
    const jpg = Buffer.from(im.data, 'base64'), size = jpegSize(jpg);
    assert.strictEqual(`${size.width}x${size.height}`, '320x240', 'the JPEG is the 320x240 frame');
    const jpegVsRaw = Math.max(...got['/camera/image'].map((m) => Buffer.from(m.data, 'base64').length)) / (320 * 240 * 3);
    assert.ok(jpegVsRaw <= 1 / 8, `the largest JPEG is ${jpegVsRaw.toFixed(3)} of the raw RGB frame`);
    assert.strictEqual(li.format, 'png');
    const lb = png.decode(Buffer.from(li.data, 'base64'));
    assert.strictEqual(`${lb.width}x${lb.height}`, '160x120');
    const palette = new Set(grid.colors.concat(['#000000', '#282828', '#808080']));
    for (let p = 0; p < lb.width * lb.height; p += 97) {
      const hex = '#' + lb.pixel(p % lb.width, Math.floor(p / lb.width)).map((x) => x.toString(16).padStart(2, '0')).join('');
      assert.ok(palette.has(hex), `label image pixel ${hex} is a prompt colour`);
    }
    const q = got['/tf'].at(-1).rotation;
    assert.ok(Math.abs(Math.hypot(q.x, q.y, q.z, q.w) - 1) < 1e-6, 'unit quaternion');
    // the calibration: vlff-sim's pinhole (65 degrees across 320 pixels, centred), in
    // OpenCV's convention (principal point at the centre minus half a pixel)
    const cal = got['/camera/calibration'].at(-1), f = 0.5 * 320 / Math.tan(0.5 * 65 * Math.PI / 180);
    assert.strictEqual(`${cal.width}x${cal.height} ${cal.frame_id} ${cal.distortion_model}`, '320x240 camera plumb_bob');
    const near = (a, b) => a.every((x, i) => Math.abs(x - b[i]) < 1e-6);
    assert.ok(near(cal.K, [f, 0, 159.5, 0, f, 119.5, 0, 0, 1]), `K ${cal.K}`);
    assert.ok(near(cal.P, [f, 0, 159.5, 0, 0, f, 119.5, 0, 0, 0, 1, 0]) && near(cal.R, [1, 0, 0, 0, 1, 0, 0, 0, 1]) &&
      near(cal.D, [0, 0, 0, 0, 0]), JSON.stringify(cal));
    ok(`camera image as JPEG (${jpg.length} bytes, at most ${jpegVsRaw.toFixed(3)} of raw RGB), label image as PNG ` +
      'in prompt colours, the camera calibration and a unit-quaternion camera pose');

    const imageSub = Object.keys(bySub).find((k) => bySub[k].topic === '/camera/image');
    client.unsubscribe(Number(imageSub));
    // A barrier rather than a guess at how long images stay in flight: the
    // server answers requests in order and drops what it had queued for the
    // subscription, so once it has answered a later request (an unknown
    // id's error) every image of the subscription has arrived.
    const statuses = [];
    client.on('status', (st) => statuses.push(st));
    client.unsubscribe(999999);
    await until(() => statuses.some((st) => /is not a subscription/.test(st.message)), 10000,
      'the answer to a later request');
    const n = got['/camera/image'].length;
    await sleep(2000);
    assert.strictEqual(got['/camera/image'].length, n, 'no images after unsubscribing');
    ok('unsubscribe stops a channel');
    client.close();
  });
  plan();
}
main();
