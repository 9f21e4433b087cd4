// The wire protocol: ViewerFrame / ViewerRequest from the server's own cutsim.proto,
// decoded by reflection over its encoded FileDescriptorSet (/cutsim.binpb) with
// @bufbuild/protobuf. Nothing is generated from text at run time (no eval), so the page
// runs under a Content-Security-Policy that forbids it.

import { create, createFileRegistry, fromBinary, toBinary } from '@bufbuild/protobuf';
import { FileDescriptorSetSchema } from '@bufbuild/protobuf/wkt';

let types = null;

/** Loads the schema once; returns the message types the viewer uses. */
export async function loadProtocol() {
  if (types) return types;
  const response = await fetch('/cutsim.binpb');
  if (!response.ok) throw new Error(`cannot load /cutsim.binpb: HTTP ${response.status}`);
  const registry = createFileRegistry(fromBinary(FileDescriptorSetSchema, new Uint8Array(await response.arrayBuffer())));
  types = {
    ViewerFrame: registry.getMessage('cutsim.v1.ViewerFrame'),
    ViewerRequest: registry.getMessage('cutsim.v1.ViewerRequest'),
  };
  return types;
}

/**
 * A message as a plain object with the .proto's field names: 64-bit integers as
 * numbers, enums by name, unset messages as null, and for a oneof its name holding the
 * set member's name (`frame.frame === 'snapshot'`, `frame.snapshot`).
 */
function plain(desc, message) {
  const out = {};
  for (const member of desc.members) {
    if (member.kind === 'oneof') {
      const chosen = message[member.localName];
      const field = member.fields.find((f) => f.localName === chosen.case);
      out[member.name] = field ? field.name : undefined;
      if (field) out[field.name] = value(field, chosen.value);
    } else {
      out[member.name] = value(member, message[member.localName]);
    }
  }
  return out;
}

function scalar(v) {
  return typeof v === 'bigint' ? Number(v) : v;
}

function value(field, v) {
  switch (field.fieldKind) {
    case 'scalar':
      return scalar(v);
    case 'enum':
      return field.enum.values.find((e) => e.number === v)?.name ?? v;
    case 'message':
      return v === undefined ? null : plain(field.message, v);
    case 'list':
      if (field.listKind === 'message') return v.map((m) => plain(field.message, m));
      if (field.listKind === 'enum') return v.map((n) => field.enum.values.find((e) => e.number === n)?.name ?? n);
      return v.length && typeof v[0] === 'bigint' ? v.map(Number) : v;
    case 'map':
      return Object.fromEntries(Object.entries(v).map(([k, m]) => [k, field.mapKind === 'message' ? plain(field.message, m) : scalar(m)]));
    default:
      return v;
  }
}

/** Decodes one binary frame into a plain object. */
export function decodeFrame(bytes) {
  return plain(types.ViewerFrame, fromBinary(types.ViewerFrame, new Uint8Array(bytes)));
}

/** Encodes a request given as `{resync: {}}` or `{set_rate_hz: 30}`. */
export function encodeRequest(request) {
  const [name, v] = Object.entries(request)[0];
  const field = types.ViewerRequest.fields.find((f) => f.name === name);
  if (!field) throw new Error(`no ViewerRequest field ${name}`);
  return toBinary(types.ViewerRequest, create(types.ViewerRequest, { request: { case: field.localName, value: v } }));
}
