// vlff-view as Foxglove sees it: the @foxglove/ws-protocol client connects to a
// running demo (vlff-sim + vlff-node + vlff-view), subscribes to every channel,
// checks every message against the schema its channel advertised and, for the
// foxglove.* channels, the advertised schema and every message against Foxglove's
// published one (the npm package @foxglove/schemas: field names, types, required
// fields, no field it does not name), and checks the voxels it was sent (a whole
// map, then deltas) against `vlff-shm label` at the same points and map version.
// /map/points (foxglove.PointCloud in protobuf) is decoded as Foxglove decodes it,
// with protobufjs from the FileDescriptorSet the channel advertises; that
// descriptor is compared with the .proto definitions @foxglove/schemas generates,
// and a second viewer with --max-queue-mb 1 sends a client the whole map in pieces
// under its queue limit, the points equal to the voxels of /map/voxels; that viewer
// takes its segments and frame ids from a config (--config), and a config the
// loader refuses stops it with the loader's message.
'use strict';
const assert = require('assert');
const { FoxgloveClient } = require('@foxglove/ws-protocol');
const published = require('@foxglove/schemas/jsonschema');
const WebSocket = require('ws');
const { spawn, spawnSync } = require('child_process');
const fs = require('fs');
const protobuf = require('protobufjs');
require('protobufjs/ext/descriptor');
const { generateProto, foxgloveMessageSchemas, foxgloveEnumSchemas } = require('@foxglove/schemas/internal');
const { start, prog, shm, shmAsync, sleep, waitVersion, learnerOfStat, ok, plan, check } = require('./demo');
const { validate, sameFields } = require('./schema');

// Foxglove's published JSON Schema for a schema name "foxglove.X", or undefined.
const publishedOf = (name) => (name.startsWith('foxglove.') ? published[name.slice(9)] : undefined);

const FREE = 65534;
const png = require('./png');

// A protobuf channel's message type, from the FileDescriptorSet it advertises (base64),
// as Foxglove builds it (protobufjs' descriptor extension).
function protobufType(c) {
  const set = protobuf.descriptor.FileDescriptorSet.decode(Buffer.from(c.schema, 'base64'));
  return { set, type: protobuf.Root.fromDescriptor(set).lookupType(c.schemaName) };
}
// A decoded PointCloud in the shape of Foxglove's JSON schema (google.protobuf.Timestamp
// is Foxglove's {sec, nsec}; bytes in base64), and its packed data.
function cloudObject(type, data) {
  const u8 = new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
  const o = type.toObject(type.decode(u8), { longs: Number, enums: Number, bytes: String, defaults: true });
  o.timestamp = { sec: o.timestamp.seconds, nsec: o.timestamp.nanos };
  return { o, bytes: Buffer.from(o.data, 'base64') };
}

