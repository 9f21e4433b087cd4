//! HTTP: the web viewer's files at `/`, the session list for operators
//! (`/api/sessions`), one session for its token holders (`/api/sessions/{id}`),
//! Prometheus metrics at `/metrics`, `/healthz`, recordings and replays, and the
//! WebSocket viewer at `/ws/sessions/{id}`.
//!
//! Every response carries a strict Content-Security-Policy and the usual security
//! headers: the viewer's own scripts run, nothing injected does.

use std::net::SocketAddr;
use std::sync::Arc;

use axum::Router;
use axum::extract::{ConnectInfo, FromRequestParts, Path, State};
use axum::http::request::Parts;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::IntoResponse;
use axum::routing::{get, post};
use serde::Serialize;
use tower_http::services::ServeDir;

use crate::auth::{Caller, Operator, Role, TOKEN_KEY};
use crate::convert;
use crate::error::ApiError;
use crate::metrics::{self, Metrics};
use crate::rate::ClientRates;
use crate::session::{CloseReason, Creator, PlaybackCommand, Registry};

/// The protocol's schema as text (for people and tools) and as an encoded
/// FileDescriptorSet, which the viewer decodes its frames with (reflection, no eval):
/// the very file the server was built from.
const PROTO: &str = include_str!("../../../proto/cutsim.proto");

#[derive(Clone)]
pub struct AppState {
    pub registry: Arc<Registry>,
    pub metrics: Arc<Metrics>,
    pub rates: Arc<ClientRates>,
    /// Security headers sent with every response.
    pub headers: Arc<SecurityHeaders>,
}

pub fn router(state: AppState) -> Router {
    let viewer = ServeDir::new(&state.registry.config.viewer_dir);
    Router::new()
        .route("/ws/sessions/{id}", get(crate::ws::upgrade))
        .route("/api/recordings", get(recordings))
        .route("/api/recordings/{session}/replay", post(replay))
        .route("/api/sessions/{id}/playback", post(playback))
        .route("/api/sessions/{id}/report", get(assessment_report))
        .route("/api/sessions/{id}/timeline", get(replay_timeline))
        .route("/api/sessions/{id}", get(session_json).delete(close_session))
        .route("/api/sessions", get(sessions_json))
        .route("/api/whoami", get(whoami))
        .route("/metrics", get(metrics_text))
        .route("/healthz", get(healthz))
        .route("/cutsim.proto", get(|| async { ([(header::CONTENT_TYPE, "text/plain; charset=utf-8")], PROTO) }))
        .route("/cutsim.binpb", get(|| async { ([(header::CONTENT_TYPE, "application/octet-stream")], cutsim_proto::FILE_DESCRIPTOR_SET) }))
        .fallback_service(viewer)
        .layer(axum::middleware::from_fn_with_state(state.clone(), security_headers))
        .layer(axum::middleware::from_fn_with_state(state.clone(), rate_limited))
        .with_state(state)
}

/// Every HTTP request (pages, API, WebSocket upgrades) counts against its client's rate.
async fn rate_limited(State(app): State<AppState>, request: axum::extract::Request, next: axum::middleware::Next) -> axum::response::Response {
    let peer = request.extensions().get::<ConnectInfo<SocketAddr>>().map(|c| c.0);
    let forwarded: Vec<&str> = request.headers().get_all("x-forwarded-for").iter().filter_map(|v| v.to_str().ok()).collect();
    match app.rates.admit(peer, &forwarded) {
        Ok(()) => next.run(request).await,
        Err(refused) => refused.into_response(),
    }
}

/// The headers every response carries.
pub struct SecurityHeaders {
    list: Vec<(header::HeaderName, HeaderValue)>,
}

