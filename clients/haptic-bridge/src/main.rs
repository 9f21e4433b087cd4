//! `haptic-bridge`: runs beside a haptic device and joins it to a cutsim session.
//!
//! A local loop at 1 kHz, on its own thread, reads the device, maps it into the scene,
//! moves the tool proxy of the virtual coupling, renders the coupling force through the
//! force and force-rate limits, and publishes the proxy's pose; a network thread streams
//! poses to the server and keeps its newest answer. Whatever the network does (slow,
//! gone, back), the device loop keeps its rate, and the force fades to zero when answers
//! are stale. See docs/haptic-bridge.md.

mod coupling;
mod cues;
mod device;
mod limiter;
mod link;
mod local_model;
mod mapping;
mod vec;

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, anyhow, bail};
use clap::Parser;
use cutsim_proto::v1 as pb;
use serde::{Deserialize, Serialize};

use coupling::{Coupling, CouplingParams};
use device::{Device, SimDevice, Trajectory, UdpDevice};
use limiter::{Limiter, Limits};
use mapping::Workspace;
use vec::V3;

/// The shortest time a device step is taken to cover, s (a guard: ticks are scheduled
/// at least half a millisecond apart).
const MIN_TICK_S: f64 = 1e-4;

#[derive(Parser)]
#[command(name = "haptic-bridge", version, about = "Joins a haptic device to a cutsim session")]
struct Args {
    /// The server's gRPC address.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    server: String,
    /// PEM CA certificate to trust for an https:// server (besides the system's roots).
    #[arg(long)]
    tls_ca: Option<std::path::PathBuf>,
    /// The session to join.
    #[arg(long)]
    session: String,
    /// The session's control token.
    #[arg(long)]
    token: String,
    /// Which tool of the scene the device drives (index in the scene's tools).
    #[arg(long, default_value_t = 0)]
    tool: u32,
    /// `sim:press` (a probe pressing the skin), `sim:cut` (a scalpel cutting),
    /// `sim:grasp` (forceps grasping the skin and lifting it), or `udp:ADDRESS:PORT` (a
    /// vendor driver sending poses, docs/haptic-bridge.md).
    #[arg(long, default_value = "sim:press")]
    device: String,
    /// Stop after this many seconds (default: run until interrupted).
    #[arg(long)]
    duration_s: Option<f64>,
    /// Write statistics as JSON here at exit.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Write every millisecond's rendered force as CSV here (t_s, fx, fy, fz, magnitude, fresh, connected, grip_n).
    #[arg(long)]
    trace: Option<PathBuf>,
    /// JSON file with `workspace`, `coupling` and `limits` (flags override it).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Scene position of the device origin, m: x,y,z.
    #[arg(long, value_delimiter = ',', num_args = 3)]
    offset_m: Option<Vec<f64>>,
    /// Scene metres per device metre.
    #[arg(long)]
    scale: Option<f64>,
    /// Rotation from device to scene axes, unit quaternion: w,x,y,z.
    #[arg(long, value_delimiter = ',', num_args = 4)]
    rotation_wxyz: Option<Vec<f64>>,
    /// The device's rated force, N.
    #[arg(long)]
    max_force_n: Option<f64>,
    /// Training cues: a short force pulse when the trainee enters a no-go region of the
    /// session's task or goes above its force limit (off by default; docs/haptic-bridge.md).
    #[arg(long)]
    cues: bool,
    /// The largest force change per second, N/s.
    #[arg(long)]
    max_force_rate_n_per_s: Option<f64>,
    /// Answers older than this are stale, ms.
    #[arg(long)]
    stale_ms: Option<f64>,
    /// Time for the force to fade to zero when answers are stale, ms.
    #[arg(long)]
    ramp_ms: Option<f64>,
}

#[derive(Debug, Clone, Copy, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
struct Config {
    workspace: Workspace,
    coupling: CouplingParams,
    limits: Limits,
}

#[derive(Debug, Default, Serialize)]
struct Report {
    device: String,
    session: String,
    tool: u32,
    duration_s: f64,
    device_steps: u64,
    /// Steps that started more than a millisecond late (the coupling, the cues and the
    /// rate limit then cover the time that passed, not one millisecond).
    late_steps: u64,
    forces_sent: u64,
    max_force_n: f64,
    /// Largest change of the rendered force from one step to the next, N.
    max_force_step_n: f64,
    /// Largest rate of change of the rendered force, N/s: a step's change over the time
    /// it covered (the rate limit bounds this).
    max_force_rate_n_per_s: f64,
    /// Ticks with no fresh answer (stale or disconnected).
    stale_steps: u64,
    /// Ticks whose fresh answer said the tool grasps tissue (the coupling's grasp damper).
    grasping_steps: u64,
    /// The largest force sent to an analog gripper, N (the forceps' jaws pushed apart).
    max_grip_force_n: f64,
    /// The largest tissue stiffness the coupling's local model learnt, N/m.
    max_local_stiffness_n_per_m: f64,
    rtt_samples: usize,
    rtt_p50_us: u32,
    rtt_p99_us: u32,
    rtt_max_us: u32,
    reconnects: u64,
    clamped: u64,
    rate_limited: u64,
    non_finite: u64,
    /// Cue pulses played (`--cues`).
    cues: u64,
    config: Config,
    ended_by: String,
}

