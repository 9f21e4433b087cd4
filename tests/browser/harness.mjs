// Shared pieces of the browser tests: the real server binary on chosen free ports, a gRPC
// client from the same cutsim.proto, and headless Debian chromium.

import { spawn } from 'node:child_process';
import { once } from 'node:events';
import net from 'node:net';
import path from 'node:path';
import fs from 'node:fs';
import os from 'node:os';
import { fileURLToPath } from 'node:url';
import grpc from '@grpc/grpc-js';
import protoLoader from '@grpc/proto-loader';
import { chromium } from 'playwright-core';

export const repo = path.resolve(path.dirname(fileURLToPath(import.meta.url)), '../..');
export const serverBinary = process.env.CUTSIM_SERVER_BIN || path.join(repo, 'target/debug/cutsim-server');
export const artifacts = path.join(repo, 'artifacts');
/** The operator token every test server is started with ($CUTSIM_OPERATOR_TOKEN). */
export const OPERATOR = 'browser-test-operator-0123456789abcdef';

export async function freePort() {
  const server = net.createServer();
  server.listen(0, '127.0.0.1');
  await once(server, 'listening');
  const { port } = server.address();
  server.close();
  await once(server, 'close');
  return port;
}

/** Starts cutsim-server with no session on the given ports; resolves when it listens. */
export async function startServer({ grpcPort, httpPort, recordings, config }) {
  const extra = config ? ['--config', config] : [];
  const child = spawn(serverBinary, ['serve', '--no-session', '--grpc-addr', `127.0.0.1:${grpcPort}`, '--http-addr', `127.0.0.1:${httpPort}`, '--recordings-dir', recordings, ...extra], {
    env: { ...process.env, RUST_LOG: 'warn', CUTSIM_OPERATOR_TOKEN: OPERATOR },
    stdio: ['ignore', 'pipe', 'inherit'],
  });
  let out = '';
  child.stdout.on('data', (d) => {
    out += d;
  });
  const deadline = Date.now() + 60_000;
  while (!out.includes('http listening on')) {
    if (child.exitCode !== null) throw new Error(`cutsim-server exited (${child.exitCode}): ${out}`);
    if (Date.now() > deadline) throw new Error(`cutsim-server did not start: ${out}`);
    await new Promise((r) => setTimeout(r, 50));
  }
  return child;
}

export function tempDir(tag) {
  return fs.mkdtempSync(path.join(os.tmpdir(), `cutsim-${tag}-`));
}

const definition = protoLoader.loadSync(path.join(repo, 'proto/cutsim.proto'), { keepCase: true, longs: Number, enums: String, defaults: true, oneofs: true });
const cutsim = grpc.loadPackageDefinition(definition).cutsim.v1;

/** Promise-returning gRPC clients for one server. */
export function grpcClients(grpcPort) {
  const address = `127.0.0.1:${grpcPort}`;
  const credentials = grpc.credentials.createInsecure();
  const sessions = new cutsim.Sessions(address, credentials);
  const scripts = new cutsim.Scripts(address, credentials);
  const unary = (method, request, token) =>
    new Promise((resolve, reject) => {
      const metadata = new grpc.Metadata();
      if (token) metadata.set('cutsim-token', token);
      sessions[method](request, metadata, (err, response) => (err ? reject(err) : resolve(response)));
    });
  return {
    createSession: (scene, mode = 'SESSION_MODE_LOCKSTEP') => unary('CreateSession', { scene_name: scene, mode, label: 'browser test' }, OPERATOR),
    createInlineSession: (sceneJson, label, mode = 'SESSION_MODE_REALTIME') => unary('CreateSession', { scene_json: sceneJson, mode, label }, OPERATOR),
    snapshot: (id, token) => unary('GetSnapshot', { session_id: id }, token),
    runScript: (id, token, scriptJson) =>
      new Promise((resolve, reject) => {
        const metadata = new grpc.Metadata();
        metadata.set('cutsim-token', token);
        const call = scripts.RunScript({ session_id: id, script_json: scriptJson, progress_every_steps: 0 }, metadata);
        let report = null;
        call.on('data', (event) => {
          if (event.report) report = event.report;
        });
        call.on('error', reject);
        call.on('end', () => (report ? resolve(report) : reject(new Error('no report'))));
      }),
    close: () => {
      sessions.close();
      scripts.close();
    },
  };
}

/** Headless Debian chromium with the flags this closed network needs. */
export async function launchBrowser() {
  return chromium.launch({
    executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
    headless: true,
    args: ['--no-sandbox', '--disable-gpu', '--disable-background-networking', '--disable-component-update', '--disable-sync', '--no-first-run', '--disable-quic', '--use-angle=swiftshader', '--enable-unsafe-swiftshader'],
  });
}

export async function waitFor(what, predicate, timeoutMs = 15_000, everyMs = 100) {
  const deadline = Date.now() + timeoutMs;
  let last;
  while (Date.now() < deadline) {
    last = await predicate();
    if (last) return last;
    await new Promise((r) => setTimeout(r, everyMs));
  }
  throw new Error(`timed out after ${timeoutMs} ms waiting for ${what} (last: ${JSON.stringify(last)})`);
}
