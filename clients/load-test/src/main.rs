//! `cutsim-load`: the load and fault test of cutsim-server, on loopback, bounded in count
//! and time (docs/reliability.md is its report).
//!
//! It starts the real server binary, opens N real-time sessions, each with a haptic
//! client streaming 1 kHz tool commands (a scalpel cutting lanes) and M viewers keeping a
//! replica of the surface, while a bot runs the example cut scripts in lockstep sessions.
//! Meanwhile the fault cases run: a viewer that stops reading, garbage clients, a haptic
//! client that vanishes mid-cut; afterwards the server is SIGKILLed and restarted (the
//! sessions replayed from their recordings to the same hash), and a server whose disk is
//! full keeps its session running and reports the loss. With `--capacity`, it also finds
//! how many real-time sessions this machine holds.

mod faults;
mod haptic;
mod report;
mod server;

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{Context, anyhow, bail};
use clap::Parser;
use cutsim_load::viewer::Viewer;
use cutsim_proto::v1 as pb;
use serde::Serialize;

use crate::faults::FaultOutcome;
use crate::haptic::{HapticStats, HapticTarget, Trajectory};
use crate::server::{Created, ServerProcess};

#[derive(Parser, Clone)]
#[command(name = "cutsim-load", version, about = "Load and fault test of cutsim-server on loopback")]
struct Args {
    /// Real-time sessions, each with one haptic client.
    #[arg(long, default_value_t = 2)]
    sessions: usize,
    /// Viewers per session.
    #[arg(long, default_value_t = 2)]
    viewers: usize,
    /// How long the load runs, s.
    #[arg(long, default_value_t = 20.0)]
    seconds: f64,
    /// Scene of the real-time sessions: a bundled scene's name, or a scene file (*.json) sent inline.
    #[arg(long, default_value = "skin-patch")]
    scene: String,
    /// The cutsim-server binary (default: beside this one).
    #[arg(long)]
    server_bin: Option<PathBuf>,
    /// Cut scripts the bot runs (default: clients/cut-bot/examples/skin-patch-*.json).
    #[arg(long)]
    script: Vec<PathBuf>,
    /// Skip the fault cases (load only).
    #[arg(long)]
    no_faults: bool,
    /// Also measure how many real-time sessions this machine holds: 1, 2, … up to this
    /// many sessions, `--capacity-seconds` each.
    #[arg(long)]
    capacity: Option<usize>,
    #[arg(long, default_value_t = 8.0)]
    capacity_seconds: f64,
    /// Write the report (Markdown) here, e.g. docs/reliability.md.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Write the measurements as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
}

/// One real-time session's figures at the end of the load.
#[derive(Serialize, Debug)]
pub struct SessionFigures {
    pub id: String,
    pub steps: u64,
    pub achieved_rate_hz: f64,
    pub step_p50_us: f64,
    pub step_p99_us: f64,
    pub step_max_us: f64,
    pub missed_deadlines: u64,
    pub cuts: u64,
    pub commands_sent: u64,
    pub commands_dropped: u64,
    pub feedback: u64,
    pub round_trip_p50_us: f64,
    pub round_trip_p99_us: f64,
    pub viewers: usize,
    pub viewers_matched: usize,
    pub viewer_frames: u64,
    pub viewer_errors: Vec<String>,
    pub haptic_errors: Vec<String>,
    pub server_surface_hash: String,
}

#[derive(Serialize, Debug)]
pub struct BotRun {
    pub script: String,
    pub passed: bool,
    pub steps: u64,
    pub wall_s: f64,
    pub detail: String,
}

#[derive(Serialize, Debug)]
pub struct LoadResult {
    pub sessions: Vec<SessionFigures>,
    pub bot: Vec<BotRun>,
    pub faults: Vec<FaultOutcome>,
}

#[derive(Serialize, Debug)]
pub struct CapacityRow {
    pub sessions: usize,
    pub min_rate_hz: f64,
    pub worst_p99_us: f64,
    pub missed_fraction: f64,
    pub holds: bool,
}

#[derive(Serialize, Debug)]
pub struct Report {
    pub command: String,
    pub machine: String,
    pub scene: String,
    pub seconds: f64,
    pub viewers_per_session: usize,
    pub load: LoadResult,
    pub capacity: Vec<CapacityRow>,
    pub failures: Vec<String>,
}

