//! `cut-bot`: the tool CI pipelines use to check a scene and the simulator.
//!
//! - `cut-bot run SCRIPT.json [--server URL] [--session ID --token T] [--scene NAME|PATH]
//!   [--report out.json] [--junit out.xml]` runs a cut script in lockstep on a server and
//!   exits 0 only when every expectation holds (1: an expectation failed; 2: an error —
//!   unreachable server, unknown scene, bad script).
//! - `cut-bot record RECORDING.jsonl [-o SCRIPT.json]` turns a recorded session into a
//!   script, so that a trainee's session becomes a regression test.
//!
//! It speaks only the gRPC API of proto/cutsim.proto.

mod junit;
mod record;

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{Context, anyhow, bail};
use clap::{Parser, Subcommand};
use cutsim_proto::v1 as pb;
use cutsim_proto::v1::scripts_client::ScriptsClient;
use cutsim_proto::v1::sessions_client::SessionsClient;
use tonic::transport::Channel;

#[derive(Parser)]
#[command(name = "cut-bot", version, about = "Scripted cuts against cutsim-server, for CI")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run a cut script and check its expectations.
    Run(RunArgs),
    /// Turn a session recording into a cut script (a regression test).
    Record(record::RecordArgs),
}

#[derive(clap::Args)]
struct RunArgs {
    /// The cut script (docs/cut-script.md).
    script: PathBuf,
    /// The server's gRPC address.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    server: String,
    /// PEM CA certificate to trust for an https:// server (besides the system's roots).
    #[arg(long)]
    tls_ca: Option<PathBuf>,
    /// An operator token: creating a session needs one (default: $CUTSIM_OPERATOR_TOKEN).
    #[arg(long, env = "CUTSIM_OPERATOR_TOKEN", hide_env_values = true)]
    operator_token: Option<String>,
    /// Run on this existing session (needs its control token) instead of a new one.
    #[arg(long, requires = "token")]
    session: Option<String>,
    /// The session's control token (with --session).
    #[arg(long)]
    token: Option<String>,
    /// Scene to create the session from (bundled name or a scene file); default: the
    /// script's `scene`.
    #[arg(long, conflicts_with = "session")]
    scene: Option<String>,
    /// Write the report as JSON here.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Write a JUnit XML file here (one test case per expectation).
    #[arg(long)]
    junit: Option<PathBuf>,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::Record(args) => match record::run(&args) {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("error: {e:#}");
                ExitCode::from(2)
            }
        },
        Command::Run(args) => {
            let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().expect("a tokio runtime");
            match runtime.block_on(run(&args)) {
                Ok(true) => ExitCode::SUCCESS,
                Ok(false) => ExitCode::from(1),
                Err(e) => {
                    eprintln!("error: {e:#}");
                    ExitCode::from(2)
                }
            }
        }
    }
}

/// Where the session's scene comes from.
enum SceneSource {
    Bundled(String),
    File(PathBuf),
}

fn scene_source(given: &str, relative_to: &Path) -> SceneSource {
    if given.ends_with(".json") || given.contains('/') {
        let path = Path::new(given);
        SceneSource::File(if path.is_absolute() { path.to_path_buf() } else { relative_to.join(path) })
    } else {
        SceneSource::Bundled(given.to_owned())
    }
}

