// The viewer page: the live session list, token entry, and up to four sessions side by
// side. Open with ?session=ID&token=OBSERVE_TOKEN to go straight to a session.

import { loadProtocol } from './protocol.js';
import { SessionPanel } from './panel.js';

const MAX_PANELS = 4;
const panels = new Map(); // session id -> SessionPanel
const tokens = JSON.parse(sessionStorage.getItem('cutsim-tokens') || '{}');

// Test hooks (read-only): the browser tests read state from here.
window.cutsimViewer = { panels, errors: [] };
window.addEventListener('error', (e) => window.cutsimViewer.errors.push(String(e.message)));

function rememberToken(id, token) {
  tokens[id] = token;
  sessionStorage.setItem('cutsim-tokens', JSON.stringify(tokens));
}

function formatAge(seconds) {
  if (seconds < 90) return `${Math.round(seconds)} s`;
  if (seconds < 5400) return `${Math.round(seconds / 60)} min`;
  return `${(seconds / 3600).toFixed(1)} h`;
}

async function refreshSessions() {
  const list = document.querySelector('#sessions tbody');
  const status = document.querySelector('#server-status');
  try {
    const response = await fetch('/api/sessions', { cache: 'no-store' });
    if (!response.ok) throw new Error(`HTTP ${response.status}`);
    const sessions = await response.json();
    status.textContent = `${sessions.length} session${sessions.length === 1 ? '' : 's'}`;
    status.dataset.state = 'up';
    list.replaceChildren(
      ...sessions.map((s) => {
        const row = document.createElement('tr');
        row.dataset.session = s.id;
        row.innerHTML = `<td><button class="open">${s.id}</button></td><td></td><td>${s.scene}</td><td>${formatAge(s.age_s)}</td><td>${Math.round(s.achieved_rate_hz)} Hz</td><td>${s.status}</td><td>${s.viewers}</td>`;
        row.children[1].textContent = s.label;
        row.querySelector('button.open').onclick = () => open(s.id);
        if (panels.has(s.id)) row.classList.add('open');
        return row;
      }),
    );
  } catch (e) {
    status.textContent = `server unreachable (${e.message}); retrying…`;
    status.dataset.state = 'down';
  }
}

function askToken(id) {
  const token = prompt(`Observe token for session ${id}`);
  if (token) rememberToken(id, token.trim());
  return token?.trim();
}

function open(id, token = tokens[id], controlToken = undefined) {
  if (panels.has(id)) return panels.get(id);
  token = token || askToken(id);
  if (!token) return null;
  if (panels.size >= MAX_PANELS) {
    // Make room: the oldest panel gives way, so switching sessions stays quick.
    const [oldest] = panels.values();
    oldest.dispose();
    panels.delete(oldest.id);
  }
  const panel = new SessionPanel(document.querySelector('#panels'), {
    id,
    token,
    controlToken,
    onClose: (p) => {
      panels.delete(p.id);
      refreshSessions();
    },
    onGone: () => refreshSessions(),
  });
  panels.set(id, panel);
  document.body.dataset.panels = String(panels.size);
  refreshSessions();
  return panel;
}

// ───── recordings: listing and replaying need the server's admin token ─────

async function listRecordings() {
  const admin = document.querySelector('#admin-token').value.trim();
  sessionStorage.setItem('cutsim-admin', admin);
  const body = document.querySelector('#recordings tbody');
  const note = document.querySelector('#recordings-status');
  const response = await fetch('/api/recordings', { headers: { 'cutsim-token': admin }, cache: 'no-store' });
  if (!response.ok) {
    note.textContent = `cannot list recordings: ${await response.text()}`;
    return;
  }
  const list = await response.json();
  note.textContent = `${list.length} recording${list.length === 1 ? '' : 's'}`;
  body.replaceChildren(
    ...list.map((r) => {
      const row = document.createElement('tr');
      row.dataset.recording = r.session;
      const when = new Date(r.modified_unix_s * 1000).toLocaleString();
      row.innerHTML = `<td><button class="replay">${r.session}</button></td><td>${r.scene}</td><td>${when}</td><td>${r.live ? 'live' : r.ended ? 'ended' : 'cut short'}</td>`;
      row.querySelector('button.replay').onclick = () => replay(r.session);
      return row;
    }),
  );
}

async function replay(recorded) {
  const admin = document.querySelector('#admin-token').value.trim();
  const response = await fetch(`/api/recordings/${encodeURIComponent(recorded)}/replay`, { method: 'POST', headers: { 'cutsim-token': admin } });
  if (!response.ok) {
    document.querySelector('#recordings-status').textContent = `cannot replay ${recorded}: ${await response.text()}`;
    return null;
  }
  const created = await response.json();
  rememberToken(created.session_id, created.observe_token);
  return open(created.session_id, created.observe_token, created.control_token);
}

async function main() {
  await loadProtocol();
  document.querySelector('#admin-token').value = sessionStorage.getItem('cutsim-admin') || '';
  document.querySelector('#recordings-form').onsubmit = (e) => {
    e.preventDefault();
    listRecordings();
  };
  document.querySelector('#token-form').onsubmit = (e) => {
    e.preventDefault();
    const id = document.querySelector('#token-session').value.trim();
    const token = document.querySelector('#token-value').value.trim();
    if (id && token) {
      rememberToken(id, token);
      open(id, token);
    }
  };
  const params = new URLSearchParams(location.search);
  const id = params.get('session');
  const token = params.get('token');
  if (id && token) rememberToken(id, token);
  await refreshSessions();
  if (id) open(id);
  setInterval(refreshSessions, 2000);
}

main().catch((e) => {
  window.cutsimViewer.errors.push(String(e));
  document.querySelector('#server-status').textContent = `cannot start the viewer: ${e.message}`;
});