fn percentile(values: &mut [u32], p: f64) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    values.sort_unstable();
    let k = ((values.len() as f64 - 1.0) * p).round() as usize;
    f64::from(values[k])
}

fn progress(message: &str) {
    eprintln!("[cutsim-load] {message}");
}

/// A viewer task: reads until told to stop, then hands the viewer back.
async fn watch(http: String, session: String, token: String, stop: tokio::sync::watch::Receiver<bool>) -> anyhow::Result<Viewer> {
    let mut viewer = Viewer::connect(&http, &session, &token).await.map_err(|e| anyhow!("viewer of {session}: {e}"))?;
    while !*stop.borrow() {
        viewer.pump_until(Duration::from_millis(50), |_| false).await;
        if viewer.closed.is_some() {
            bail!("viewer of {session} closed by the server: {:?}", viewer.closed);
        }
    }
    Ok(viewer)
}

/// The server's surface hash, and whether every viewer reaches it. Real-time tissue may
/// still settle after the tool left, so the server is asked again until the viewers and
/// it agree (or 20 tries).
async fn viewers_reach_the_server(server: &ServerProcess, session: &Created, viewers: &mut [Viewer]) -> anyhow::Result<(String, usize)> {
    let mut best = (String::new(), 0);
    for _ in 0..20 {
        let snapshot = server.sessions().await?.get_snapshot(server::authed(pb::GetSnapshotRequest { session_id: session.id.clone() }, &session.observe)?).await?.into_inner();
        let target = snapshot.surface_hash;
        let mut matched = 0;
        for v in viewers.iter_mut() {
            if v.pump_until(Duration::from_millis(500), |v| v.surface_hash().as_deref() == Some(target.as_str())).await {
                matched += 1;
            }
        }
        if matched >= best.1 {
            best = (target, matched);
        }
        if matched == viewers.len() {
            break;
        }
    }
    Ok(best)
}

/// The bot: runs each script in a lockstep session of its own, in turn, until `until`.
async fn bot(server_grpc: String, scripts: Vec<PathBuf>, until: Instant) -> Vec<BotRun> {
    let mut runs = Vec::new();
    let mut k = 0;
    while Instant::now() < until && !scripts.is_empty() {
        let path = &scripts[k % scripts.len()];
        k += 1;
        let name = path.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let started = Instant::now();
        let outcome = run_script(&server_grpc, path).await;
        let wall_s = started.elapsed().as_secs_f64();
        runs.push(match outcome {
            Ok(r) => BotRun { script: name, passed: r.passed, steps: r.steps, wall_s, detail: if r.passed { String::new() } else { r.report_json } },
            Err(e) => BotRun { script: name, passed: false, steps: 0, wall_s, detail: format!("{e:#}") },
        });
    }
    runs
}

async fn run_script(grpc: &str, path: &Path) -> anyhow::Result<pb::ScriptReport> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let script: serde_json::Value = serde_json::from_str(&text)?;
    let scene = script["scene"].as_str().ok_or_else(|| anyhow!("{} names no scene", path.display()))?;
    let channel = tonic::transport::Channel::from_shared(format!("http://{grpc}"))?.connect().await?;
    let created = cutsim_proto::v1::sessions_client::SessionsClient::new(channel.clone())
        .create_session(server::authed(
            pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneName(scene.into())), mode: pb::SessionMode::Lockstep as i32, label: "cutsim-load bot".into() },
            server::OPERATOR_TOKEN,
        )?)
        .await?
        .into_inner();
    let id = created.session.map(|s| s.id).unwrap_or_default();
    let request = server::authed(pb::RunScriptRequest { session_id: id.clone(), script_json: text, progress_every_steps: 0 }, &created.control_token)?;
    let mut events = cutsim_proto::v1::scripts_client::ScriptsClient::new(channel.clone()).run_script(request).await?.into_inner();
    let mut report = None;
    while let Some(event) = events.message().await? {
        if let Some(pb::script_event::Event::Report(r)) = event.event {
            report = Some(r);
        }
    }
    let close = server::authed(pb::CloseSessionRequest { session_id: id }, &created.control_token)?;
    let _ = cutsim_proto::v1::sessions_client::SessionsClient::new(channel).close_session(close).await;
    report.ok_or_else(|| anyhow!("the script ended without a report"))
}