impl SecurityHeaders {
    /// For the viewer in `viewer_dir`: its index.html's inline import map is allowed by
    /// its hash, every other script must come from the server itself, and no script may
    /// be made from text (no eval). `tls`: browsers are told to use https only.
    pub fn new(viewer_dir: &std::path::Path, tls: bool) -> Self {
        let import_maps = std::fs::read_to_string(viewer_dir.join("index.html")).map(|html| inline_script_hashes(&html)).unwrap_or_default();
        let csp = format!(
            "default-src 'none'; script-src 'self'{import_maps}; style-src 'self'; img-src 'self' data: blob:; connect-src 'self'; \
             font-src 'self'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'; object-src 'none'"
        );
        let mut list = vec![
            (header::CONTENT_SECURITY_POLICY, csp),
            (header::X_CONTENT_TYPE_OPTIONS, "nosniff".into()),
            (header::REFERRER_POLICY, "no-referrer".into()),
            (header::X_FRAME_OPTIONS, "DENY".into()),
            (header::HeaderName::from_static("cross-origin-opener-policy"), "same-origin".into()),
            (header::HeaderName::from_static("cross-origin-resource-policy"), "same-origin".into()),
            (header::HeaderName::from_static("permissions-policy"), "camera=(), microphone=(), geolocation=(), usb=(), payment=()".into()),
        ];
        if tls {
            list.push((header::STRICT_TRANSPORT_SECURITY, "max-age=31536000".into()));
        }
        Self { list: list.into_iter().map(|(n, v)| (n, HeaderValue::from_str(&v).expect("header values are ASCII"))).collect() }
    }
}

/// `'sha256-…'` sources for the inline `<script>` blocks of a page (its import map).
fn inline_script_hashes(html: &str) -> String {
    use base64::Engine as _;
    let mut out = String::new();
    let mut rest = html;
    while let Some(open) = rest.find("<script") {
        let after = &rest[open..];
        let Some(tag_end) = after.find('>') else { break };
        let tag = &after[..tag_end];
        let body_and_more = &after[tag_end + 1..];
        let Some(close) = body_and_more.find("</script>") else { break };
        if !tag.contains(" src=") {
            let digest = ring::digest::digest(&ring::digest::SHA256, body_and_more[..close].as_bytes());
            out.push_str(&format!(" 'sha256-{}'", base64::engine::general_purpose::STANDARD.encode(digest.as_ref())));
        }
        rest = &body_and_more[close..];
    }
    out
}

async fn security_headers(State(app): State<AppState>, request: axum::extract::Request, next: axum::middleware::Next) -> axum::response::Response {
    let api = request.uri().path().starts_with("/api/");
    let mut response = next.run(request).await;
    let headers = response.headers_mut();
    for (name, value) in &app.headers.list {
        // A page with a policy of its own (the printable report) keeps it.
        if name == header::CONTENT_SECURITY_POLICY && headers.contains_key(name) {
            continue;
        }
        headers.insert(name.clone(), value.clone());
    }
    if api {
        headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    }
    response
}

/// Who is calling over HTTP: the `cutsim-token` header, the peer, and whether its TLS
/// client certificate is an operator's.
pub struct HttpCaller {
    token: Option<String>,
    peer: Option<SocketAddr>,
    certificate: bool,
}

impl HttpCaller {
    pub fn caller(&self) -> Caller<'_> {
        Caller { token: self.token.as_deref(), peer: self.peer, operator_certificate: self.certificate }
    }

    pub fn token(&self) -> Option<&str> {
        self.token.as_deref()
    }

    fn operator(&self, app: &AppState) -> Result<Operator, ApiError> {
        app.registry.operators.authenticate(&self.caller())
    }

    /// A caller with no credentials at all is refused before anything is looked up (an
    /// anonymous client learns nothing, not even whether a session exists).
    pub fn require_credentials(&self, app: &AppState) -> Result<(), ApiError> {
        if self.token.as_deref().is_some_and(|t| !t.is_empty()) || self.operator(app).is_ok() {
            return Ok(());
        }
        Err(ApiError::Unauthenticated(format!("this needs a session token or an operator's credentials (header `{TOKEN_KEY}`)")))
    }
}

impl<S: Send + Sync> FromRequestParts<S> for HttpCaller {
    type Rejection = std::convert::Infallible;

    async fn from_request_parts(parts: &mut Parts, _: &S) -> Result<Self, Self::Rejection> {
        Ok(Self {
            token: parts.headers.get(TOKEN_KEY).and_then(|v| v.to_str().ok()).map(str::to_owned),
            peer: parts.extensions.get::<ConnectInfo<SocketAddr>>().map(|c| c.0),
            certificate: parts.extensions.get::<crate::tls::OperatorCertificate>().is_some(),
        })
    }
}

