//! `cutsim-server serve`: the gRPC and HTTP servers, and a first session.

use std::sync::Arc;

use anyhow::Context;
use cutsim_proto::v1::haptics_server::HapticsServer;
use cutsim_proto::v1::scripts_server::ScriptsServer;
use cutsim_proto::v1::sessions_server::SessionsServer;
use tokio::net::TcpListener;

use crate::config::ServerConfig;
use crate::grpc::Api;
use crate::http::{self, AppState};
use crate::metrics::Metrics;
use crate::session::{Creator, Mode, Registry, SceneSource, SessionHealth};

/// Runs the servers until SIGINT or SIGTERM — gRPC on the calling runtime, HTTP on
/// `http_runtime` (whose threads run below the haptic path); `first_scene` opens a
/// session at start.
pub async fn serve(config: ServerConfig, first_scene: Option<String>, http_runtime: tokio::runtime::Handle) -> anyhow::Result<()> {
    config.check_development_mode().map_err(|e| anyhow::anyhow!(e))?;
    let mut operator_tokens = config.operator_token_list();
    let made_up = operator_tokens.is_empty().then(|| crate::auth::Token::generate().as_str().to_owned());
    if let Some(token) = &made_up {
        operator_tokens.push(("made up at start".into(), token.clone()));
    }
    let operators = crate::auth::Operators::new(operator_tokens, config.development_mode).map_err(|e| anyhow::anyhow!(e))?;
    let config = Arc::new(config);
    let registry = Registry::new(config.clone(), operators);
    let metrics = Arc::new(Metrics::default());

    let grpc_listener = TcpListener::bind(config.grpc_addr).await.with_context(|| format!("cannot listen for gRPC on {}", config.grpc_addr))?;
    // Bound here, registered with the HTTP runtime: its connections are served there.
    let http_listener = std::net::TcpListener::bind(config.http_addr).with_context(|| format!("cannot listen for HTTP on {}", config.http_addr))?;
    http_listener.set_nonblocking(true)?;
    let http_listener = {
        let _inside = http_runtime.enter();
        TcpListener::from_std(http_listener)?
    };
    let grpc_addr = grpc_listener.local_addr()?;
    let http_addr = http_listener.local_addr()?;

    let trusted_proxies = config.limits.trusted_proxy_blocks().map_err(|e| anyhow::anyhow!("limits.{e}"))?;
    let rates = Arc::new(crate::rate::ClientRates::new(config.limits.requests_per_second_per_client, config.limits.request_burst_per_client, trusted_proxies));
    let api = Api { registry: registry.clone() };
    let limit = config.limits.max_message_bytes;
    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<SessionsServer<Api>>().await;
    health.set_serving::<HapticsServer<Api>>().await;
    health.set_serving::<ScriptsServer<Api>>().await;
    // Reflection in both versions: grpcurl asks v1, grpcio's tooling (Python) v1alpha.
    let reflection = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(cutsim_proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    let reflection_v1 = reflection().build_v1().context("building the reflection service (v1)")?;
    let reflection_v1alpha = reflection().build_v1alpha().context("building the reflection service (v1alpha)")?;
    // Each session shows in health as `cutsim.v1.Session/<id>`: SERVING, or NOT_SERVING
    // once its physics failed (the server and its other sessions serve on).
    let (health_tx, mut session_health) = tokio::sync::mpsc::unbounded_channel::<(String, SessionHealth)>();
    registry.report_health_to(health_tx);
    {
        let mut health = health.clone();
        tokio::spawn(async move {
            while let Some((id, state)) = session_health.recv().await {
                let name = format!("cutsim.v1.Session/{id}");
                match state {
                    SessionHealth::Serving => health.set_service_status(name, tonic_health::ServingStatus::Serving).await,
                    SessionHealth::Failed => health.set_service_status(name, tonic_health::ServingStatus::NotServing).await,
                    SessionHealth::Gone => health.clear_service_status(&name).await,
                }
            }
        });
    }
    let shutdown = shutdown_signal();
    let (stop_tx, _) = tokio::sync::broadcast::channel::<()>(1);
    let mut stop_grpc = stop_tx.subscribe();
    let mut stop_http = stop_tx.subscribe();
    let tls = match &config.tls {
        Some(c) => Some(crate::tls::Tls::load(c).map_err(|e| anyhow::anyhow!(e))?),
        None => None,
    };
    let mut grpc_server = tonic::transport::Server::builder();
    if let Some(tls) = &tls {
        grpc_server = grpc_server.tls_config(tls.grpc_config()).context("TLS for gRPC")?;
    }
    // HTTP/2 keepalive finds peers that vanished without closing (a dropped network, a
    // paused process): their streams end and their tools leave the scene.
    let keepalive = std::time::Duration::from_secs_f64(config.limits.keepalive_interval_s);
    let grpc = grpc_server
        .tcp_nodelay(true)
        .http2_keepalive_interval(Some(keepalive))
        .http2_keepalive_timeout(Some(std::time::Duration::from_secs_f64(config.limits.keepalive_timeout_s)))
        .layer(tonic::service::InterceptorLayer::new(crate::rate::admit_grpc(rates.clone())))
        .add_service(health_service)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(SessionsServer::new(api.clone()).max_decoding_message_size(limit))
        .add_service(HapticsServer::new(api.clone()).max_decoding_message_size(limit))
        .add_service(ScriptsServer::new(api).max_decoding_message_size(limit))
        .serve_with_incoming_shutdown(tonic::transport::server::TcpIncoming::from(grpc_listener).with_nodelay(Some(true)).with_keepalive(Some(keepalive)), async move {
            let _ = stop_grpc.recv().await;
        });
    let headers = Arc::new(http::SecurityHeaders::new(&config.viewer_dir, tls.is_some()));
    let app = http::router(AppState { registry: registry.clone(), metrics, rates, headers });
    let stop_http = async move {
        let _ = stop_http.recv().await;
    };
    let http_server: std::pin::Pin<Box<dyn std::future::Future<Output = ()> + Send>> = match &tls {
        Some(tls) => Box::pin(crate::tls::serve_https(http_listener, tls.http_acceptor.clone(), app, stop_http)),
        None => {
            let listener = axum::serve::ListenerExt::tap_io(http_listener, |tcp| {
                let _ = tcp.set_nodelay(true);
            });
            let serving = axum::serve(listener, app.into_make_service_with_connect_info::<std::net::SocketAddr>()).with_graceful_shutdown(stop_http);
            Box::pin(async move {
                if let Err(e) = serving.await {
                    tracing::error!("HTTP server: {e}");
                }
            })
        }
    };
    let scheme = if tls.is_some() { "https" } else { "http" };

    println!("grpc listening on {grpc_addr}");
    println!("http listening on {http_addr}");
    if tls.is_some() {
        println!("tls on: gRPC and HTTP/WebSocket take TLS only (https://, wss://)");
    }
    if let Some(token) = &made_up {
        println!("operator token (create, list and close sessions; recordings): {token}");
    }
    if config.development_mode {
        let warning = "DEVELOPMENT MODE: every program on this machine is an operator (creates, lists and closes sessions, reads recordings) without a token. Never use it on a shared machine.";
        println!("WARNING: {warning}");
        tracing::warn!("{warning}");
    }
    tracing::info!(%grpc_addr, %http_addr, "cutsim-server listening");

    if let Some(scene) = first_scene {
        let creator = Creator { who: "the command line".into(), expires: false };
        let session = registry.create(SceneSource::Operator(scene), Mode::Realtime, "default".into(), creator).await.map_err(|e| anyhow::anyhow!("{e}"))?;
        let (control, observe) = session.tokens();
        println!("session {} on scene {}", session.id, session.scene_name);
        println!("  viewer:        {scheme}://{http_addr}/?session={}&token={observe}", session.id);
        println!("  control token: {control}");
        if let Some(path) = session.recording_path() {
            println!("  recording:     {}", path.display());
        }
    }
    use std::io::Write;
    let _ = std::io::stdout().flush();

    let grpc_task = tokio::spawn(grpc);
    let http_task = http_runtime.spawn(http_server);
    tokio::spawn(housekeeping(registry.clone()));
    shutdown.await;
    tracing::info!("shutting down: closing sessions");
    let _ = stop_tx.send(());
    let closing = registry.clone();
    tokio::task::spawn_blocking(move || closing.close_all()).await?;
    let _ = grpc_task.await;
    let _ = http_task.await;
    Ok(())
}

/// Off the request path, every second: idle sessions expire; every minute: old
/// recordings go (retention policy).
async fn housekeeping(registry: Arc<Registry>) {
    let mut tick = tokio::time::interval(std::time::Duration::from_secs(1));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut ticks: u64 = 0;
    loop {
        tick.tick().await;
        registry.expire_idle().await;
        if ticks % 60 == 0 {
            let dir = registry.config.recordings_dir.clone();
            let policy = registry.config.recordings.clone();
            let live: Vec<String> = registry.list().iter().map(|s| s.id.clone()).collect();
            match tokio::task::spawn_blocking(move || crate::session::retention::sweep(&dir, &policy, &live, std::time::SystemTime::now())).await {
                Ok(Ok(removed)) if !removed.is_empty() => tracing::info!(count = removed.len(), "recordings removed by the retention policy"),
                Ok(Err(e)) => tracing::warn!("recording retention: {e}"),
                _ => {}
            }
        }
        ticks += 1;
    }
}

async fn shutdown_signal() {
    let ctrl_c = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()).expect("a SIGTERM handler");
        tokio::select! {
            _ = ctrl_c => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    {
        let _ = ctrl_c.await;
    }
}
