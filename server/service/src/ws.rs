//! The WebSocket viewer protocol at `/ws/sessions/{id}`: binary protobuf `ViewerFrame`s.
//!
//! On connect: Hello, then a Snapshot. Then, as they happen, TopologyDeltas (never
//! dropped: a viewer that falls behind the hub's backlog gets a fresh Snapshot instead),
//! and at the viewer's rate Positions (only the vertices that moved since the last
//! frame sent to this viewer), ToolStates and, ten times less often, SessionStats. A slow
//! viewer only slows itself: the physics never waits for it. The connection logic is
//! generic over the sink and stream so tests can drive it without sockets.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use axum::extract::ws::{CloseFrame, Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Path, Query, State};
use axum::http::HeaderMap;
use axum::response::Response;
use cutsim_proto::v1 as pb;
use cutsim_sim::surface::SurfaceSnapshot;
use futures_util::{Sink, SinkExt, Stream, StreamExt};
use prost::Message as _;
use serde::Deserialize;
use tokio::sync::broadcast::error::RecvError;

use crate::auth::{Role, TOKEN_KEY};
use crate::convert;
use crate::error::ApiError;
use crate::http::AppState;
use crate::session::Session;
use crate::session::hub::{Frame, HubMessage};

/// A viewer that does not take a frame within this time is disconnected.
const SEND_TIMEOUT: Duration = Duration::from_secs(10);
/// Largest message a viewer may send, bytes.
const MAX_INCOMING_BYTES: usize = 64 * 1024;

#[derive(Deserialize)]
pub struct ViewerQuery {
    token: Option<String>,
    /// Positions frames per second (1 to 240).
    rate_hz: Option<f64>,
}

/// `GET /ws/sessions/{id}?token=…[&rate_hz=…]`: checks the page's origin (a browser's
/// upgrade from another site's page is refused), the session, the token (observe or
/// control, or an operator's; a missing or wrong one gets 401) and the viewer limit,
/// then upgrades.
pub async fn upgrade(
    Path(id): Path<String>,
    Query(query): Query<ViewerQuery>,
    headers: HeaderMap,
    caller: crate::http::HttpCaller,
    State(app): State<AppState>,
    ws: WebSocketUpgrade,
) -> Result<Response, ApiError> {
    check_origin(&headers, &app.registry.config.allowed_origins)?;
    let session = app.registry.get(&id)?;
    let token = query.token.as_deref().or_else(|| headers.get(TOKEN_KEY).and_then(|v| v.to_str().ok()));
    let role = match session.authorize(token, Role::Observe) {
        Ok(role) => role,
        Err(e) => {
            let by_query = crate::auth::Caller { token, ..caller.caller() };
            app.registry.operators.authenticate(&by_query).map_err(|_| e)?;
            Role::Observe
        }
    };
    if let Some(e) = session.failed_error() {
        return Err(e);
    }
    let limit = app.registry.config.limits.max_viewers_per_session;
    if session.viewers.load(Ordering::Relaxed) as usize >= limit {
        return Err(ApiError::exhausted("viewers", format!("session {id} already has its maximum of {limit} viewers")));
    }
    let rate = match query.rate_hz {
        Some(r) if (1.0..=240.0).contains(&r) => r,
        Some(r) => return Err(ApiError::InvalidArgument(format!("rate_hz must be within [1, 240] Hz, got {r}"))),
        None => app.registry.config.viewer_rate_hz,
    };
    let metrics = app.metrics.clone();
    let requests_per_second = app.registry.config.limits.viewer_requests_per_second;
    Ok(ws.max_message_size(MAX_INCOMING_BYTES).on_upgrade(move |socket: WebSocket| async move {
        let (sink, stream) = socket.split();
        let outcome = run_viewer(sink, stream, session.clone(), ViewerOptions { observer: role == Role::Observe, rate_hz: rate, requests_per_second }, &metrics).await;
        tracing::debug!(session = %session.id, ?outcome, "viewer left");
    }))
}

/// A browser sends the page's origin with every WebSocket upgrade: only the server's
/// own pages (the origin's host is the Host the request was sent to) and the configured
/// `allowed_origins` may open viewers. Clients that are not browsers send no Origin.
fn check_origin(headers: &HeaderMap, allowed: &[String]) -> Result<(), ApiError> {
    let Some(origin) = headers.get(axum::http::header::ORIGIN) else { return Ok(()) };
    let origin = origin.to_str().unwrap_or_default();
    let host = headers.get(axum::http::header::HOST).and_then(|h| h.to_str().ok()).unwrap_or_default();
    let origin_host = origin.split_once("://").map_or("", |(_, rest)| rest.trim_end_matches('/'));
    if (!host.is_empty() && origin_host.eq_ignore_ascii_case(host)) || allowed.iter().any(|a| a.trim_end_matches('/').eq_ignore_ascii_case(origin)) {
        return Ok(());
    }
    Err(ApiError::PermissionDenied(format!(
        "a page from {origin:?} may not open viewers here; only this server's own pages (and allowed_origins in its config) may"
    )))
}

