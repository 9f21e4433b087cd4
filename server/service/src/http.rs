//! HTTP: the web viewer's files at `/`, the session list (`/api/sessions` JSON,
//! `/sessions` HTML), Prometheus metrics at `/metrics`, `/healthz`, and the WebSocket
//! viewer at `/ws/sessions/{id}`.

use std::sync::Arc;

use axum::Router;
use axum::extract::State;
use axum::http::header;
use axum::response::{Html, IntoResponse};
use axum::extract::Path;
use axum::http::{HeaderMap, StatusCode};
use axum::routing::{get, post};
use serde::Serialize;
use tower_http::services::ServeDir;

use crate::auth::{Role, TOKEN_KEY, Token};
use crate::convert;
use crate::rate::ClientRates;
use crate::error::ApiError;
use crate::session::PlaybackCommand;
use crate::metrics::{self, Metrics};
use crate::session::Registry;

/// The protocol's schema, served to the viewer (which parses it with protobufjs): the
/// very file the server was built from.
const PROTO: &str = include_str!("../../../proto/cutsim.proto");

#[derive(Clone)]
pub struct AppState {
    pub registry: Arc<Registry>,
    pub metrics: Arc<Metrics>,
    pub rates: Arc<ClientRates>,
}

pub fn router(state: AppState) -> Router {
    let viewer = ServeDir::new(&state.registry.config.viewer_dir);
    Router::new()
        .route("/ws/sessions/{id}", get(crate::ws::upgrade))
        .route("/api/recordings", get(recordings))
        .route("/api/recordings/{session}/replay", post(replay))
        .route("/api/sessions/{id}/playback", post(playback))
        .route("/api/sessions", get(sessions_json))
        .route("/sessions", get(sessions_html))
        .route("/metrics", get(metrics_text))
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/cutsim.proto", get(|| async { ([(header::CONTENT_TYPE, "text/plain; charset=utf-8")], PROTO) }))
        .fallback_service(viewer)
        .layer(axum::middleware::from_fn_with_state(state.clone(), rate_limited))
        .with_state(state)
}

/// Every HTTP request (pages, API, WebSocket upgrades) counts against its client's rate.
async fn rate_limited(State(app): State<AppState>, request: axum::extract::Request, next: axum::middleware::Next) -> axum::response::Response {
    let peer = request.extensions().get::<axum::extract::ConnectInfo<std::net::SocketAddr>>().map(|c| c.0);
    let forwarded: Vec<&str> = request.headers().get_all("x-forwarded-for").iter().filter_map(|v| v.to_str().ok()).collect();
    match app.rates.admit(peer, &forwarded) {
        Ok(()) => next.run(request).await,
        Err(refused) => refused.into_response(),
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
}

fn summaries(registry: &Registry) -> Vec<SessionSummary> {
    registry
        .list()
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
            }
        })
        .collect()
}

async fn sessions_json(State(app): State<AppState>) -> impl IntoResponse {
    axum::Json(summaries(&app.registry))
}

async fn sessions_html(State(app): State<AppState>) -> Html<String> {
    let rows: String = summaries(&app.registry)
        .iter()
        .map(|s| {
            format!(
                "<tr><td><a href=\"/?session={id}\">{id}</a></td><td>{label}</td><td>{scene}</td><td>{model}</td><td>{status}</td><td>{rate:.0} Hz</td><td>{age:.0} s</td><td>{p99:.0} µs</td><td>{viewers}</td></tr>",
                id = escape(&s.id),
                label = escape(&s.label),
                scene = escape(&s.scene),
                model = escape(&s.model),
                status = escape(&s.status),
                rate = s.achieved_rate_hz,
                age = s.age_s,
                p99 = s.step_time_p99_us,
                viewers = s.viewers
            )
        })
        .collect();
    Html(format!(
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>cutsim sessions</title></head><body><h1>Sessions</h1>\
         <table><tr><th>id</th><th>label</th><th>scene</th><th>model</th><th>status</th><th>rate</th><th>age</th><th>p99 step</th><th>viewers</th></tr>{rows}</table>\
         <p>Open a session with its observe token: <code>/?session=ID&amp;token=TOKEN</code></p></body></html>"
    ))
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

async fn metrics_text(State(app): State<AppState>) -> impl IntoResponse {
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], metrics::render(&app.registry, &app.metrics))
}

fn header_token(headers: &HeaderMap) -> Option<&str> {
    headers.get(TOKEN_KEY).and_then(|v| v.to_str().ok())
}

/// Recordings and replays need the server's admin token.
fn check_admin(app: &AppState, headers: &HeaderMap) -> Result<(), ApiError> {
    let expected = app.registry.config.admin_token.as_deref().unwrap_or_default();
    match header_token(headers) {
        Some(given) if !expected.is_empty() && Token::from_string(expected.to_owned()).matches(given) => Ok(()),
        Some(_) => Err(ApiError::Unauthenticated("the admin token is not valid".into())),
        None => Err(ApiError::Unauthenticated(format!("recordings need the server's admin token (header `{TOKEN_KEY}`)"))),
    }
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

async fn recordings(State(app): State<AppState>, headers: HeaderMap) -> Result<impl IntoResponse, ApiError> {
    check_admin(&app, &headers)?;
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

async fn replay(State(app): State<AppState>, headers: HeaderMap, Path(session): Path<String>) -> Result<impl IntoResponse, ApiError> {
    check_admin(&app, &headers)?;
    let replay = app.registry.create_replay(&session).await?;
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
    headers: HeaderMap,
    Path(id): Path<String>,
    body: Result<axum::Json<PlaybackRequest>, axum::extract::rejection::JsonRejection>,
) -> Result<StatusCode, ApiError> {
    let session = app.registry.get(&id)?;
    session.authorize(header_token(&headers), Role::Control)?;
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
    applied.await.map_err(|_| ApiError::FailedPrecondition(format!("session {id} stopped")))?;
    Ok(StatusCode::NO_CONTENT)
}