fn main() -> ExitCode {
    let args = Args::parse();
    match run(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}

fn load_config(args: &Args) -> anyhow::Result<Config> {
    let mut config: Config = match &args.config {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
            serde_json::from_str(&text).map_err(|e| anyhow!("{}: {e}", path.display()))?
        }
        None => Config::default(),
    };
    if let Some(o) = &args.offset_m {
        config.workspace.offset_m = [o[0], o[1], o[2]];
    }
    if let Some(s) = args.scale {
        config.workspace.scale = s;
    }
    if let Some(r) = &args.rotation_wxyz {
        config.workspace.rotation_wxyz = [r[0], r[1], r[2], r[3]];
    }
    let l = &mut config.limits;
    l.max_force_n = args.max_force_n.unwrap_or(l.max_force_n);
    l.max_force_rate_n_per_s = args.max_force_rate_n_per_s.unwrap_or(l.max_force_rate_n_per_s);
    l.stale_ms = args.stale_ms.unwrap_or(l.stale_ms);
    l.ramp_ms = args.ramp_ms.unwrap_or(l.ramp_ms);
    config.workspace.check().map_err(|e| anyhow!("workspace: {e}"))?;
    config.limits.check().map_err(|e| anyhow!("limits: {e}"))?;
    config.coupling.check().map_err(|e| anyhow!("coupling: {e}"))?;
    Ok(config)
}

fn open_device(spec: &str) -> anyhow::Result<Box<dyn Device>> {
    Ok(match spec {
        "sim" | "sim:press" => Box::new(SimDevice::new(Trajectory::Press)),
        "sim:cut" => Box::new(SimDevice::new(Trajectory::Cut)),
        "sim:grasp" => Box::new(SimDevice::new(Trajectory::Grasp)),
        other => match other.strip_prefix("udp:") {
            Some(address) => {
                let device = UdpDevice::bind(address).with_context(|| format!("cannot listen for the device on UDP {address}"))?;
                eprintln!("waiting for device poses on UDP {}", device.local_addr()?);
                Box::new(device)
            }
            None => bail!("unknown device {other:?}: use sim:press, sim:cut, sim:grasp or udp:ADDRESS:PORT"),
        },
    })
}