// The descriptor's files against the .proto text @foxglove/schemas generates: the
// same file names, package, imports, message, and fields (label, type, name, number)
// and enum values. Returns a list of differences.
function descriptorVsPublished(set) {
  const errs = [];
  const scalar = { 1: 'double', 3: 'int64', 5: 'int32', 7: 'fixed32', 9: 'string', 12: 'bytes', 13: 'uint32',
    15: 'sfixed32', 8: 'bool' };
  const timestampProto = 'syntax = "proto3";\npackage google.protobuf;\nmessage Timestamp {\n  int64 seconds = 1;\n' +
    '  int32 nanos = 2;\n}\n';
  for (const f of set.file) {
    const name = f.name.replace(/\.proto$/, '');
    let text;
    if (name === 'google/protobuf/timestamp') text = timestampProto; // the well-known type
    else {
      const schema = foxgloveMessageSchemas[name.replace('foxglove/', '')];
      if (!schema) { errs.push(`${f.name}: not a schema of @foxglove/schemas`); continue; }
      text = generateProto(schema, Object.values(foxgloveEnumSchemas).filter((e) => e.parentSchemaName === schema.name));
    }
    const lines = text.split('\n').map((l) => l.trim()).filter((l) => l && !l.startsWith('//'));
    const want = {
      package: lines.find((l) => l.startsWith('package ')).slice(8, -1),
      imports: lines.filter((l) => l.startsWith('import ')).map((l) => l.slice(8, -2)).sort(),
      message: /^message (\w+)/.exec(lines.find((l) => l.startsWith('message ')))[1],
      fields: lines.filter((l) => /^(repeated )?[\w.]+ \w+ = \d+;$/.test(l)).map((l) => l.replace(/[\w]+\./g, '')),
      values: lines.filter((l) => /^[A-Z0-9_]+ = \d+;$/.test(l)),
    };
    const m = f.messageType[0];
    const got = {
      package: f.package, imports: [...f.dependency].sort(), message: m.name,
      fields: m.field.map((d) => `${d.label === 3 ? 'repeated ' : ''}${d.typeName ? d.typeName.split('.').at(-1) :
        scalar[d.type]} ${d.name} = ${d.number};`),
      values: (m.enumType || []).flatMap((e) => e.value.map((v) => `${v.name} = ${v.number};`)),
    };
    if (f.syntax !== 'proto3') errs.push(`${f.name}: syntax ${f.syntax}`);
    if (f.messageType.length !== 1) errs.push(`${f.name}: one message per file`);
    const a = JSON.stringify(got), b = JSON.stringify(want);
    if (a !== b) errs.push(`${f.name}: ${a} against @foxglove/schemas' ${b}`);
  }
  return errs;
}

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
    let grid = null, voxelVersion = 0, voxelT = 0n, sceneT = 0n, fullSeen = 0, deltaSeen = 0, bad = [], nextPiece = 0;
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
      const c = bySub[subscriptionId];
      let msg;
      if (c.encoding === 'protobuf') {
        msg = cloudObject(protobufType(c).type, data).o;
      } else {
        msg = JSON.parse(td.decode(data));
        const errs = validate(JSON.parse(c.schema), msg);
        if (errs.length) bad.push(`${c.topic}: ${errs.slice(0, 3).join('; ')}`);
      }
      const pub = publishedOf(c.schemaName);
      if (pub) {
        const perrs = validate(pub, msg, '$', [], true);
        if (perrs.length) bad.push(`${c.topic} against @foxglove/schemas: ${perrs.slice(0, 3).join('; ')}`);
        checkedPublished[c.schemaName] = (checkedPublished[c.schemaName] || 0) + 1;
      }
      (got[c.topic] = got[c.topic] || []).push(msg);
      if (c.topic === '/map/voxels') {
        // a version's pieces in a row, the first of a whole map full
        assert.deepStrictEqual([msg.piece, msg.full], [nextPiece, msg.full && !msg.piece], `v${msg.version} pieces`);
        nextPiece = msg.piece + 1 < msg.pieces ? msg.piece + 1 : 0;
        if (msg.full) { voxels.clear(); fullSeen++; } else if (!msg.piece) deltaSeen++;
        grid = msg;
        for (let n = 0; n < msg.voxels.length; n += 3) {
          if (msg.voxels[n + 1] >= FREE) voxels.delete(msg.voxels[n]);
          else voxels.set(msg.voxels[n], [msg.voxels[n + 1], msg.voxels[n + 2]]);
        }
        if (!nextPiece) { // the version's last piece
          assert.strictEqual(voxels.size, msg.occupied, `v${msg.version}: client holds as many voxels as the map`);
          voxelVersion = msg.version;
          voxelT = timestamp;
        }
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

    await until(() => serverInfo && Object.keys(chans).length === 11, 10000, 'serverInfo and advertise');
    assert.deepStrictEqual(Object.keys(chans).sort(), ['/camera/calibration', '/camera/depth', '/camera/image',
      '/camera/labels', '/log', '/map', '/map/grid', '/map/points', '/map/voxels', '/tf', '/vlff/status']);
    const pbChannels = { '/map/points': 'foxglove.PointCloud', '/map/grid': 'foxglove.Grid',
      '/camera/depth': 'foxglove.RawImage' };
    for (const c of Object.values(chans)) {
      if (pbChannels[c.topic]) continue;
      assert.strictEqual(c.encoding, 'json');
      assert.strictEqual(c.schemaEncoding, 'jsonschema');
      assert.strictEqual(JSON.parse(c.schema).title, c.schemaName);
    }
    for (const [t, name] of Object.entries(pbChannels)) {
      const pc = chans[t];
      assert.ok(pc.encoding === 'protobuf' && pc.schemaEncoding === 'protobuf' && pc.schemaName === name,
        JSON.stringify(pc));
      assert.deepStrictEqual(descriptorVsPublished(protobufType(pc).set), [], t);
    }
    assert.strictEqual(chans['/map'].schemaName, 'foxglove.SceneUpdate');
    assert.strictEqual(chans['/camera/image'].schemaName, 'foxglove.CompressedImage');
    assert.strictEqual(chans['/camera/labels'].schemaName, 'foxglove.CompressedImage');
    assert.strictEqual(chans['/camera/calibration'].schemaName, 'foxglove.CameraCalibration');
    assert.strictEqual(chans['/tf'].schemaName, 'foxglove.FrameTransform');
    assert.deepStrictEqual(serverInfo.capabilities, [], 'no clientPublish without a token');
    assert.strictEqual(chans['/log'].schemaName, 'foxglove.Log');
    ok('serverInfo and eleven channels advertised: JSON schemas, and /map/points, /map/grid and /camera/depth in ' +
      'protobuf whose FileDescriptorSets have the files, imports, messages, fields and numbers of the .proto that ' +
      '@foxglove/schemas generates');
    const foxgloveChannels = Object.values(chans).filter((c) => c.schemaName.startsWith('foxglove.') &&
      c.encoding === 'json');
    for (const c of foxgloveChannels) {
      const pub = publishedOf(c.schemaName);
      assert.ok(pub && pub.title === c.schemaName, `${c.schemaName} is a schema of @foxglove/schemas`);
      assert.deepStrictEqual(sameFields(JSON.parse(c.schema), pub), [],
        `${c.topic}: the advertised ${c.schemaName} against @foxglove/schemas`);
    }
    ok(`${foxgloveChannels.map((c) => `${c.topic} (${c.schemaName})`).join(', ')}: advertised schemas have the ` +
      'field names, types and required fields of @foxglove/schemas');

    await until(() => fullSeen >= 1 && deltaSeen >= 2 && ['/camera/image', '/camera/labels', '/camera/calibration',
      '/tf', '/vlff/status', '/log', '/map/points', '/map/grid', '/camera/depth']
      .every((t) => got[t]), 120000, 'a whole map, two deltas and every channel');
    assert.deepStrictEqual(bad, [], 'every message matches its advertised schema and the published one');
    for (const n of ['foxglove.SceneUpdate', 'foxglove.CompressedImage', 'foxglove.CameraCalibration',
      'foxglove.FrameTransform', 'foxglove.Log', 'foxglove.PointCloud', 'foxglove.Grid', 'foxglove.RawImage'])
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
    // (a scene comes in pieces of whole bricks: the version's last piece holds as many
    // cubes as there are voxels)
    const sceneCubes = () => [...scene.values()].reduce((n, e) => n + e.cubes.length, 0);
    // Within 10 s of the pause, or after letting the learner publish once more: a
    // pause that caught the node mid-publish left the two channels a version apart
    // for good in one fresh-clone run.
    for (let attempt = 0; ; attempt++) {
      try {
        await until(() => sceneT === voxelT && sceneCubes() === voxels.size, 10000, 'scene and voxels of one version');
        break;
      } catch (e) {
        if (attempt === 2) throw e;
        demo.resume();
        await sleep(2000);
        demo.pause();
        await sleep(1500);
      }
    }
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

    // A second viewer with --max-queue-mb 1, a client of /map/voxels and /map/points:
    // the whole map comes in point cloud pieces of at most 1/8 of the queue limit,
    // the client is not dropped, and after each version the points are the voxels.
    // Its segments and frames come from a config: the map's frame "odom", the
    // camera's "cam_optical".
    const PIECE = (1 << 20) / 8;
    const cfg2 = `${demo.dir}/view2.yaml`;
    fs.writeFileSync(cfg2, `shm:\n  map: "${demo.names.map}"\n  ring: "${demo.names.frames}"\n  prompts: ` +
      `"${demo.names.prompts}"\ndds:\n  frame_id: "odom"\n  camera_frame_id: "cam_optical"\n`);
    fs.writeFileSync(`${demo.dir}/bad.yaml`, 'dds:\n  frame_id: "odom"\n  camera_frame_id: "odom"\n');
    const refused = spawnSync(prog.view, ['--port', '0', '--config', `${demo.dir}/bad.yaml`], { encoding: 'utf8',
      timeout: 20000 });
    assert.ok(refused.status === 1 && /bad\.yaml:3:\d+: key 'dds\.camera_frame_id': expected a frame distinct/
      .test(refused.stderr), `${refused.status} ${refused.stderr}`);
    let text = '', log2 = '';
    const v2 = spawn(prog.view, ['--port', '0', '--config', cfg2, '--max-queue-mb', '1'],
      { stdio: ['ignore', 'pipe', 'pipe'] });
    process.on('exit', () => { if (v2.exitCode === null) v2.kill('SIGKILL'); });
    v2.stderr.on('data', (d) => { log2 += d; });
    const port2 = await new Promise((resolve, reject) => {
      v2.stdout.on('data', (d) => {
        text += d;
        const m = /serving http:\/\/127\.0\.0\.1:(\d+)\//.exec(text);
        if (m) resolve(Number(m[1]));
      });
      v2.on('exit', (code) => reject(new Error(`the second vlff-view exited ${code}: ${log2}`)));
    });
    const c2 = new FoxgloveClient({ ws: new WebSocket(`ws://127.0.0.1:${port2}/`,
      [FoxgloveClient.SUPPORTED_SUBPROTOCOL]) });
    const ev = [], subs2 = {};
    let ptype = null, closed = null;
    c2.on('advertise', (cs) => {
      for (const c of cs) {
        if (c.topic === '/map/points') ptype = protobufType(c).type;
        if (['/map/voxels', '/map/points', '/tf', '/camera/calibration', '/camera/image'].includes(c.topic)) {
          subs2[c2.subscribe(c.id)] = c;
        }
      }
    });
    c2.on('close', (e) => { closed = e; });
    c2.on('message', ({ subscriptionId, data }) => {
      ev.push({ topic: subs2[subscriptionId].topic, data: Buffer.from(data.buffer, data.byteOffset, data.byteLength) });
    });
    // four versions: their first /map/voxels pieces
    const versions2 = () => ev.filter((e) => e.topic === '/map/voxels' && /"piece":0,/.test(td.decode(e.data.subarray(0, 120))));
    for (const t0 = Date.now(); versions2().length < 4;) {
      if (Date.now() - t0 > 60000 || closed) throw new Error(`no four map versions from the second viewer: ${log2}`);
      await sleep(100);
    }
    c2.close();
    v2.kill('SIGINT');
    const cloud = new Map(), vox = new Map(), perr = [];
    let g = null, compared = 0, maxLen = 0, vmax = 0, first = 0, points = 0, started = false, afterFirst = false;
    const frames = new Set();
    for (const e of ev) {
      if (['/tf', '/camera/calibration', '/camera/image'].includes(e.topic)) {
        const m = JSON.parse(td.decode(e.data));
        frames.add(e.topic === '/tf' ? `${e.topic} ${m.parent_frame_id} -> ${m.child_frame_id}` : `${e.topic} ${m.frame_id}`);
        continue;
      }
      if (e.topic === '/map/voxels') {
        const v = JSON.parse(td.decode(e.data));
        vmax = Math.max(vmax, e.data.length);
        // at a version's first piece every piece of the versions before it has come: the points are the voxels
        if (started && !v.piece) {
          afterFirst = true;
          const same = cloud.size === vox.size && [...vox].every(([k, x]) => cloud.get(k) === x);
          if (!same) perr.push(`before version ${v.version}: ${cloud.size} points, ${vox.size} voxels`);
          compared++;
        }
        g = v;
        if (g.full) vox.clear();
        for (let n = 0; n < g.voxels.length; n += 3) {
          if (g.voxels[n + 1] >= FREE) vox.delete(g.voxels[n]);
          else vox.set(g.voxels[n], `${g.voxels[n + 1]},${g.voxels[n + 2]}`);
        }
        continue;
      }
      started = true;
      if (!afterFirst) first++;
      maxLen = Math.max(maxLen, e.data.length);
      const { o, bytes } = cloudObject(ptype, e.data);
      perr.push(...validate(published.PointCloud, o, '$', [], true).slice(0, 2));
      frames.add(`${e.topic} ${o.frame_id}`);
      if (o.point_stride !== 20 || bytes.length % 20) perr.push(`${o.frame_id} ${o.point_stride}`);
      const at = Object.fromEntries(o.fields.map((f) => [f.name, [f.offset, f.type]]));
      assert.deepStrictEqual(at, { x: [0, 7], y: [4, 7], z: [8, 7], red: [12, 1], green: [13, 1], blue: [14, 1],
        alpha: [15, 1], label: [16, 3], confidence: [18, 1] }, 'the packed fields (FLOAT32 7, UINT8 1, UINT16 3)');
      const [nx, ny] = g.dims;
      for (let p = 0; p < bytes.length; p += 20, points++) {
        const ijk = [0, 1, 2].map((a) => Math.round((bytes.readFloatLE(p + 4 * a) - g.origin[a]) / g.voxel_size - 0.5));
        const idx = ijk[0] + nx * (ijk[1] + ny * ijk[2]), label = bytes.readUInt16LE(p + 16);
        const rgba = `#${bytes.subarray(p + 12, p + 15).toString('hex')}`, alpha = bytes[p + 15];
        if (label >= FREE) {
          cloud.delete(idx);
          if (alpha !== 0) perr.push(`a freed voxel ${idx} with alpha ${alpha}`);
        } else {
          cloud.set(idx, `${label},${bytes[p + 18]}`);
          if (alpha !== 255 || (label < g.colors.length && rgba !== g.colors[label])) {
            perr.push(`voxel ${idx} label ${label}: ${rgba} alpha ${alpha}, prompt colour ${g.colors[label]}`);
          }
        }
      }
    }
    assert.deepStrictEqual(perr.slice(0, 4), []);
    assert.deepStrictEqual([...frames].sort(), ['/camera/calibration cam_optical', '/camera/image cam_optical',
      '/map/points odom', '/tf odom -> cam_optical'], 'the frames of the config');
    assert.strictEqual(closed, null, 'the client of the second viewer was not dropped');
    assert.ok(compared >= 2, `${compared} versions compared`);
    assert.ok(maxLen <= PIECE, `a point cloud message of ${maxLen} bytes, above ${PIECE}`);
    assert.ok(vmax <= PIECE, `a /map/voxels message of ${vmax} bytes, above ${PIECE}`);
    const whole = first > 0 ? vox.size : 0;
    ok(`/map/points decoded by protobufjs from its descriptor, valid against @foxglove/schemas' PointCloud: the ` +
      `whole map in ${first} piece(s) of at most ${maxLen} bytes (limit ${PIECE} with --max-queue-mb 1; /map/voxels ` +
      `pieces of at most ${vmax} bytes), ${points} ` +
      `points in all, equal to /map/voxels after each of ${compared} versions (${whole} voxels), in the prompts' ` +
      'colours, freed voxels transparent');
    // A third with --max-queue-mb 0.25, below the whole map's point cloud: the pieces
    // (32 KiB) go out one after another and only the waiting one counts, so a client
    // of /map/points and /vlff/status that reads gets the whole map and is not dropped.
    let text3 = '', log3 = '';
    const v3 = spawn(prog.view, ['--port', '0', '--config', cfg2, '--max-queue-mb', '0.25'],
      { stdio: ['ignore', 'pipe', 'pipe'] });
    process.on('exit', () => { if (v3.exitCode === null) v3.kill('SIGKILL'); });
    v3.stderr.on('data', (d) => { log3 += d; });
    const port3 = await new Promise((resolve, reject) => {
      v3.stdout.on('data', (d) => {
        text3 += d;
        const m = /serving http:\/\/127\.0\.0\.1:(\d+)\//.exec(text3);
        if (m) resolve(Number(m[1]));
      });
      v3.on('exit', (code) => reject(new Error(`the third vlff-view exited ${code}: ${log3}`)));
    });
    const c3 = new FoxgloveClient({ ws: new WebSocket(`ws://127.0.0.1:${port3}/`,
      [FoxgloveClient.SUPPORTED_SUBPROTOCOL]) });
    const ev3 = [], subs3 = {}, occupied = new Set();
    let closed3 = null;
    c3.on('advertise', (cs) => {
      for (const c of cs) if (c.topic === '/map/points' || c.topic === '/vlff/status') subs3[c3.subscribe(c.id)] = c;
    });
    c3.on('close', (e) => { closed3 = e; });
    c3.on('message', ({ subscriptionId, timestamp, data }) => {
      const t = subs3[subscriptionId].topic;
      if (t === '/vlff/status') occupied.add(JSON.parse(td.decode(data)).map.occupied);
      else ev3.push({ timestamp, len: data.byteLength, points: cloudObject(ptype, data).bytes.length / 20 });
    });
    await sleep(4000);
    const closedBy = closed3 && `${closed3.code} ${closed3.reason}`;
    c3.close();
    v3.kill('SIGINT');
    assert.strictEqual(closedBy, null, 'the client of the third viewer was not dropped');
    const firstT = ev3.length && ev3[0].timestamp, group = ev3.filter((e) => e.timestamp === firstT);
    const wholePoints = group.reduce((a, e) => a + e.points, 0), max3 = Math.max(...ev3.map((e) => e.len));
    assert.ok(wholePoints * 20 > (1 << 20) / 4, `the whole map's ${wholePoints} points fit the queue limit anyway`);
    assert.ok(occupied.has(wholePoints), `${wholePoints} points in the whole map, occupied ${[...occupied]}`);
    assert.ok(max3 <= (1 << 20) / 32, `a piece of ${max3} bytes`);
    ok(`--max-queue-mb 0.25: the whole map (${wholePoints} points, ${wholePoints * 20} bytes) reaches a client that ` +
      `reads in ${group.length} pieces of at most ${max3} bytes, as many points as the status counts occupied`);
    ok('--config: the second viewer reads the segments and frame ids of a config (points in "odom", the pose ' +
      '"odom" -> "cam_optical", image and calibration in "cam_optical"); a config whose frames are the same is ' +
      'refused with the loader\'s file:line message');
  });
  plan();
}
main();