/// One session in the public list (no tokens).
#[derive(Serialize)]
pub struct SessionSummary {
    pub id: String,
    pub label: String,
    pub scene: String,
    pub model: String,
    pub mode: String,
    pub status: String,
    pub rate_hz: f64,
    /// Multirate: the deformation's rate, Hz (0: single-rate).
    pub deformation_rate_hz: f64,
    pub age_s: f64,
    pub step: u64,
    pub viewers: u32,
    pub haptic_clients: u32,
    pub step_time_p50_us: f64,
    pub step_time_p99_us: f64,
    pub missed_deadlines: u64,
    pub achieved_rate_hz: f64,
    pub cuts: u64,
    pub surface_triangles: u64,
    /// Cut updates of the current tissue left as open holes, each with its step and
    /// reason (`SessionInfo.fallbacks`).
    pub reconstruction_fallbacks: u64,
    pub fallbacks: Vec<FallbackSummary>,
    /// Strokes whose last piece could not be stitched and was left uncut.
    pub uncut_last_pieces: u64,
}

/// A cut update whose wound was left as an open hole: the tissue's step and why.
#[derive(Serialize)]
pub struct FallbackSummary {
    pub step: u64,
    pub reason: String,
}

fn summaries(sessions: &[Arc<crate::session::Session>]) -> Vec<SessionSummary> {
    sessions
        .iter()
        .map(|s| {
            let info = convert::session_info(s);
            let stats = info.stats.unwrap_or_default();
            let counters = info.counters.unwrap_or_default();
            SessionSummary {
                id: info.id,
                label: info.label,
                scene: info.scene,
                model: info.model,
                mode: format!("{:?}", s.mode).to_lowercase(),
                status: cutsim_proto::v1::SessionStatus::try_from(info.status)
                    .map(|st| st.as_str_name().trim_start_matches("SESSION_STATUS_").to_lowercase())
                    .unwrap_or_default(),
                rate_hz: info.rate_hz,
                deformation_rate_hz: info.deformation_rate_hz,
                age_s: info.age_s,
                step: info.step,
                viewers: info.viewers,
                haptic_clients: info.haptic_clients,
                step_time_p50_us: stats.p50_us,
                step_time_p99_us: stats.p99_us,
                missed_deadlines: stats.missed_deadlines,
                achieved_rate_hz: stats.achieved_rate_hz,
                cuts: counters.cuts,
                surface_triangles: counters.surface_triangles,
                reconstruction_fallbacks: counters.reconstruction_fallbacks,
                fallbacks: info.fallbacks.into_iter().map(|f| FallbackSummary { step: f.step, reason: f.reason }).collect(),
                uncut_last_pieces: counters.uncut_last_pieces,
            }
        })
        .collect()
}

async fn sessions_json(State(app): State<AppState>, caller: HttpCaller) -> Result<impl IntoResponse, ApiError> {
    caller.operator(&app)?;
    Ok(axum::Json(summaries(&app.registry.list())))
}

/// A session its caller may watch: with its observe or control token, or as an operator.
fn observed_session(app: &AppState, caller: &HttpCaller, id: &str) -> Result<Arc<crate::session::Session>, ApiError> {
    caller.require_credentials(app)?;
    let session = app.registry.get(id)?;
    if let Err(e) = session.authorize(caller.token(), Role::Observe) {
        caller.operator(app).map_err(|_| e)?;
    }
    Ok(session)
}

/// `GET /api/sessions/{id}`: one session, for its token holders and operators (the
/// viewer asks whether its session still exists).
async fn session_json(State(app): State<AppState>, caller: HttpCaller, Path(id): Path<String>) -> Result<impl IntoResponse, ApiError> {
    let session = observed_session(&app, &caller, &id)?;
    Ok(axum::Json(summaries(&[session]).remove(0)))
}

