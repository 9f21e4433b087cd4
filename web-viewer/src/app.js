// The viewer page: the live session list (for operators), token entry, and up to four
// sessions side by side. Open with ?session=ID&token=OBSERVE_TOKEN to go straight to a
// session; the token leaves the address bar as soon as the page has read it.
//
// Nothing the server sends is ever parsed as HTML: every name, label and id goes into
// the page as text (textContent), and the server's Content-Security-Policy forbids any
// script but the viewer's own.

import { loadProtocol } from './protocol.js';
import { SessionPanel } from './panel.js';

const MAX_PANELS = 4;
const panels = new Map(); // session id -> SessionPanel
const tokens = JSON.parse(sessionStorage.getItem('cutsim-tokens') || '{}');

// Test hooks (read-only): the browser tests read state from here.
window.cutsimViewer = { panels, errors: [] };
window.addEventListener('error', (e) => window.cutsimViewer.errors.push(String(e.message)));
window.addEventListener('unhandledrejection', (e) => window.cutsimViewer.errors.push(String(e.reason)));

function rememberToken(id, token) {
  tokens[id] = token;
  sessionStorage.setItem('cutsim-tokens', JSON.stringify(tokens));
}

function operatorToken() {
  return sessionStorage.getItem('cutsim-operator') || '';
}

/** Headers for an operator's request (none when not signed in). */
export function operatorHeaders() {
  const token = operatorToken();
  return token ? { 'cutsim-token': token } : {};
}

function formatAge(seconds) {
  if (seconds < 90) return `${Math.round(seconds)} s`;
  if (seconds < 5400) return `${Math.round(seconds / 60)} min`;
  return `${(seconds / 3600).toFixed(1)} h`;
}

/** A table row of text cells; `first` (an element) goes in the first cell. */
function row(first, ...texts) {
  const tr = document.createElement('tr');
  const lead = document.createElement('td');
  lead.append(first);
  tr.append(lead);
  for (const text of texts) {
    const td = document.createElement('td');
    td.textContent = String(text);
    tr.append(td);
  }
  return tr;
}

function button(className, text, onclick) {
  const b = document.createElement('button');
  b.className = className;
  b.textContent = text;
  b.onclick = onclick;
  return b;
}

async function refreshSessions() {
  const list = document.querySelector('#sessions tbody');
  const status = document.querySelector('#server-status');
  try {
    // Only operators may list sessions: ask first rather than provoke a refusal.
    const who = await fetch('/api/whoami', { cache: 'no-store', headers: operatorHeaders() });
    if (!who.ok) throw new Error(`HTTP ${who.status}`);
    if (!(await who.json()).operator) {
      status.textContent = 'sign in with an operator token to list the sessions (or open one with its token)';
      status.dataset.state = 'locked';
      list.replaceChildren();
      return;
    }
    const response = await fetch('/api/sessions', { cache: 'no-store', headers: operatorHeaders() });
    if (!response.ok) throw new Error(`HTTP ${response.status}`);
    const sessions = await response.json();
    status.textContent = `${sessions.length} session${sessions.length === 1 ? '' : 's'}`;
    status.dataset.state = 'up';
    list.replaceChildren(
      ...sessions.map((s) => {
        const tr = row(button('open', s.id, () => openWhenReady(s.id)), s.label, s.scene, formatAge(s.age_s), `${Math.round(s.achieved_rate_hz)} Hz`, s.status, s.viewers);
        tr.dataset.session = s.id;
        if (panels.has(s.id)) tr.classList.add('open');
        return tr;
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
  // An operator watches any session with the operator token.
  token = token || operatorToken() || askToken(id);
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

// ───── recordings: listing and replaying need an operator ─────

async function listRecordings() {
  const body = document.querySelector('#recordings tbody');
  const note = document.querySelector('#recordings-status');
  const response = await fetch('/api/recordings', { headers: operatorHeaders(), cache: 'no-store' });
  if (!response.ok) {
    note.textContent = `cannot list recordings: ${await response.text()}`;
    return;
  }
  const list = await response.json();
  note.textContent = `${list.length} recording${list.length === 1 ? '' : 's'}`;
  body.replaceChildren(
    ...list.map((r) => {
      const when = new Date(r.modified_unix_s * 1000).toLocaleString();
      const tr = row(button('replay', r.session, () => replay(r.session)), r.scene, when, r.live ? 'live' : r.ended ? 'ended' : 'cut short');
      tr.dataset.recording = r.session;
      return tr;
    }),
  );
}

async function replay(recorded) {
  const response = await fetch(`/api/recordings/${encodeURIComponent(recorded)}/replay`, { method: 'POST', headers: operatorHeaders() });
  if (!response.ok) {
    document.querySelector('#recordings-status').textContent = `cannot replay ${recorded}: ${await response.text()}`;
    return null;
  }
  const created = await response.json();
  rememberToken(created.session_id, created.observe_token);
  return openWhenReady(created.session_id, created.observe_token, created.control_token);
}

// The schema loads in the background; whatever draws a session waits for it.
let protocolReady = null;

/** Opens a session once the schema has loaded (a panel decodes frames with it); a
 * schema that failed to load is reported by `main`, so here it only stops the panel. */
async function openWhenReady(id, token, controlToken) {
  try {
    await protocolReady;
  } catch {
    return null;
  }
  return open(id, token, controlToken);
}

async function main() {
  // Everything a user can touch is wired before the first await: the page's 'load'
  // event does not wait for the schema's fetch, and a form submitted before its handler
  // exists would reload the page (dropping the session in the address), while a token
  // typed before this line ran would be overwritten by the stored one.
  protocolReady = loadProtocol();
  const operatorInput = document.querySelector('#operator-token');
  if (!operatorInput.value) operatorInput.value = operatorToken();
  document.querySelector('#operator-form').onsubmit = (e) => {
    e.preventDefault();
    sessionStorage.setItem('cutsim-operator', operatorInput.value.trim());
    refreshSessions();
  };
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
      openWhenReady(id, token);
    }
  };
  const params = new URLSearchParams(location.search);
  const id = params.get('session');
  const token = params.get('token');
  if (id && token) rememberToken(id, token);
  if (token) {
    // The token leaves the address bar (and so the history, bookmarks and screen shares)
    // once read; the session stays in the address so a reload reopens it.
    params.delete('token');
    const rest = params.toString();
    history.replaceState(null, '', `${location.pathname}${rest ? `?${rest}` : ''}${location.hash}`);
  }
  await protocolReady;
  await refreshSessions();
  if (id) open(id);
  setInterval(refreshSessions, 2000);
}

main().catch((e) => {
  window.cutsimViewer.errors.push(String(e));
  document.querySelector('#server-status').textContent = `cannot start the viewer: ${e.message}`;
});
