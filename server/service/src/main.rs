//! `cutsim-server`: the cutsim server binary.
//!
//! - `cutsim-server [serve] [--grpc-addr A] [--http-addr A] [--scene NAME|PATH] [--config FILE]`
//!   serves sessions over gRPC and the viewer over HTTP/WebSocket, with one session open
//!   on the scene (the default subcommand).
//! - `cutsim-server run SCENE [--steps N] [--script SCRIPT.json] [--json]` runs a scene
//!   headless in lockstep and prints a report.
//! - `cutsim-server replay RECORDING.jsonl [--json]` replays a session recording and checks
//!   its state-hash checkpoints.
//! - `cutsim-server scene-schema` prints the JSON Schema of scene files.

mod auth;
mod config;
mod convert;
mod error;
mod grpc;
mod headless;
mod http;
mod metrics;
mod priority;
mod rate;
mod serve;
mod session;
mod tls;
mod ws;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};

#[derive(Parser)]
#[command(name = "cutsim-server", version, about = "Soft-tissue cutting simulator server")]
struct Cli {
    /// Directory of bundled scenes (repeatable; default: $CUTSIM_SCENES_DIR, else the
    /// repository's server/scenes).
    #[arg(long = "scenes-dir", global = true)]
    scenes_dir: Vec<PathBuf>,
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// Serve sessions (gRPC) and the viewer (HTTP, WebSocket). The default.
    Serve(ServeArgs),
    /// Run a scene headless in lockstep (as fast as the CPU allows) and print a report.
    Run(headless::RunArgs),
    /// Replay a session recording and check its state-hash checkpoints.
    Replay(ReplayArgs),
    /// Print the JSON Schema of scene files.
    SceneSchema,
    /// Ask a running server's gRPC health service whether it is serving (exit 0) or not
    /// (exit 1): the container's HEALTHCHECK and a probe for orchestrators without gRPC probes.
    Health(HealthArgs),
}

#[derive(Args)]
struct HealthArgs {
    /// The server's gRPC address.
    #[arg(long, default_value = "127.0.0.1:50051")]
    grpc_addr: SocketAddr,
    /// Give up after this many seconds.
    #[arg(long, default_value_t = 3.0)]
    timeout_s: f64,
    /// Ask over TLS, trusting this PEM CA certificate (a server started with --tls-cert).
    #[arg(long)]
    tls_ca: Option<PathBuf>,
    /// With --tls-ca: the name the server's certificate must carry, when it is not the
    /// address dialled (a probe inside the pod dials 127.0.0.1; the certificate names the
    /// public host).
    #[arg(long, requires = "tls_ca")]
    tls_domain: Option<String>,
}

#[derive(Args, Default)]
struct ServeArgs {
    /// gRPC address (port 0: any free port, printed at start).
    #[arg(long)]
    grpc_addr: Option<SocketAddr>,
    /// HTTP/WebSocket address (port 0: any free port, printed at start).
    #[arg(long)]
    http_addr: Option<SocketAddr>,
    /// Scene of the session opened at start (bundled name or path).
    #[arg(long, default_value = "skin-patch")]
    scene: String,
    /// Open no session at start.
    #[arg(long)]
    no_session: bool,
    /// JSON config file (docs/server.md); flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Where session recordings are written.
    #[arg(long)]
    recordings_dir: Option<PathBuf>,
    /// PEM certificate chain: serve gRPC and HTTP/WebSocket over TLS (with --tls-key).
    #[arg(long, requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// PEM private key of --tls-cert.
    #[arg(long, requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// With TLS: the operators' CA (PEM). A client certificate it signed makes its
    /// holder an operator.
    #[arg(long, requires = "tls_cert")]
    tls_client_ca: Option<PathBuf>,
    /// Development mode: every caller on loopback is an operator (no operator token
    /// needed). Refused unless both listeners are on loopback.
    #[arg(long)]
    dev: bool,
}

#[derive(Args)]
struct ReplayArgs {
    /// A recording written by `cutsim-server serve` (recordings/<session>.jsonl).
    recording: PathBuf,
    /// Print the report as one JSON object.
    #[arg(long)]
    json: bool,
}