/// `GET /api/sessions/{id}/report`: the session's assessment as a printable HTML page
/// (docs/assessment.md), for its token holders and operators. It holds no script; it is
/// served as an attachment so that it opens as a file of its own, outside the viewer.
async fn assessment_report(State(app): State<AppState>, caller: HttpCaller, Path(id): Path<String>) -> Result<impl IntoResponse, ApiError> {
    let session = observed_session(&app, &caller, &id)?;
    let cell = &session.assessment;
    let header = cutsim_sim::assessment::report::ReportHeader {
        session: &session.id,
        scene: &session.scene_name,
        task: &cell.task.description,
        build: crate::session::recording::BUILD,
    };
    let html = cutsim_sim::assessment::report::render(&header, &cell.checked, &cell.load(), &cell.history());
    let disposition = format!("attachment; filename=\"cutsim-report-{}.html\"", session.id);
    Ok((
        [
            (header::CONTENT_TYPE, "text/html; charset=utf-8".to_owned()),
            (header::CONTENT_DISPOSITION, disposition),
            // Its own page: inline styles, no script, nothing loaded from anywhere.
            (header::CONTENT_SECURITY_POLICY, "default-src 'none'; style-src 'unsafe-inline'".to_owned()),
        ],
        html,
    ))
}

/// `GET /api/sessions/{id}/timeline`: a replay's force and metric curves over its whole
/// recording (docs/server.md), as far as the replay has indexed it, for its token
/// holders and operators.
async fn replay_timeline(State(app): State<AppState>, caller: HttpCaller, Path(id): Path<String>) -> Result<impl IntoResponse, ApiError> {
    let session = observed_session(&app, &caller, &id)?;
    if session.mode != crate::session::Mode::Replay {
        return Err(ApiError::FailedPrecondition(format!("session {id} is not a replay; only replays have a timeline")));
    }
    let timeline = session.assessment.timeline().ok_or_else(|| ApiError::Unavailable(format!("replay {id} is starting; ask again")))?;
    Ok(axum::Json(timeline.as_ref().clone()))
}

/// `DELETE /api/sessions/{id}`: an operator closes any session; its control token
/// closes it too.
async fn close_session(State(app): State<AppState>, caller: HttpCaller, Path(id): Path<String>) -> Result<StatusCode, ApiError> {
    caller.require_credentials(&app)?;
    let session = app.registry.get(&id)?;
    if let Err(e) = session.authorize(caller.token(), Role::Control) {
        let operator = caller.operator(&app).map_err(|_| e)?;
        tracing::info!(session = %id, by = %operator, "an operator closes the session");
    }
    app.registry.close(&id, CloseReason::Closed).await?;
    Ok(StatusCode::NO_CONTENT)
}

/// `GET /api/whoami`: whether the caller is an operator (the viewer asks before it
/// lists sessions, rather than provoke a 401): `{"operator": true, "as": "operator \"lab\""}`.
async fn whoami(State(app): State<AppState>, caller: HttpCaller) -> impl IntoResponse {
    let operator = caller.operator(&app).ok();
    axum::Json(serde_json::json!({ "operator": operator.is_some(), "as": operator.map(|o| o.to_string()) }))
}

/// `GET /healthz`: 200 while the server serves; says how many sessions failed.
async fn healthz(State(app): State<AppState>) -> impl IntoResponse {
    let failed = app.registry.list().iter().filter(|s| s.failure().is_some()).count();
    format!("ok\nsessions {}\nfailed sessions {failed}\n", app.registry.list().len())
}

async fn metrics_text(State(app): State<AppState>) -> impl IntoResponse {
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], metrics::render(&app.registry, &app.metrics))
}

/// One recording in the list.
#[derive(Serialize)]
pub struct RecordingSummary {
    pub session: String,
    pub scene: String,
    pub bytes: u64,
    pub modified_unix_s: f64,
    /// Whether the session was closed (false: still running, or the server stopped).
    pub ended: bool,
    pub live: bool,
}

async fn recordings(State(app): State<AppState>, caller: HttpCaller) -> Result<impl IntoResponse, ApiError> {
    caller.operator(&app)?;
    let dir = app.registry.config.recordings_dir.clone();
    let live: Vec<String> = app.registry.list().iter().map(|s| s.id.clone()).collect();
    let list = tokio::task::spawn_blocking(move || list_recordings(&dir, &live)).await.map_err(|e| ApiError::Internal(e.to_string()))?;
    Ok(axum::Json(list))
}