/// Why a viewer connection ended.
#[derive(Debug, PartialEq)]
pub enum ViewerEnd {
    ClientClosed,
    SessionClosed,
    SendFailed,
    Protocol(String),
}

/// Counts the viewer in (and out, whatever happens).
struct ViewerGuard(Arc<Session>);

impl Drop for ViewerGuard {
    fn drop(&mut self) {
        self.0.viewers.fetch_sub(1, Ordering::Relaxed);
    }
}

/// What this viewer has been sent: the vertex positions it holds.
struct Mirror {
    version: u64,
    epoch_version: u64,
    /// Position last sent, by vertex id (None: not a vertex now).
    positions: Vec<Option<[f32; 3]>>,
    /// Sequence number of the last frame looked at.
    last_frame: u64,
}

impl Mirror {
    fn from_snapshot(s: &SurfaceSnapshot, epoch_version: u64) -> Self {
        let len = s.vertices.iter().map(|v| v.id as usize + 1).max().unwrap_or(0);
        let mut positions = vec![None; len];
        for v in &s.vertices {
            positions[v.id as usize] = Some(v.position_m);
        }
        Self { version: s.version, epoch_version, positions, last_frame: u64::MAX }
    }

    fn apply(&mut self, d: &cutsim_sim::surface::TopologyDelta) {
        for &id in &d.removed_vertices {
            if let Some(p) = self.positions.get_mut(id as usize) {
                *p = None;
            }
        }
        for v in &d.added_vertices {
            let i = v.id as usize;
            if i >= self.positions.len() {
                self.positions.resize(i + 1, None);
            }
            self.positions[i] = Some(v.position_m);
        }
        self.version = d.version;
        // A delta can arrive after the frame that already holds its vertices where they
        // have moved to since they were made (the physics thread publishes frames, the
        // hub encodes deltas apart): look at the newest frame again, or a session that
        // stops stepping would leave this viewer with their first positions.
        self.last_frame = u64::MAX;
    }

    /// The vertices whose position in `frame` differs from what was sent, as a
    /// Positions message (and records them as sent).
    fn moved(&mut self, frame: &Frame) -> Option<pb::Positions> {
        if frame.epoch_version != self.epoch_version {
            return None;
        }
        let mut ids = Vec::new();
        let mut coords = Vec::new();
        let mut previous = 0u32;
        for (id, sent) in self.positions.iter_mut().enumerate() {
            let (Some(sent), Some(now)) = (sent.as_mut(), frame.positions.get(id)) else { continue };
            if sent.map(f32::to_bits) != now.map(f32::to_bits) {
                *sent = *now;
                ids.push(id as u32 - previous);
                previous = id as u32;
                coords.extend_from_slice(now);
            }
        }
        (!ids.is_empty()).then(|| pb::Positions {
            step: frame.total_steps,
            topology_version: self.version,
            id_deltas: ids,
            positions_m: coords,
        })
    }
}

fn frame_bytes(frame: pb::viewer_frame::Frame) -> Vec<u8> {
    pb::ViewerFrame { frame: Some(frame) }.encode_to_vec()
}

/// How one viewer is served.
pub struct ViewerOptions {
    /// Holds the observe token (not the control token).
    pub observer: bool,
    /// Positions frames per second, to begin with.
    pub rate_hz: f64,
    /// ViewerRequests per second it may send (a second's worth at once).
    pub requests_per_second: f64,
}

