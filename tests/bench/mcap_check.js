// Reads an MCAP recording with @mcap/core (CRCs checked: chunks, summary; the data
// section's with @foxglove/crc) and prints one JSON line: ok (every message read,
// as many as the statistics count, each a JSON text or, on a protobuf channel, a
// message protobufjs decodes with the channel's schema), messages, channels, chunks,
// bytes, span_s (first to last log time). Usage: node mcap_check.js FILE
'use strict';
const fs = require('fs');
const { McapIndexedReader } = require('@mcap/core');
const { crc32 } = require('@foxglove/crc');
const zstd = require('@foxglove/wasm-zstd');
const protobuf = require('protobufjs');
require('protobufjs/ext/descriptor');

async function main() {
  await zstd.isLoaded;
  const bytes = fs.readFileSync(process.argv[2]);
  const out = { ok: 0, messages: 0, channels: 0, chunks: 0, bytes: bytes.length, span_s: 0, error: null };
  try {
    const r = await McapIndexedReader.Initialize({
      readable: { size: async () => BigInt(bytes.length), read: async (o, s) => bytes.subarray(Number(o), Number(o + s)) },
      decompressHandlers: { zstd: (b, size) => zstd.decompress(b, Number(size)) },
    });
    const td = new TextDecoder('utf-8', { fatal: true });
    let first = null, last = null;
    const types = new Map();
    const typeOf = (c) => {
      if (!types.has(c.id)) {
        const s = r.schemasById.get(c.schemaId);
        const set = protobuf.descriptor.FileDescriptorSet.decode(s.data);
        types.set(c.id, protobuf.Root.fromDescriptor(set).lookupType(s.name));
      }
      return types.get(c.id);
    };
    for await (const m of r.readMessages({ validateCrcs: true })) {
      const c = r.channelsById.get(m.channelId);
      if (c.messageEncoding === 'protobuf') typeOf(c).decode(m.data);
      else JSON.parse(td.decode(m.data));
      if (first === null) first = m.logTime;
      last = m.logTime;
      out.messages++;
    }
    out.channels = r.channelsById.size;
    out.chunks = r.chunkIndexes.length;
    out.span_s = first === null ? 0 : Number(last - first) / 1e9;
    if (r.dataSectionCrc && r.dataSectionCrc !== crc32(bytes.subarray(0, Number(r.dataEndOffset)))) {
      throw new Error('data section CRC does not match');
    }
    if (!r.statistics || r.statistics.messageCount !== BigInt(out.messages)) throw new Error('statistics miscount');
    out.ok = out.messages > 0 ? 1 : 0;
  } catch (e) {
    out.error = String(e.message || e);
  }
  console.log(JSON.stringify(out));
}
main();