/// Runs the script; Ok(passed).
async fn run(args: &RunArgs) -> anyhow::Result<bool> {
    let script_text = std::fs::read_to_string(&args.script).with_context(|| format!("cannot read the script {}", args.script.display()))?;
    let script: serde_json::Value = serde_json::from_str(&script_text).map_err(|e| anyhow!("{}: not JSON: {e}", args.script.display()))?;
    let name = args.script.file_stem().and_then(|s| s.to_str()).unwrap_or("script").to_owned();
    let channel = connect(&args.server, args.tls_ca.as_deref()).await?;
    let mut sessions = SessionsClient::new(channel.clone());

    let (session_id, token, created) = match (&args.session, &args.token) {
        (Some(id), Some(token)) => (id.clone(), token.clone(), false),
        _ => {
            let scene = match (&args.scene, script.get("scene")) {
                (Some(s), _) => s.clone(),
                (None, Some(serde_json::Value::String(s))) => s.clone(),
                (None, Some(other)) => bail!("{}: scene: expected a scene name or path (a string), got {other}", args.script.display()),
                (None, None) => bail!("{}: the script names no scene; give --scene NAME or --session ID", args.script.display()),
            };
            let base = args.script.parent().unwrap_or(Path::new("."));
            let request = match scene_source(&scene, base) {
                SceneSource::Bundled(name) => pb::create_session_request::Scene::SceneName(name),
                SceneSource::File(path) => pb::create_session_request::Scene::SceneJson(
                    std::fs::read_to_string(&path).with_context(|| format!("cannot read the scene file {}", path.display()))?,
                ),
            };
            let Some(operator) = &args.operator_token else {
                bail!("creating a session needs an operator token: give --operator-token or set CUTSIM_OPERATOR_TOKEN (or run on an existing session with --session ID --token CONTROL)");
            };
            let mut create = tonic::Request::new(pb::CreateSessionRequest { scene: Some(request), mode: pb::SessionMode::Lockstep as i32, label: format!("cut-bot {name}") });
            create.metadata_mut().insert("cutsim-token", operator.parse().map_err(|_| anyhow!("the operator token must be printable ASCII"))?);
            let created = sessions
                .create_session(create)
                .await
                .map_err(|s| anyhow!("cannot create a session on scene {scene:?}: {}", s.message()))?
                .into_inner();
            let id = created.session.map(|s| s.id).ok_or_else(|| anyhow!("the server answered without a session"))?;
            (id, created.control_token, true)
        }
    };

    let outcome = run_on_session(channel, &session_id, &token, &script_text).await;
    if created {
        let mut request = tonic::Request::new(pb::CloseSessionRequest { session_id: session_id.clone() });
        request.metadata_mut().insert("cutsim-token", token.parse()?);
        let _ = sessions.close_session(request).await;
    }
    let (report, elapsed) = outcome?;
    print_report(&name, &report);
    if let Some(path) = &args.report {
        std::fs::write(path, &report.report_json).with_context(|| format!("cannot write the report {}", path.display()))?;
    }
    if let Some(path) = &args.junit {
        std::fs::write(path, junit::render(&name, &report, elapsed)).with_context(|| format!("cannot write the JUnit file {}", path.display()))?;
    }
    Ok(report.passed)
}

async fn connect(url: &str, ca: Option<&Path>) -> anyhow::Result<Channel> {
    let endpoint = cutsim_proto::endpoint(url, ca).map_err(|e| anyhow!(e))?;
    endpoint
        .connect_timeout(Duration::from_secs(5))
        .connect()
        .await
        .map_err(|e| anyhow!("cannot reach the server at {url}: {e} (is cutsim-server running?)"))
}

async fn run_on_session(channel: Channel, session: &str, token: &str, script: &str) -> anyhow::Result<(pb::ScriptReport, Duration)> {
    let mut request = tonic::Request::new(pb::RunScriptRequest { session_id: session.to_owned(), script_json: script.to_owned(), progress_every_steps: 0 });
    request.metadata_mut().insert("cutsim-token", token.parse().map_err(|_| anyhow!("the token has characters a token cannot have"))?);
    let started = Instant::now();
    let mut events = ScriptsClient::new(channel)
        .run_script(request)
        .await
        .map_err(|s| anyhow!("the server refused the script: {}", s.message()))?
        .into_inner();
    let progress = Progress::new();
    let mut report = None;
    while let Some(event) = events.message().await.map_err(|s| anyhow!("the script failed: {}", s.message()))? {
        match event.event {
            Some(pb::script_event::Event::Progress(p)) => progress.show(&p),
            Some(pb::script_event::Event::Report(r)) => report = Some(r),
            None => {}
        }
    }
    progress.finish();
    Ok((report.ok_or_else(|| anyhow!("the server ended the script without a report"))?, started.elapsed()))
}