/// Runs one viewer until it leaves, the session closes or a send fails.
pub async fn run_viewer<Tx, Rx, E>(
    mut sink: Tx,
    mut incoming: Rx,
    session: Arc<Session>,
    ViewerOptions { observer, rate_hz, requests_per_second }: ViewerOptions,
    metrics: &crate::metrics::Metrics,
) -> ViewerEnd
where
    Tx: Sink<Message> + Unpin,
    Rx: Stream<Item = Result<Message, E>> + Unpin,
{
    session.viewers.fetch_add(1, Ordering::Relaxed);
    let _guard = ViewerGuard(session.clone());
    let send = async |sink: &mut Tx, bytes: Vec<u8>| -> bool {
        let len = bytes.len() as u64;
        let ok = matches!(tokio::time::timeout(SEND_TIMEOUT, sink.send(Message::Binary(bytes.into()))).await, Ok(Ok(())));
        if ok {
            session.bytes_sent.fetch_add(len, Ordering::Relaxed);
            metrics.viewer_bytes.fetch_add(len, Ordering::Relaxed);
        }
        ok
    };
    let hello = pb::Hello { session: Some(convert::session_info(&session)), rate_hz, observer };
    if !send(&mut sink, frame_bytes(pb::viewer_frame::Frame::Hello(hello))).await {
        return ViewerEnd::SendFailed;
    }
    let subscribe = |session: &Session| {
        let frame = session.frame.load();
        let (snapshot, rx, epoch) = session.hub.subscribe(&frame);
        (snapshot, rx, epoch, frame.total_steps)
    };
    let (snapshot, mut rx, epoch, step) = subscribe(&session);
    let mut mirror = Mirror::from_snapshot(&snapshot, epoch);
    if !send(&mut sink, frame_bytes(pb::viewer_frame::Frame::Snapshot(convert::snapshot(&snapshot, &session.id, step)))).await {
        return ViewerEnd::SendFailed;
    }
    let mut ticker = tokio::time::interval(Duration::from_secs_f64(1.0 / rate_hz));
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut ticks: u64 = 0;
    let mut last_playback = None;
    let mut last_assessment: Option<std::sync::Arc<cutsim_sim::assessment::Assessment>> = None;
    let mut requests = crate::rate::TokenBucket::new(requests_per_second, requests_per_second, std::time::Instant::now());
    loop {
        let mut resync = false;
        tokio::select! {
            message = rx.recv() => match message {
                Ok(HubMessage::Delta(delta, bytes)) => {
                    if delta.version <= mirror.version {
                        continue; // already in the snapshot this viewer got
                    }
                    if delta.version != mirror.version + 1 {
                        resync = true;
                    } else {
                        mirror.apply(&delta);
                        if !send(&mut sink, (*bytes).clone()).await {
                            return ViewerEnd::SendFailed;
                        }
                    }
                }
                Ok(HubMessage::Reset) | Err(RecvError::Lagged(_)) => resync = true,
                Ok(HubMessage::Closed) | Err(RecvError::Closed) => {
                    session.settled().await;
                    // A failed session closes with "internal error" and the reason (cut
                    // to a close frame's 123 bytes).
                    let (code, reason) = match session.failure() {
                        Some(reason) => (1011, format!("session failed: {reason}").chars().scan(0, |n, c| { *n += c.len_utf8(); (*n <= 123).then_some(c) }).collect::<String>()),
                        None => (1001, "session closed".to_owned()),
                    };
                    let _ = sink.send(Message::Close(Some(CloseFrame { code, reason: reason.into() }))).await;
                    return ViewerEnd::SessionClosed;
                }
            },
            _ = ticker.tick() => {
                // Encode everything from the newest frame first, then send: a frame is
                // never held across a send, so a viewer that stops reading cannot pin the
                // physics thread's frames (it publishes into frames nobody holds).
                let outgoing = {
                    let frame = session.frame.load();
                    // The metrics change off the physics thread (an idle session's final
                    // metrics arrive after its last frame): they are news on their own.
                    let assessment = session.assessment.load();
                    let assessment_changed = !last_assessment.as_ref().is_some_and(|a| std::sync::Arc::ptr_eq(a, &assessment));
                    let new_frame = frame.sequence != mirror.last_frame;
                    if !new_frame && !assessment_changed {
                        continue;
                    }
                    let mut outgoing = Vec::with_capacity(3);
                    if new_frame {
                        mirror.last_frame = frame.sequence;
                        if let Some(moved) = mirror.moved(&frame) {
                            outgoing.push(frame_bytes(pb::viewer_frame::Frame::Positions(moved)));
                        }
                        outgoing.push(frame_bytes(pb::viewer_frame::Frame::Tools(convert::tool_states(&frame))));
                    }
                    // Stats ten times less often — and at once when a replay's playback
                    // changed, or the metrics changed while no frame came.
                    let playback_changed = frame.playback != last_playback;
                    last_playback = frame.playback;
                    if (new_frame && ticks % 10 == 0) || playback_changed || !new_frame {
                        let stats = pb::SessionStats {
                            step: frame.total_steps,
                            stats: Some(convert::stats(&frame.stats)),
                            counters: Some(convert::counters(&frame.counters, frame.pieces)),
                            fallbacks: frame.fallbacks.iter().map(convert::cut_fallback).collect(),
                            viewers: session.viewers.load(Ordering::Relaxed),
                            haptic_clients: session.subscribers.count() as u32,
                            status: convert::status(frame.status) as i32,
                            server_unix_ms: frame.unix_ms,
                            playback: convert::playback(&frame.playback, &session),
                            // The metrics only when they changed (their events list may be long).
                            assessment: assessment_changed.then(|| convert::assessment(&assessment, session.assessment.problem(), &session.assessment.task)),
                        };
                        if assessment_changed {
                            last_assessment = Some(assessment);
                        }
                        outgoing.push(frame_bytes(pb::viewer_frame::Frame::Stats(stats)));
                    }
                    outgoing
                };
                for bytes in outgoing {
                    if !send(&mut sink, bytes).await {
                        return ViewerEnd::SendFailed;
                    }
                }
                ticks += 1;
            },
            message = incoming.next() => match message {
                Some(Ok(Message::Binary(_))) if requests.take(std::time::Instant::now()).is_err() => {
                    return close(&mut sink, 1008, &format!("more than {requests_per_second} requests per second")).await;
                }
                Some(Ok(Message::Binary(bytes))) => match pb::ViewerRequest::decode(bytes.as_ref()) {
                    Ok(pb::ViewerRequest { request: Some(pb::viewer_request::Request::Resync(_)) }) => resync = true,
                    Ok(pb::ViewerRequest { request: Some(pb::viewer_request::Request::SetRateHz(hz)) }) if (1.0..=240.0).contains(&hz) => {
                        ticker = tokio::time::interval(Duration::from_secs_f64(1.0 / hz));
                        ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
                    }
                    Ok(other) => return close(&mut sink, 1008, &format!("unsupported request {other:?}: rates are 1 to 240 Hz")).await,
                    Err(e) => return close(&mut sink, 1007, &format!("not a ViewerRequest: {e}")).await,
                },
                Some(Ok(Message::Text(_))) => return close(&mut sink, 1003, "send binary protobuf ViewerRequest frames").await,
                Some(Ok(Message::Close(_))) | None | Some(Err(_)) => return ViewerEnd::ClientClosed,
                Some(Ok(_)) => {} // ping/pong are answered by the socket
            },
        }
        if resync {
            let (snapshot, new_rx, epoch, step) = subscribe(&session);
            rx = new_rx;
            mirror = Mirror::from_snapshot(&snapshot, epoch);
            if !send(&mut sink, frame_bytes(pb::viewer_frame::Frame::Snapshot(convert::snapshot(&snapshot, &session.id, step)))).await {
                return ViewerEnd::SendFailed;
            }
        }
    }
}