struct LoadPlan {
    sessions: usize,
    viewers: usize,
    seconds: f64,
    scene: String,
    scripts: Vec<PathBuf>,
    faults: bool,
}

/// Runs the load (and the faults that happen during it) on `server`; returns the
/// sessions' figures, the bot's runs and the fault cases' outcomes. (The kill-and-restart
/// case after it runs on a session of its own: `faults::session_past_a_checkpoint`.)
async fn load(server: &ServerProcess, plan: &LoadPlan) -> anyhow::Result<(Vec<SessionFigures>, Vec<BotRun>, Vec<FaultOutcome>)> {
    let mut sessions = Vec::new();
    for k in 0..plan.sessions {
        sessions.push(server::create(server, &plan.scene, pb::SessionMode::Realtime, &format!("cutsim-load {k}")).await?);
    }
    let start = Instant::now();
    let until = start + Duration::from_secs_f64(plan.seconds);
    let at = |fraction: f64| start + Duration::from_secs_f64(plan.seconds * fraction);
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let mut viewer_tasks = Vec::new();
    let mut haptic_tasks = Vec::new();
    for (k, s) in sessions.iter().enumerate() {
        let tasks: Vec<_> = (0..plan.viewers).map(|_| tokio::spawn(watch(server.http.clone(), s.id.clone(), s.observe.clone(), stop_rx.clone()))).collect();
        viewer_tasks.push(tasks);
        let target = HapticTarget { grpc: server.grpc.clone(), session: s.id.clone(), token: s.control.clone(), trajectory: Trajectory::from_info(&s.info) };
        let vanish = (plan.faults && k + 1 == plan.sessions).then(|| at(0.6));
        haptic_tasks.push(tokio::spawn(haptic::run(target, until, vanish)));
    }
    let bot_task = tokio::spawn(bot(server.grpc.clone(), plan.scripts.clone(), until));

    let mut fault_outcomes = Vec::new();
    if plan.faults {
        tokio::time::sleep_until(at(0.2).into()).await;
        progress("fault: a viewer that stops reading");
        let regular = plan.viewers as u32;
        let stall = faults::stalled_viewer(server, &sessions[0], regular, Duration::from_secs_f64((plan.seconds * 0.75).max(15.0)));
        let garbage = async {
            tokio::time::sleep_until(at(0.4).into()).await;
            progress("fault: garbage clients");
            faults::garbage_clients(server, &sessions[0]).await
        };
        let last = &sessions[plan.sessions - 1];
        let vanish = async {
            progress("fault: a haptic client vanishing mid-cut (at 60 %)");
            faults::vanishing_haptic_client(server, last, at(0.6)).await
        };
        let (stall, garbage, vanish) = tokio::join!(stall, garbage, vanish);
        fault_outcomes.push(stall);
        fault_outcomes.extend(garbage);
        fault_outcomes.push(vanish);
    }

    let mut haptic_stats: Vec<HapticStats> = Vec::new();
    for task in haptic_tasks {
        haptic_stats.push(task.await?);
    }
    progress("load over: the tools left; checking the viewers against the server");
    let _ = stop_tx.send(true);
    let mut figures = Vec::new();
    for ((s, tasks), mut stats) in sessions.iter().zip(viewer_tasks).zip(haptic_stats) {
        let mut viewers = Vec::new();
        let mut viewer_errors = Vec::new();
        for task in tasks {
            match task.await? {
                Ok(v) => viewers.push(v),
                Err(e) => viewer_errors.push(format!("{e:#}")),
            }
        }
        let (hash, matched) = viewers_reach_the_server(server, s, &mut viewers).await?;
        viewer_errors.extend(viewers.iter().flat_map(|v| v.errors.iter().cloned()));
        let info = server::info(server, &s.id, &s.observe, false).await?;
        let step = info.stats.clone().unwrap_or_default();
        figures.push(SessionFigures {
            id: s.id.clone(),
            steps: info.step,
            achieved_rate_hz: step.achieved_rate_hz,
            step_p50_us: step.p50_us,
            step_p99_us: step.p99_us,
            step_max_us: step.max_us,
            missed_deadlines: step.missed_deadlines,
            cuts: info.counters.map_or(0, |c| c.cuts),
            commands_sent: stats.commands_sent,
            commands_dropped: stats.commands_dropped,
            feedback: stats.feedback,
            round_trip_p50_us: percentile(&mut stats.round_trips_us, 0.5),
            round_trip_p99_us: percentile(&mut stats.round_trips_us, 0.99),
            viewers: plan.viewers,
            viewers_matched: matched,
            viewer_frames: viewers.iter().map(|v| v.frames).sum(),
            viewer_errors,
            haptic_errors: stats.errors,
            server_surface_hash: hash,
        });
    }
    // The load is over and its figures are taken: the real-time sessions are closed, so
    // that the bot's script in flight gets the cores. A lockstep script runs in the idle
    // class, and beside two real-time sessions that saturate a 2-core machine it had
    // almost none: this phase of CI waited about ten minutes for it.
    for s in &sessions {
        let close = server::authed(pb::CloseSessionRequest { session_id: s.id.clone() }, &s.control)?;
        server.sessions().await?.close_session(close).await.map_err(|e| anyhow!("closing session {} after the load: {}", s.id, e.message()))?;
    }
    let bot_runs = bot_task.await?;
    Ok((figures, bot_runs, fault_outcomes))
}