/// A progress bar on a terminal, plain lines otherwise.
struct Progress {
    bar: Option<indicatif::ProgressBar>,
}

impl Progress {
    fn new() -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = indicatif::ProgressBar::new(0);
            bar.set_style(
                indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} steps {msg}").expect("a valid template"),
            );
            bar
        });
        Self { bar }
    }

    fn show(&self, p: &pb::ScriptProgress) {
        match &self.bar {
            Some(bar) => {
                bar.set_length(p.total_steps);
                bar.set_position(p.step);
                bar.set_message(format!("cuts {}, max force {:.3} N", p.cuts, p.max_tool_force_n));
            }
            None => eprintln!("progress: step {}/{}, cuts {}, max force {:.3} N", p.step, p.total_steps, p.cuts, p.max_tool_force_n),
        }
    }

    fn finish(&self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }
}

/// The task's metrics, where the scene has a task.
fn print_assessment(a: &pb::Assessment) {
    let Some(passed) = a.passed else { return };
    let optional = |v: Option<f64>, unit: &str| v.map_or("n/a".to_owned(), |v| format!("{v:.2}{unit}"));
    println!("task             {}", if a.task.is_empty() { "(no description)" } else { &a.task });
    println!(
        "  score {} · coverage {} · deviation RMS {} (max {}) · time {} · strokes {} · path {:.1} mm · peak force {:.2} N",
        optional(a.score, ""),
        optional(a.coverage.map(|c| c * 100.0), " %"),
        optional(a.deviation_rms_mm, " mm"),
        optional(a.deviation_max_mm, " mm"),
        optional(a.time_to_complete_s, " s"),
        a.strokes,
        a.path_length_mm,
        a.peak_force_n
    );
    if a.peak_grip_force_n > 0.0 {
        println!("  peak grip {:.2} N{}", a.peak_grip_force_n, a.time_above_grip_limit_s.map_or(String::new(), |t| format!(" ({t:.3} s above the grip limit)")));
    }
    println!("  task {}", if passed { "passed".to_owned() } else { format!("failed: {}", a.failures.join("; ")) });
}

fn print_report(name: &str, r: &pb::ScriptReport) {
    println!("script           {name} on scene {} ({})", r.scene, r.model);
    println!("steps            {} ({:.3} s simulated, {:.0} steps/s)", r.steps, r.simulated_time_s, r.steps_per_second);
    println!("cuts             {} ({} updates, {} fallbacks)", r.cuts, r.cut_updates, r.reconstruction_fallbacks);
    for f in &r.fallbacks {
        println!("  fallback at step {}: {}", f.step, f.reason);
    }
    if let Some(uncut) = r.counters.as_ref().map(|c| c.uncut_last_pieces).filter(|&n| n > 0) {
        println!("  last pieces left uncut (the incision ends short of where the blade left): {uncut}");
    }
    println!("removed elements {}", r.removed_elements);
    println!("incision length  {:.2} mm", r.incision_length_m * 1e3);
    println!("pieces           {}", r.pieces);
    println!("max tool force   {:.4} N", r.max_tool_force_n);
    for t in &r.tools {
        if t.grasping_s > 0.0 {
            println!("  {:<14} {:.4} N, grasping {:.3} s, pinching at most {:.2} N", t.name, t.max_force_n, t.grasping_s, t.max_jaws_force_n);
        } else {
            println!("  {:<14} {:.4} N", t.name, t.max_force_n);
        }
    }
    println!("state_hash       {}", r.state_hash);
    if let Some(a) = &r.assessment {
        print_assessment(a);
    }
    for e in &r.expectations {
        if e.passed {
            println!("PASS {:<26} {}", e.name, e.expected);
        } else {
            println!("FAIL {:<26} expected {}, got {}", e.name, e.expected, e.actual);
        }
    }
    let failed = r.expectations.iter().filter(|e| !e.passed).count();
    println!("result           {} ({} of {} expectations hold)", if r.passed { "PASS" } else { "FAIL" }, r.expectations.len() - failed, r.expectations.len());
}
