// The wire protocol: ViewerFrame / ViewerRequest from the server's own cutsim.proto,
// parsed at run time by protobufjs (reflection, no generated or hand-written parser).

/* global protobuf */

let types = null;

/** Loads /cutsim.proto once; returns the message types the viewer uses. */
export async function loadProtocol() {
  if (types) return types;
  const response = await fetch('/cutsim.proto');
  if (!response.ok) throw new Error(`cannot load /cutsim.proto: HTTP ${response.status}`);
  const root = protobuf.parse(await response.text(), { keepCase: true }).root;
  types = {
    ViewerFrame: root.lookupType('cutsim.v1.ViewerFrame'),
    ViewerRequest: root.lookupType('cutsim.v1.ViewerRequest'),
  };
  return types;
}

/** Decodes one binary frame into a plain object (64-bit integers as numbers). */
export function decodeFrame(bytes) {
  const message = types.ViewerFrame.decode(new Uint8Array(bytes));
  return types.ViewerFrame.toObject(message, { longs: Number, enums: String, defaults: true, arrays: true, oneofs: true });
}

export function encodeRequest(request) {
  return types.ViewerRequest.encode(types.ViewerRequest.fromObject(request)).finish();
}