fn list_recordings(dir: &std::path::Path, live: &[String]) -> Vec<RecordingSummary> {
    use std::io::{BufRead, Read, Seek, SeekFrom};
    let mut out = Vec::new();
    let Ok(entries) = std::fs::read_dir(dir) else { return out };
    for entry in entries.flatten() {
        let path = entry.path();
        let Some(session) = path.file_name().and_then(|n| n.to_str()).and_then(|n| n.strip_suffix(".jsonl")).map(str::to_owned) else { continue };
        let Ok(mut file) = std::fs::File::open(&path) else { continue };
        let meta = file.metadata().ok();
        let mut header = String::new();
        if std::io::BufReader::new(&file).read_line(&mut header).is_err() {
            continue;
        }
        let scene = serde_json::from_str::<serde_json::Value>(&header)
            .ok()
            .and_then(|h| h["scene"]["name"].as_str().map(str::to_owned))
            .unwrap_or_default();
        let len = meta.as_ref().map_or(0, |m| m.len());
        let mut tail = String::new();
        let _ = file.seek(SeekFrom::Start(len.saturating_sub(256))).and_then(|_| file.read_to_string(&mut tail));
        out.push(RecordingSummary {
            live: live.contains(&session),
            session,
            scene,
            bytes: len,
            modified_unix_s: meta
                .and_then(|m| m.modified().ok())
                .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                .map_or(0.0, |d| d.as_secs_f64()),
            ended: tail.trim_end().lines().last().is_some_and(|l| l.contains("\"t\":\"end\"")),
        });
    }
    out.sort_by(|a, b| b.modified_unix_s.total_cmp(&a.modified_unix_s));
    out
}

#[derive(Serialize)]
struct ReplayCreated {
    session_id: String,
    control_token: String,
    observe_token: String,
    total_steps: u64,
}

async fn replay(State(app): State<AppState>, caller: HttpCaller, Path(session): Path<String>) -> Result<impl IntoResponse, ApiError> {
    let operator = caller.operator(&app)?;
    let replay = app.registry.create_replay(&session, Creator { who: operator.to_string(), expires: true }).await?;
    let (control, observe) = replay.tokens();
    // The frame with the playback state comes from the replay thread; wait for it briefly.
    let mut total_steps = 0;
    for _ in 0..100 {
        if let Some(p) = replay.frame.load().playback {
            total_steps = p.total_steps;
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(5)).await;
    }
    Ok((
        StatusCode::CREATED,
        axum::Json(ReplayCreated { session_id: replay.id.clone(), control_token: control.to_owned(), observe_token: observe.to_owned(), total_steps }),
    ))
}

/// `{"action": "play" | "pause" | "seek" | "speed", "step": 1234, "speed": 2.0}`
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct PlaybackRequest {
    action: String,
    step: Option<u64>,
    speed: Option<f64>,
}

async fn playback(
    State(app): State<AppState>,
    caller: HttpCaller,
    Path(id): Path<String>,
    body: Result<axum::Json<PlaybackRequest>, axum::extract::rejection::JsonRejection>,
) -> Result<StatusCode, ApiError> {
    caller.require_credentials(&app)?;
    let session = app.registry.get(&id)?;
    session.authorize(caller.token(), Role::Control)?;
    session.touch();
    if session.mode != crate::session::Mode::Replay {
        return Err(ApiError::FailedPrecondition(format!("session {id} is not a replay; only replays have a playback")));
    }
    let axum::Json(request) = body.map_err(|e| ApiError::InvalidArgument(format!("playback request: {e}")))?;
    let command = match (request.action.as_str(), request.step, request.speed) {
        ("play", None, None) => PlaybackCommand::Play,
        ("pause", None, None) => PlaybackCommand::Pause,
        ("seek", Some(step), None) => PlaybackCommand::Seek(step),
        ("speed", None, Some(speed)) if speed.is_finite() && (0.05..=20.0).contains(&speed) => PlaybackCommand::Speed(speed),
        _ => {
            return Err(ApiError::InvalidArgument(
                "playback takes {\"action\": \"play\"}, {\"action\": \"pause\"}, {\"action\": \"seek\", \"step\": N} or {\"action\": \"speed\", \"speed\": 0.05 to 20}".into(),
            ));
        }
    };
    let (done, applied) = tokio::sync::oneshot::channel();
    session.send_control(crate::session::Control::Playback(command, done))?;
    applied.await.map_err(|_| session.stopped_error())?;
    Ok(StatusCode::NO_CONTENT)
}
