//! HTTP: the web viewer's files at `/`, the session list (`/api/sessions` JSON,
//! `/sessions` HTML), Prometheus metrics at `/metrics`, `/healthz`, and the WebSocket
//! viewer at `/ws/sessions/{id}`.

use std::sync::Arc;

use axum::Router;
use axum::extract::State;
use axum::http::header;
use axum::response::{Html, IntoResponse};
use axum::routing::get;
use serde::Serialize;
use tower_http::services::ServeDir;

use crate::convert;
use crate::metrics::{self, Metrics};
use crate::session::Registry;

/// The protocol's schema, served to the viewer (which parses it with protobufjs): the
/// very file the server was built from.
const PROTO: &str = include_str!("../../../proto/cutsim.proto");

#[derive(Clone)]
pub struct AppState {
    pub registry: Arc<Registry>,
    pub metrics: Arc<Metrics>,
}

pub fn router(state: AppState) -> Router {
    let viewer = ServeDir::new(&state.registry.config.viewer_dir);
    Router::new()
        .route("/ws/sessions/{id}", get(crate::ws::upgrade))
        .route("/api/sessions", get(sessions_json))
        .route("/sessions", get(sessions_html))
        .route("/metrics", get(metrics_text))
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/cutsim.proto", get(|| async { ([(header::CONTENT_TYPE, "text/plain; charset=utf-8")], PROTO) }))
        .fallback_service(viewer)
        .with_state(state)
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
