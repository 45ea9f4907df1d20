// Reads an MCAP file with Foxglove's own TypeScript reader (@mcap/core) and decodes every message as
// Foxglove would (JSON channels with JSON.parse, protobuf channels with protobufjs from the schema's
// FileDescriptorSet). Prints one JSON object: channels, schemas, messages per topic, decode failures, the
// log-time span and whether the file read whole.
//
//   node tests/mcap_check.js FILE whole   indexed reader, CRCs validated (a complete file)
//   node tests/mcap_check.js FILE stream  stream reader, CRCs validated, as far as the file goes (a cut one)
//
// NODE_PATH must hold @mcap/core and protobufjs (tests/provision.py installs them under .ci/cache).
"use strict";
const fs = require("fs");
const { McapIndexedReader, McapStreamReader } = require("@mcap/core");
const protobuf = require("protobufjs");
const descriptor = require("protobufjs/ext/descriptor");

const [file, mode] = process.argv.slice(2);
const out = { mode, channels: 0, schemas: [], messages: 0, perTopic: {}, decodeErrors: 0, firstError: null,
              logTimeMin: null, logTimeMax: null, complete: true, readError: null };
const decoders = new Map(); // schema id -> (bytes) => object

function decoderFor(schema) {
  if (schema.encoding === "protobuf") {
    const set = descriptor.FileDescriptorSet.decode(schema.data);
    const type = protobuf.Root.fromDescriptor(set).lookupType(schema.name);
    return (bytes) => type.toObject(type.decode(bytes));
  }
  if (schema.encoding === "jsonschema" || schema.encoding === "") {
    const text = new TextDecoder();
    return (bytes) => JSON.parse(text.decode(bytes));
  }
  throw new Error(`unknown schema encoding ${schema.encoding}`);
}

const schemas = new Map();
const channels = new Map();

function onSchema(s) {
  schemas.set(s.id, s);
}

function onChannel(c) {
  channels.set(c.id, c);
}

function onMessage(m) {
  const c = channels.get(m.channelId);
  out.messages += 1;
  out.perTopic[c.topic] = (out.perTopic[c.topic] || 0) + 1;
  const t = Number(m.logTime);
  out.logTimeMin = out.logTimeMin === null ? t : Math.min(out.logTimeMin, t);
  out.logTimeMax = out.logTimeMax === null ? t : Math.max(out.logTimeMax, t);
  try {
    let dec = decoders.get(c.schemaId);
    if (!dec) {
      dec = decoderFor(schemas.get(c.schemaId));
      decoders.set(c.schemaId, dec);
    }
    dec(m.data);
  } catch (e) {
    out.decodeErrors += 1;
    if (!out.firstError) out.firstError = `${c.topic}: ${e.message}`;
  }
}

async function whole() {
  const fd = fs.openSync(file, "r");
  const size = fs.fstatSync(fd).size;
  const readable = {
    size: async () => BigInt(size),
    read: async (offset, length) => {
      const buf = Buffer.alloc(Number(length));
      fs.readSync(fd, buf, 0, Number(length), Number(offset));
      return new Uint8Array(buf.buffer, buf.byteOffset, buf.byteLength);
    },
  };
  const reader = await McapIndexedReader.Initialize({ readable });
  for (const s of reader.schemasById.values()) onSchema(s);
  for (const c of reader.channelsById.values()) onChannel(c);
  for await (const m of reader.readMessages({ validateCrcs: true })) onMessage(m);
}

function stream() {
  const reader = new McapStreamReader({ validateCrcs: true });
  reader.append(new Uint8Array(fs.readFileSync(file)));
  for (;;) {
    let rec;
    try {
      rec = reader.nextRecord();
    } catch (e) {
      out.complete = false;
      out.readError = e.message;
      return;
    }
    if (rec === undefined) {
      out.complete = reader.done();
      return;
    }
    if (rec.type === "Schema") onSchema(rec);
    else if (rec.type === "Channel") onChannel(rec);
    else if (rec.type === "Message") onMessage(rec);
  }
}

(async () => {
  try {
    if (mode === "whole") await whole();
    else stream();
  } catch (e) {
    out.complete = false;
    out.readError = e.message;
  }
  out.channels = channels.size;
  out.schemas = [...new Set([...schemas.values()].map((s) => s.name))].sort();
  process.stdout.write(JSON.stringify(out) + "\n");
})();