async fn close<Tx: Sink<Message> + Unpin>(sink: &mut Tx, code: u16, reason: &str) -> ViewerEnd {
    let _ = sink.send(Message::Close(Some(CloseFrame { code, reason: reason.to_owned().into() }))).await;
    ViewerEnd::Protocol(reason.to_owned())
}

#[cfg(test)]
mod tests {
    use super::*;
    use cutsim_sim::surface::{SurfaceVertex, TopologyDelta};

    fn vertex(id: u32, x: f32) -> SurfaceVertex {
        SurfaceVertex { id, position_m: [x, 0.0, 0.0], material: 0 }
    }

    /// The frame of the step that made a vertex, looked at before the delta that adds it
    /// arrives, still sends the vertex's position once the delta is in (the session may
    /// publish no other frame).
    #[test]
    fn a_vertex_added_after_its_frame_was_looked_at_gets_that_frames_position() {
        let snapshot = SurfaceSnapshot { version: 3, vertices: vec![vertex(0, 0.0), vertex(1, 1.0)], triangles: vec![] };
        let mut mirror = Mirror::from_snapshot(&snapshot, 0);
        let frame = Frame { sequence: 7, positions: vec![[0.5, 0.0, 0.0], [1.0, 0.0, 0.0], [2.5, 0.0, 0.0]], ..Frame::default() };
        // The tick sees the frame first: vertex 0 moved; vertex 2 is not the viewer's yet.
        mirror.last_frame = frame.sequence;
        let moved = mirror.moved(&frame).expect("vertex 0 moved");
        assert_eq!((moved.id_deltas, moved.positions_m), (vec![0], vec![0.5, 0.0, 0.0]));
        // Then the delta that made vertex 2 (at 2.0; the frame has it at 2.5).
        mirror.apply(&TopologyDelta { version: 4, added_vertices: vec![vertex(2, 2.0)], ..TopologyDelta::default() });
        assert_ne!(mirror.last_frame, frame.sequence, "the frame is looked at again");
        let moved = mirror.moved(&frame).expect("vertex 2 is behind the frame");
        assert_eq!((moved.id_deltas, moved.positions_m), (vec![2], vec![2.5, 0.0, 0.0]));
        assert!(mirror.moved(&frame).is_none(), "then nothing is behind");
    }
}