/// Where bundled scenes are looked up: the given directories, else $CUTSIM_SCENES_DIR,
/// else the repository's server/scenes.
pub fn scene_dirs(given: &[PathBuf]) -> Vec<PathBuf> {
    if !given.is_empty() {
        return given.to_vec();
    }
    if let Some(dir) = std::env::var_os("CUTSIM_SCENES_DIR") {
        return std::env::split_paths(&dir).collect();
    }
    vec![PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../scenes"))]
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let dirs = scene_dirs(&cli.scenes_dir);
    match cli.command.unwrap_or(Command::Serve(ServeArgs { scene: "skin-patch".into(), ..Default::default() })) {
        Command::Run(args) => headless::run(&args, &dirs),
        Command::SceneSchema => {
            println!("{}", serde_json::to_string_pretty(&cutsim_sim::scene::json_schema()).expect("schema is JSON"));
            ExitCode::SUCCESS
        }
        Command::Replay(args) => replay(&args),
        Command::Health(args) => health(&args),
        Command::Serve(args) => serve(args, dirs, !cli.scenes_dir.is_empty()),
    }
}

fn serve(args: ServeArgs, dirs: Vec<PathBuf>, dirs_given: bool) -> ExitCode {
    // A recording that grows past the file-size limit must fail its write (EFBIG, counted
    // and reported like a full disk), not kill every session with SIGXFSZ.
    #[cfg(unix)]
    // SAFETY: setting a signal's disposition to "ignore" at start, before any thread exists.
    unsafe {
        libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
    }
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        .init();
    let mut config = match &args.config {
        Some(path) => match config::ServerConfig::load(path) {
            Ok(c) => c,
            Err(e) => {
                eprintln!("error: {e}");
                return ExitCode::from(2);
            }
        },
        None => config::ServerConfig::default(),
    };
    if dirs_given || args.config.is_none() {
        config.scene_dirs = dirs;
    }
    if let Some(a) = args.grpc_addr {
        config.grpc_addr = a;
    }
    if let Some(a) = args.http_addr {
        config.http_addr = a;
    }
    if let Some(d) = args.recordings_dir {
        config.recordings_dir = d;
    }
    if let (Some(cert_path), Some(key_path)) = (args.tls_cert, args.tls_key) {
        config.tls = Some(tls::TlsConfig { cert_path, key_path, client_ca_path: args.tls_client_ca });
    }
    if args.dev {
        config.development_mode = true;
    }
    let first = (!args.no_session).then_some(args.scene);
    // The models' worker threads (a multirate deformation step, a preconditioner rebuilt
    // after a cut) run below everything with a deadline (see `priority`).
    cutsim_sim::solver::background::set_worker_setup(priority::yield_to_real_time);
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().expect("a tokio runtime");
    // The HTTP side (viewers, REST, the viewer's files) on a runtime of its own, below the
    // haptic path (see `priority`).
    let http_runtime = tokio::runtime::Builder::new_multi_thread()
        .thread_name("http")
        .on_thread_start(priority::below_haptics)
        .enable_all()
        .build()
        .expect("a tokio runtime for HTTP");
    match runtime.block_on(serve::serve(config, first, http_runtime.handle().clone())) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}

fn health(args: &HealthArgs) -> ExitCode {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().expect("a tokio runtime");
    let timeout = std::time::Duration::from_secs_f64(args.timeout_s.clamp(0.1, 600.0));
    let url = format!("{}://{}", if args.tls_ca.is_some() { "https" } else { "http" }, args.grpc_addr);
    let check = async {
        let channel = cutsim_proto::endpoint_for_name(&url, args.tls_ca.as_deref(), args.tls_domain.as_deref())?.connect_timeout(timeout).connect().await?;
        let reply = HealthClient::new(channel).check(HealthCheckRequest { service: String::new() }).await?;
        Ok::<_, Box<dyn std::error::Error>>(reply.into_inner().status)
    };
    match runtime.block_on(async { tokio::time::timeout(timeout, check).await }) {
        Ok(Ok(status)) if status == ServingStatus::Serving as i32 => {
            println!("{url}: serving");
            ExitCode::SUCCESS
        }
        Ok(Ok(status)) => {
            println!("{url}: not serving (status {status})");
            ExitCode::from(1)
        }
        Ok(Err(e)) => {
            eprintln!("{url}: no answer from the gRPC health service: {e}");
            ExitCode::from(1)
        }
        Err(_) => {
            eprintln!("{url}: no answer within {} s", args.timeout_s);
            ExitCode::from(1)
        }
    }
}

fn replay(args: &ReplayArgs) -> ExitCode {
    match session::recording::replay(&args.recording) {
        Ok(report) => {
            if args.json {
                println!("{}", serde_json::to_string(&report).expect("report is JSON"));
            } else {
                println!("recording        {}", report.recording);
                println!("session          {} (scene {})", report.session, report.scene);
                println!("steps replayed   {} ({} resets, {} commands)", report.steps, report.resets, report.commands);
                if !report.build.is_empty() {
                    println!("recorded by      {}", report.build);
                }
                println!(
                    "checkpoints      {} verified (at least {} expected), {} mismatched",
                    report.checkpoints_verified,
                    report.checkpoints_expected,
                    report.checkpoint_mismatches.len()
                );
                if let Some(failure) = &report.failure {
                    println!("failed           {failure}");
                }
                for (step, recorded, replayed) in &report.checkpoint_mismatches {
                    println!("  step {step}: recorded {recorded}, replayed {replayed}");
                }
                if report.lost_events > 0 {
                    println!("lost events      {} (the recording is incomplete; replay cannot be exact past them)", report.lost_events);
                }
                println!("ended cleanly    {}", if report.ended_cleanly { "yes" } else { "no (the server stopped without closing the session)" });
                println!("final            step {}, state_hash {}", report.final_step, report.final_state_hash);
                println!("result           {}", if report.passed { "PASS" } else { "FAIL" });
            }
            if report.passed { ExitCode::SUCCESS } else { ExitCode::from(1) }
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}