fn run(args: &Args) -> anyhow::Result<()> {
    let config = load_config(args)?;
    let mut device = open_device(&args.device)?;
    let server = cutsim_proto::endpoint(&args.server, args.tls_ca.as_deref()).map_err(|e| anyhow::anyhow!(e))?;
    let origin = Instant::now();
    let mut watcher = args.cues.then(|| cues::Watcher::start(server.clone(), args.session.clone(), args.token.clone()));
    let mut pulse = cues::Pulse::new(config.limits.max_force_rate_n_per_s);
    let mut link = link::Link::start(
        link::Target { server, session: args.session.clone(), token: args.token.clone(), tool: args.tool },
        origin,
    );
    let interrupted = Arc::new(AtomicBool::new(false));
    {
        let interrupted = interrupted.clone();
        let _ = ctrlc_like(move || interrupted.store(true, Ordering::Release));
    }
    let mut trace = match &args.trace {
        Some(path) => Some(std::io::BufWriter::new(std::fs::File::create(path).with_context(|| format!("cannot write {}", path.display()))?)),
        None => None,
    };
    if let Some(t) = trace.as_mut() {
        writeln!(t, "t_s,fx_n,fy_n,fz_n,magnitude_n,fresh,connected,grip_n")?;
    }

    precise_timers();
    let dt = Duration::from_millis(1);
    let dt_s = dt.as_secs_f64();
    let mut coupling = Coupling::new(config.coupling);
    let mut limiter = Limiter::new(config.limits);
    let mut grip_limiter = Limiter::new(config.limits.of_gripper());
    let mut report = Report { device: device.name(), session: args.session.clone(), tool: args.tool, config, ..Default::default() };
    // The last tick's start and the device's position then.
    let mut previous = None::<(Instant, V3)>;
    let mut previous_force = V3::default();
    let mut previous_grip_n = 0.0;
    // The poses sent lately, to find the one an answer is for; the newest answer's echo.
    let mut sent_poses = SentPoses::default();
    let mut last_answer = None::<Instant>;
    let mut next = Instant::now();
    let deadline = args.duration_s.map(|s| origin + Duration::from_secs_f64(s));
    // After the run, a last stretch with no answers brings the force to zero smoothly.
    let mut ramping_out_until: Option<Instant> = None;
    loop {
        let now = Instant::now();
        if ramping_out_until.is_none() && (deadline.is_some_and(|d| now >= d) || interrupted.load(Ordering::Acquire)) {
            report.ended_by = if interrupted.load(Ordering::Acquire) { "interrupted".into() } else { "duration".into() };
            ramping_out_until = Some(now + Duration::from_secs_f64(config.limits.ramp_ms / 1e3 + 0.5));
        }
        if let Some(until) = ramping_out_until
            && ((previous_force.norm() == 0.0 && previous_grip_n == 0.0) || now >= until)
        {
            break;
        }
        let state = device.read(now - origin);
        let position = config.workspace.position(state.position_m);
        // The time this tick covers (a millisecond, or more where the OS delayed it) and
        // where the device was when it began.
        let (elapsed_s, from) = previous.map_or((dt_s, position), |(t, p)| ((now - t).as_secs_f64().max(MIN_TICK_S), p));
        previous = Some((now, position));

        let connected = link.connected.load(Ordering::Acquire);
        let answer = link.answer.load_full();
        let fresh = ramping_out_until.is_none()
            && connected
            && answer.as_ref().is_some_and(|a| now.duration_since(a.received).as_secs_f64() * 1e3 <= config.limits.stale_ms);
        let fresh_answer = answer.as_deref().filter(|_| fresh);
        let (tissue, resistance, grasping, jaws_force_n) = fresh_answer.map_or_else(Default::default, |a| (a.force, a.resistance, a.grasping, a.jaws_force_n));
        match fresh_answer {
            // Each new answer teaches the local model, at the pose it answered (a server
            // catching up answers one pose several times, as the tissue moves on).
            Some(a) if Some(a.received) != last_answer => {
                last_answer = Some(a.received);
                match sent_poses.find(a.echo_client_time_ns) {
                    Some(at) => coupling.answered(at, a.force, a.resistance),
                    None => coupling.forget_answers(),
                }
            }
            Some(_) => {}
            None => coupling.forget_answers(),
        }
        report.max_local_stiffness_n_per_m = report.max_local_stiffness_n_per_m.max(coupling.local_stiffness_n_per_m());
        coupling.set_grasping(grasping);
        report.grasping_steps += u64::from(grasping);
        let mut wanted = if state.present { coupling.advance(elapsed_s, dt_s, from, position, tissue, resistance) } else { V3::default() };
        if let Some(w) = watcher.as_ref().filter(|_| state.present && ramping_out_until.is_none()) {
            wanted = wanted + pulse.step(elapsed_s, w.warnings.load(Ordering::Acquire), tissue);
        }
        let force = limiter.apply(config.workspace.force_to_device(wanted), fresh, elapsed_s);
        // The gripper's force goes as the answer came (the squeeze is the hand's, not the
        // proxy's), through limits of its own.
        let grip_n = grip_limiter.apply(V3(jaws_force_n, 0.0, 0.0), fresh, elapsed_s).0;
        device.write_force(force, grip_n, fresh);
        report.max_grip_force_n = report.max_grip_force_n.max(grip_n);
        previous_grip_n = grip_n;

        if state.present && ramping_out_until.is_none() {
            let q = config.workspace.orientation(state.orientation);
            let p = coupling.proxy;
            let client_time_ns = (Instant::now() - origin).as_nanos() as u64 + 1;
            sent_poses.push(client_time_ns, p);
            link.send(pb::ToolCommand {
                tool: args.tool,
                pose: Some(pb::Pose { position_m: Some(pb::Vec3 { x: p.0, y: p.1, z: p.2 }), orientation: Some(pb::Quaternion { w: q.0, x: q.1, y: q.2, z: q.3 }) }),
                active: true,
                cut: state.buttons & 1 == 1,
                client_time_ns,
                feedback_every_steps: 1,
                grip: state.grip,
            });
        }

        report.device_steps += 1;
        report.forces_sent += 1;
        report.max_force_n = report.max_force_n.max(force.norm());
        report.max_force_step_n = report.max_force_step_n.max((force - previous_force).norm());
        report.max_force_rate_n_per_s = report.max_force_rate_n_per_s.max((force - previous_force).norm() / elapsed_s);
        report.stale_steps += u64::from(!fresh);
        previous_force = force;
        if let Some(t) = trace.as_mut() {
            writeln!(t, "{:.6},{},{},{},{},{},{},{}", (now - origin).as_secs_f64(), force.0, force.1, force.2, force.norm(), u8::from(fresh), u8::from(connected), grip_n)?;
        }

        // Ticks are due every millisecond. After one the OS delayed by less than a tick
        // the loop catches up with ticks half a millisecond apart, never closer (a
        // velocity measured over a few microseconds is noise); after a longer delay it
        // starts counting again from now.
        let after = Instant::now();
        next = if now > next + dt {
            report.late_steps += 1;
            now + dt
        } else {
            (next + dt).max(now + dt / 2)
        };
        if next > after {
            std::thread::sleep(next - after);
        }
    }
    // Tell the server the tool left, then stop the network.
    link.send(pb::ToolCommand { tool: args.tool, active: false, ..Default::default() });
    std::thread::sleep(Duration::from_millis(20));
    link.stop();
    if let Some(w) = watcher.as_mut() {
        w.stop();
        report.cues = pulse.played();
    }
    if let Some(mut t) = trace {
        t.flush()?;
    }

    report.duration_s = origin.elapsed().as_secs_f64();
    report.reconnects = link.reconnects.load(Ordering::Relaxed);
    report.clamped = limiter.clamped;
    report.rate_limited = limiter.rate_limited;
    report.non_finite = limiter.non_finite;
    let mut rtt = link.round_trips_us.lock().expect("rtt lock").clone();
    rtt.sort_unstable();
    report.rtt_samples = rtt.len();
    let quantile = |q: f64| rtt.get(((rtt.len() as f64 * q) as usize).min(rtt.len().saturating_sub(1))).copied().unwrap_or(0);
    report.rtt_p50_us = quantile(0.5);
    report.rtt_p99_us = quantile(0.99);
    report.rtt_max_us = rtt.last().copied().unwrap_or(0);
    eprintln!(
        "{}: {} ticks, round trip p50 {} µs / p99 {} µs, max force {:.3} N, max step {:.4} N, stale {} ticks, reconnects {}",
        report.device, report.device_steps, report.rtt_p50_us, report.rtt_p99_us, report.max_force_n, report.max_force_step_n, report.stale_steps, report.reconnects
    );
    if let Some(path) = &args.report {
        std::fs::write(path, serde_json::to_string_pretty(&report)?).with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(())
}

/// The proxy poses of the last commands sent, by their `client_time_ns`: an answer
/// echoes the command it used, and the local model learns at that pose. A fixed ring
/// (the device loop allocates nothing): answers come within a round trip, and an
/// answer for a pose older than the ring holds is not learnt from.
struct SentPoses {
    poses: [(u64, V3); 256],
    next: usize,
}

impl Default for SentPoses {
    fn default() -> Self {
        Self { poses: [(0, V3::default()); 256], next: 0 }
    }
}

impl SentPoses {
    fn push(&mut self, client_time_ns: u64, pose: V3) {
        self.poses[self.next] = (client_time_ns, pose);
        self.next = (self.next + 1) % self.poses.len();
    }

    /// The pose sent with `client_time_ns`, looked for from the newest (an answer is for
    /// one of the last few).
    fn find(&self, client_time_ns: u64) -> Option<V3> {
        if client_time_ns == 0 {
            return None;
        }
        let (older, newer) = self.poses.split_at(self.next);
        newer.iter().chain(older).rev().find(|(t, _)| *t == client_time_ns).map(|(_, pose)| *pose)
    }
}

/// Calls `on_interrupt` on SIGINT or SIGTERM (the device loop then fades the force out).
fn ctrlc_like(on_interrupt: impl Fn() + Send + 'static) -> std::io::Result<()> {
    std::thread::Builder::new().name("bridge-signals".into()).spawn(move || {
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().expect("a tokio runtime");
        runtime.block_on(async {
            #[cfg(unix)]
            {
                let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()).expect("a SIGTERM handler");
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {}
                    _ = term.recv() => {}
                }
            }
            #[cfg(not(unix))]
            let _ = tokio::signal::ctrl_c().await;
        });
        on_interrupt();
    })?;
    Ok(())
}

/// 1 ns timer slack so that the 1 kHz loop wakes on time (Linux).
fn precise_timers() {
    #[cfg(target_os = "linux")]
    // SAFETY: PR_SET_TIMERSLACK takes an integer and affects only the calling thread.
    unsafe {
        libc::prctl(libc::PR_SET_TIMERSLACK, 1 as libc::c_ulong, 0, 0, 0);
    }
}