fn server_binary(given: Option<&Path>) -> anyhow::Result<PathBuf> {
    let path = match given {
        Some(p) => p.to_path_buf(),
        None => std::env::current_exe()?.with_file_name("cutsim-server"),
    };
    if !path.is_file() {
        bail!("{} not found: build it (cargo build [--release] -p cutsim-server) or give --server-bin", path.display());
    }
    Ok(path)
}

fn default_scripts() -> Vec<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../cut-bot/examples");
    let mut scripts: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map(|entries| entries.filter_map(Result::ok).map(|e| e.path()).filter(|p| p.file_name().is_some_and(|n| n.to_string_lossy().starts_with("skin-patch-"))).collect())
        .unwrap_or_default();
    scripts.sort();
    scripts
}

/// A temporary directory, removed at the end.
struct Scratch(PathBuf);

impl Scratch {
    fn new() -> anyhow::Result<Self> {
        let dir = std::env::temp_dir().join(format!("cutsim-load-{}", std::process::id()));
        std::fs::create_dir_all(&dir)?;
        Ok(Self(dir))
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

async fn run(args: &Args) -> anyhow::Result<Report> {
    if args.sessions == 0 || !(args.seconds >= 2.0) {
        bail!("give --sessions ≥ 1 and --seconds ≥ 2");
    }
    let binary = server_binary(args.server_bin.as_deref())?;
    let scratch = Scratch::new()?;
    let config = server::write_config(&scratch.0)?;
    let recordings = scratch.0.join("recordings");
    let scripts = if args.script.is_empty() { default_scripts() } else { args.script.clone() };
    let plan = LoadPlan { sessions: args.sessions, viewers: args.viewers, seconds: args.seconds, scene: args.scene.clone(), scripts, faults: !args.no_faults };

    progress(&format!("{} real-time sessions of {} × {} viewers + a haptic client each, and a bot, for {} s", plan.sessions, plan.scene, plan.viewers, plan.seconds));
    let mut server = ServerProcess::start(&binary, &config, &recordings, None)?;
    let (sessions, bot, mut fault_outcomes) = load(&server, &plan).await?;
    if !server.alive() {
        bail!("the server died during the load");
    }
    if plan.faults {
        progress("fault: SIGKILL and restart");
        let checkpoints = faults::session_past_a_checkpoint(&server, &plan.scene).await?;
        tokio::time::sleep(Duration::from_millis(300)).await;
        server.kill();
        let restarted = ServerProcess::start(&binary, &config, &recordings, None)?;
        fault_outcomes.extend(faults::replay_after_kill(&binary, &restarted, &recordings, &checkpoints).await);
        drop(restarted);
        progress("fault: a full disk while recording");
        let full = scratch.0.join("full-disk");
        fault_outcomes.push(faults::disk_full(&binary, &config, &full, &plan.scene, 256 << 10).await);
    }
    drop(server);

    let mut capacity = Vec::new();
    if let Some(most) = args.capacity {
        for n in 1..=most {
            progress(&format!("capacity: {n} real-time sessions, one viewer each, {} s", args.capacity_seconds));
            let server = ServerProcess::start(&binary, &config, &scratch.0.join(format!("capacity-{n}")), None)?;
            let sweep = LoadPlan { sessions: n, viewers: 1, seconds: args.capacity_seconds, scene: args.scene.clone(), scripts: Vec::new(), faults: false };
            let (figures, _, _) = load(&server, &sweep).await?;
            let min_rate = figures.iter().map(|f| f.achieved_rate_hz).fold(f64::INFINITY, f64::min);
            let worst_p99 = figures.iter().map(|f| f.step_p99_us).fold(0.0, f64::max);
            let missed: u64 = figures.iter().map(|f| f.missed_deadlines).sum();
            let steps: u64 = figures.iter().map(|f| f.steps).sum();
            let missed_fraction = missed as f64 / steps.max(1) as f64;
            let holds = min_rate >= 990.0 && missed_fraction <= 0.01;
            capacity.push(CapacityRow { sessions: n, min_rate_hz: min_rate, worst_p99_us: worst_p99, missed_fraction, holds });
            if !holds {
                break;
            }
        }
    }

    let mut failures = Vec::new();
    for s in &sessions {
        if s.viewers_matched != s.viewers {
            failures.push(format!("session {}: {} of {} viewers ended with the server's surface hash", s.id, s.viewers_matched, s.viewers));
        }
        failures.extend(s.viewer_errors.iter().map(|e| format!("session {}: viewer: {e}", s.id)));
        failures.extend(s.haptic_errors.iter().map(|e| format!("session {}: haptic client: {e}", s.id)));
        if s.feedback == 0 {
            failures.push(format!("session {}: the haptic client got no force feedback", s.id));
        }
    }
    failures.extend(bot.iter().filter(|b| !b.passed).map(|b| format!("bot: {} failed: {}", b.script, b.detail)));
    failures.extend(fault_outcomes.iter().filter(|f| !f.passed).map(|f| format!("fault case {}: {}", f.case, f.detail)));
    let command = std::env::args().map(|a| if a.contains(' ') { format!("{a:?}") } else { a }).collect::<Vec<_>>().join(" ");
    Ok(Report {
        command,
        machine: report::machine(),
        scene: plan.scene,
        seconds: plan.seconds,
        viewers_per_session: plan.viewers,
        load: LoadResult { sessions, bot, faults: fault_outcomes },
        capacity,
        failures,
    })
}

fn main() -> ExitCode {
    let args = Args::parse();
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().expect("a tokio runtime");
    let report = match runtime.block_on(run(&args)) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: {e:#}");
            return ExitCode::from(2);
        }
    };
    let markdown = report::markdown(&report);
    print!("{markdown}");
    let written = (|| -> anyhow::Result<()> {
        if let Some(path) = &args.report {
            std::fs::write(path, &markdown).with_context(|| format!("writing {}", path.display()))?;
        }
        if let Some(path) = &args.json {
            std::fs::write(path, serde_json::to_string_pretty(&report)?).with_context(|| format!("writing {}", path.display()))?;
        }
        Ok(())
    })();
    if let Err(e) = written {
        eprintln!("error: {e:#}");
        return ExitCode::from(2);
    }
    if report.failures.is_empty() {
        ExitCode::SUCCESS
    } else {
        for f in &report.failures {
            eprintln!("FAIL {f}");
        }
        ExitCode::from(1)
    }
}

#[cfg(test)]
mod tests {
    use super::percentile;

    #[test]
    fn percentiles_of_round_trips() {
        assert_eq!(percentile(&mut [], 0.99), 0.0);
        let mut v: Vec<u32> = (1..=100).rev().collect();
        assert_eq!(percentile(&mut v, 0.5), 51.0);
        assert_eq!(percentile(&mut v, 0.99), 99.0);
        assert_eq!(percentile(&mut v, 1.0), 100.0);
    }
}
