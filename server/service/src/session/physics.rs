//! The physics thread of one session.
//!
//! Real-time sessions step once per period of the scene's rate (1 kHz by default),
//! against absolute deadlines. With a haptic device attached a step starts at once when
//! the device's fresh command arrives (so its round trip does not wait for a period
//! boundary), as early as half a period before its period begins, or at the latest when
//! the rest of its period just holds a step; the periods follow the device's clock. Inputs
//! and outputs cross to networking through lock-free slots; topology deltas
//! go to the hub through a channel; frames through a lock-free cell; recording through a
//! lock-free ring. Nothing here waits for a network task, logs per step or allocates per
//! step (cuts and frames after a cut grew the surface excepted).
//!
//! Scripts run here too, in lockstep: the tissue is rebuilt from the scene and stepped
//! as fast as the CPU allows, publishing to viewers as it goes.

use std::sync::Arc;
use std::sync::mpsc::Receiver;
use std::time::{Duration, Instant};

use cutsim_sim::assessment::ToolSample;
use cutsim_sim::runner::{self, Progress};
use cutsim_sim::scene::Scene;
use cutsim_sim::stats::LatencyHistogram;
use cutsim_sim::surface::{SurfaceSnapshot, TopologyDelta};
use cutsim_sim::tissue::Tissue;
use cutsim_sim::tool::{ToolCommand, ToolFeedback};
use tokio::sync::mpsc::UnboundedSender;

use super::assessing::AssessProducer;
use super::hub::{FramePool, HubEvent, PlaybackState, StepStats, ToolFrame};
use super::records::{FeedbackRecord, StampedCommand};
use super::recording::{RecordEvent, RecordingProducer};
use super::{CloseReason, Control, Mode, ScriptEvent, Session, Status};

/// Frames per second published for viewers (they pick their own rate below it).
const FRAME_RATE_HZ: f64 = 250.0;
/// Margin kept before a period's end when waiting for a haptic command.
const START_MARGIN: Duration = Duration::from_micros(150);
/// Step-time statistics are recomputed this often (quantiles walk the histogram).
const STATS_EVERY_STEPS: u64 = 100;

/// How a session's physics thread behaves beyond its scene.
#[derive(Debug, Clone, Copy, Default)]
pub struct Settings {
    /// A tool whose command is older than this is lifted (real-time sessions).
    pub stale_after: Duration,
    /// Record the state hash every this many steps of a real-time session (0: never).
    pub checkpoint_every: u64,
    /// Fault injection (tests): panic when this many steps were taken.
    pub panic_at_step: Option<u64>,
}

pub struct Physics {
    pub(super) scene: Scene,
    settings: Settings,
    /// When each tool's newest command arrived (for the stale-command watchdog).
    fresh_at: Vec<Instant>,
    /// Tools lifted by the watchdog, until their client sends again.
    lifted: Vec<bool>,
    pub(super) tissue: Box<dyn Tissue>,
    pub(super) control: Receiver<Control>,
    stamped: Vec<StampedCommand>,
    seen_versions: Vec<u64>,
    pub(super) histogram: LatencyHistogram,
    missed: u64,
    rate_window: (Instant, u64),
    estimated_step: Duration,
    /// Steps counted (`Outputs::total_steps`) when the last viewer frame was published.
    last_frame_step: u64,
    /// What publishing a frame takes (a slow-leaning estimate, as for steps).
    estimated_publish: Duration,
    pub(super) out: Outputs,
}

/// Everything a step publishes (kept apart from the tissue so that a script's runner
/// can hold the tissue while its per-step hook publishes).
pub(super) struct Outputs {
    pub(super) session: Arc<Session>,
    hub: UnboundedSender<HubEvent>,
    /// None for replays (they do not record themselves).
    recording: Option<RecordingProducer>,
    /// The assessor's ring (None for replays: they assess on this thread, see playback).
    assess: Option<AssessProducer>,
    pub(super) commands: Vec<ToolCommand>,
    recorded: Vec<ToolCommand>,
    pub(super) feedback: Vec<ToolFeedback>,
    deltas: Vec<TopologyDelta>,
    stats: StepStats,
    pub(super) total_steps: u64,
    /// Published topology version of the current tissue's version 0.
    epoch_version: u64,
    /// Highest topology version published so far (versions only ever grow).
    max_published: u64,
    frames: FramePool,
    pub(super) publish_every: u64,
    pub(super) status: Status,
    pieces: u64,
    pub(super) playback: Option<PlaybackState>,
}

impl Physics {
    pub fn new(
        session: Arc<Session>,
        scene: Scene,
        tissue: Box<dyn Tissue>,
        control: Receiver<Control>,
        hub: UnboundedSender<HubEvent>,
        recording: Option<RecordingProducer>,
        assess: Option<AssessProducer>,
        settings: Settings,
    ) -> Self {
        let tools = tissue.tools().len();
        let rate = 1.0 / tissue.time_step_s();
        let status = if session.mode == Mode::Realtime { Status::Running } else { Status::Idle };
        let pieces = tissue.pieces() as u64;
        Self {
            scene,
            settings,
            fresh_at: vec![Instant::now(); tools],
            lifted: vec![false; tools],
            tissue,
            control,
            stamped: vec![StampedCommand::default(); tools],
            seen_versions: vec![0; tools],
            histogram: LatencyHistogram::new(),
            missed: 0,
            rate_window: (Instant::now(), 0),
            estimated_step: Duration::from_micros(200),
            last_frame_step: 0,
            estimated_publish: Duration::ZERO,
            out: Outputs {
                session,
                hub,
                recording,
                assess,
                commands: vec![ToolCommand::default(); tools],
                recorded: vec![ToolCommand::default(); tools],
                feedback: vec![ToolFeedback::default(); tools],
                deltas: Vec::with_capacity(8),
                stats: StepStats::default(),
                total_steps: 0,
                epoch_version: 0,
                max_published: 0,
                frames: FramePool::new(4),
                publish_every: (rate / FRAME_RATE_HZ).round().max(1.0) as u64,
                status,
                pieces,
                playback: None,
            },
        }
    }

    /// The thread's body: runs until the session closes.
    pub fn run(mut self) {
        crate::priority::precise_timers();
        let period = Duration::from_secs_f64(self.tissue.time_step_s());
        // The beginning of the next step's period.
        let mut next = Instant::now();
        self.out.publish_frame(self.tissue.as_ref());
        loop {
            while let Ok(message) = self.control.try_recv() {
                if let Some(reason) = self.handle(message) {
                    return self.finish(reason);
                }
                next = next.max(Instant::now());
            }
            if self.out.session.is_closed() {
                return self.finish(CloseReason::Closed);
            }
            if self.out.session.mode == Mode::Lockstep {
                std::thread::park_timeout(Duration::from_millis(20));
                continue;
            }
            let haptic = self.out.session.subscribers.count() > 0;
            if haptic {
                self.wait_for_device(next, period);
            } else {
                park_until(next);
            }
            let started = Instant::now();
            let fresh = self.read_commands();
            self.lift_stale_tools(started);
            self.step_realtime();
            if fresh {
                // The periods follow the device's clock, a tenth of a period a step at
                // most (a client cannot drive the physics more than 11 % above the
                // scene's rate): its commands then arrive as their periods begin, which
                // leaves them the most room either side.
                let arrival = self.newest_arrival();
                let limit = period / 10;
                next = if arrival > next { next + period + (arrival - next).min(limit) } else { next + period - (next - arrival).min(limit) };
            } else {
                next += period;
            }
            self.publish_frame_if_room(next);
            let end = Instant::now();
            if end > next {
                self.missed += 1;
            }
            if end > next + 5 * period {
                // Far behind (a long cut update, a stalled machine): resume from now
                // rather than run a burst of late steps.
                next = end;
            }
        }
    }

    /// With a haptic device attached, steps follow its commands, which it sends once per
    /// period by its own clock: a step starts as soon as a fresh command arrives, from
    /// half a period before its own period begins; without one it starts at the end of its
    /// period minus the time a step takes, at the latest (and never before its period
    /// begins). A device's command thus never waits for a period boundary, and its round
    /// trip is the transport plus one step. The periods are the wall clock's, nudged
    /// towards the device's (see `run`), not counted from the last step: a command that
    /// came late (its step went without it) starts the next step as soon as it arrives,
    /// and the commands after it do not wait.
    fn wait_for_device(&self, period_begins: Instant, period: Duration) {
        let earliest = period_begins - period / 2;
        // (A slow step, say one that waited for a deformation job, raises the estimate for
        // a while: steps without a command still wait for their period.)
        let latest = (period_begins + period.saturating_sub(self.estimated_step + START_MARGIN)).max(period_begins);
        loop {
            let now = Instant::now();
            let fresh = self.fresh_command();
            if now >= latest || (now >= earliest && fresh) {
                return;
            }
            // Parked: a command's arrival unparks (Session::submit); one that came too
            // early waits for its earliest start. (Spinning for the command instead of
            // parking was tried: on two cores with a deformation thread busy, the spinning
            // thread kept the command's network thread from running, delaying the very
            // command it watched for.)
            std::thread::park_timeout(if fresh { earliest - now } else { latest - now });
        }
    }

    /// Handles a control message; the reason when the session must stop.
    fn handle(&mut self, message: Control) -> Option<CloseReason> {
        match message {
            Control::Close(reason) => return Some(reason),
            Control::Snapshot(reply) => {
                let _ = reply.send((self.snapshot(), self.tissue.step_index()));
            }
            Control::StateHash(reply) => {
                let (step, hash) = (self.tissue.step_index(), self.tissue.state_hash());
                self.out.record(RecordEvent::Checkpoint { step, hash });
                let _ = reply.send((step, hash));
            }
            Control::RunScript { script, progress_every, events } => {
                if self.out.session.mode == Mode::Replay {
                    let _ = events.send(ScriptEvent::Failed("a replay session plays its recording; run scripts on another session".into()));
                } else {
                    self.run_script(&script, progress_every, &events);
                }
            }
            // Only replays have a playback (see `run_replay`).
            Control::Playback(..) => {}
        }
        None
    }

    pub(super) fn snapshot(&self) -> SurfaceSnapshot {
        self.snapshot_of(self.tissue.as_ref())
    }

    /// A tissue's surface under the versions viewers of this session know.
    pub(super) fn snapshot_of(&self, tissue: &dyn Tissue) -> SurfaceSnapshot {
        let mut s = tissue.snapshot();
        s.version += self.out.epoch_version;
        s
    }

    /// When the newest of the tools' commands arrived (on the session's clock).
    fn newest_arrival(&self) -> Instant {
        let newest = self.stamped.iter().map(|s| s.received_ns).max().unwrap_or(0);
        self.out.session.created + Duration::from_nanos(newest)
    }

    fn fresh_command(&self) -> bool {
        self.out.session.commands.iter().zip(&self.seen_versions).any(|(slot, &seen)| slot.version() != seen)
    }

    /// Takes the newest command of every tool (keeping the previous one if a writer is
    /// caught mid-write: the physics never waits for networking); whether any was fresh.
    fn read_commands(&mut self) -> bool {
        let mut fresh = false;
        for (tool, slot) in self.out.session.commands.iter().enumerate() {
            if let Some((words, version)) = slot.try_read(16) {
                if version != self.seen_versions[tool] {
                    self.fresh_at[tool] = Instant::now();
                    self.lifted[tool] = false;
                    fresh = true;
                }
                self.seen_versions[tool] = version;
                if version != 0 && !self.lifted[tool] {
                    self.stamped[tool] = StampedCommand::from_words(&words);
                    self.out.commands[tool] = self.stamped[tool].command;
                }
            }
        }
        fresh
    }

    /// The stale-command watchdog: a tool whose client has sent nothing for
    /// `stale_after` (its process paused, its network gone without a goodbye) is lifted
    /// out of the tissue — it stops pressing and cutting — until commands come again.
    /// The lift is an ordinary command change, so the recording replays it exactly.
    fn lift_stale_tools(&mut self, now: Instant) {
        for tool in 0..self.out.commands.len() {
            let command = &mut self.out.commands[tool];
            if command.active && !self.lifted[tool] && now.duration_since(self.fresh_at[tool]) > self.settings.stale_after {
                command.active = false;
                command.cut = false;
                self.lifted[tool] = true;
                self.out.session.stale_lifts.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
        }
    }

    /// Fault injection for tests: a panic at a chosen step.
    fn inject_faults(&self) {
        if self.settings.panic_at_step == Some(self.out.total_steps) {
            panic!("injected fault: panic_at_step {}", self.out.total_steps);
        }
    }

    /// A real-time session writes its state hash into the recording every
    /// `checkpoint_every` steps: a replay then proves it reached the same states.
    fn checkpoint_if_due(&mut self) {
        let every = self.settings.checkpoint_every;
        let step = self.tissue.step_index();
        if every > 0 && step > 0 && step % every == 0 {
            let hash = self.tissue.state_hash();
            self.out.record(RecordEvent::Checkpoint { step, hash });
        }
    }

    fn step_realtime(&mut self) {
        self.inject_faults();
        let step = self.tissue.step_index();
        self.out.record_commands(step);
        let started = Instant::now();
        self.tissue.step(&self.out.commands, &mut self.out.feedback);
        let elapsed = started.elapsed();
        self.histogram.record(elapsed);
        // A slow-moving estimate that leans to the slow side: it sets how late a step
        // may start.
        self.estimated_step = if elapsed > self.estimated_step { elapsed } else { (self.estimated_step * 63 + elapsed) / 64 };
        let now_ns = self.out.session.now_ns();
        for (tool, slot) in self.out.session.feedback.iter().enumerate() {
            let stamped = &self.stamped[tool];
            let record = FeedbackRecord {
                step: self.out.total_steps,
                feedback: self.out.feedback[tool],
                echo_client_time_ns: stamped.client_time_ns,
                server_latency_ns: if stamped.client_time_ns == 0 { 0 } else { now_ns.saturating_sub(stamped.received_ns) },
                step_time_ns: elapsed.as_nanos() as u64,
            };
            slot.write(record.to_words());
        }
        self.out.session.subscribers.wake_all();
        self.out.after_step(self.tissue.as_mut());
        self.checkpoint_if_due();
        if self.out.total_steps % STATS_EVERY_STEPS == 0 {
            self.update_stats();
        }
    }

    /// Publishes the viewers' frame when one is due and there is room for it before the
    /// step's deadline, or when it is a whole frame period late. A frame copies every
    /// surface vertex (for a branched grid, interpolated from its element's nodes: a few
    /// hundred microseconds for a CT liver), which beside a slow step would make that step
    /// late; viewers do not notice a frame a few steps later.
    fn publish_frame_if_room(&mut self, deadline: Instant) {
        let since = self.out.total_steps.saturating_sub(self.last_frame_step);
        if since < self.out.publish_every {
            return;
        }
        let started = Instant::now();
        if started + self.estimated_publish > deadline && since < 2 * self.out.publish_every {
            return;
        }
        self.out.publish_frame(self.tissue.as_ref());
        self.last_frame_step = self.out.total_steps;
        let elapsed = started.elapsed();
        self.estimated_publish = if elapsed > self.estimated_publish { elapsed } else { (self.estimated_publish * 63 + elapsed) / 64 };
    }

    fn update_stats(&mut self) {
        let h = &self.histogram;
        let stats = &mut self.out.stats;
        let (window_start, window_steps) = self.rate_window;
        let elapsed = window_start.elapsed().as_secs_f64();
        if elapsed >= 1.0 {
            stats.achieved_rate_hz = (self.out.total_steps - window_steps) as f64 / elapsed;
            self.rate_window = (Instant::now(), self.out.total_steps);
        }
        stats.p50_us = h.quantile_ns(0.5) as f64 / 1e3;
        stats.p99_us = h.quantile_ns(0.99) as f64 / 1e3;
        stats.max_us = h.max_ns() as f64 / 1e3;
        stats.steps = h.count();
        stats.missed_deadlines = self.missed;
        if self.tissue.counters().blowups_contained > 0 && self.out.status == Status::Running {
            self.out.status = Status::Degraded;
        }
    }

    /// Resets the tissue to the scene's initial state and runs a script in lockstep. On
    /// a real-time session the script runs on a helper thread in the background
    /// scheduling class (the session's own thread keeps its priority for when the
    /// script ends). A script stops early when its client goes away or the session
    /// closes.
    fn run_script(&mut self, script: &cutsim_sim::script::CompiledScript, progress_every: u64, events: &UnboundedSender<ScriptEvent>) {
        let previous_status = self.out.status;
        self.out.status = Status::RunningScript;
        if let Err(e) = self.reset() {
            let _ = events.send(ScriptEvent::Failed(e));
            self.out.status = previous_status;
            return;
        }
        self.out.publish_frame(self.tissue.as_ref());
        let frame_every = Duration::from_secs_f64(1.0 / 60.0);
        let mut last_frame = Instant::now();
        let steps = script.steps;
        let every = if progress_every == 0 { (steps / 20).max(1) } else { progress_every };
        let task = self.scene.task();
        let (tissue, scene_name, out, panic_at) = (self.tissue.as_mut(), &self.scene.name, &mut self.out, self.settings.panic_at_step);
        let realtime = out.session.mode == Mode::Realtime;
        // The hook records, publishes deltas and, about 60 times a second of wall time,
        // a frame for viewers; it is not part of the timed step.
        let run = move || {
            if realtime {
                crate::priority::yield_to_real_time();
            }
            runner::run_with_hook(
                tissue,
                scene_name,
                task,
                Some(script),
                steps,
                every,
                |p: &Progress| {
                    let _ = events.send(ScriptEvent::Progress(*p));
                },
                |tissue, commands, feedback| {
                    if panic_at == Some(out.total_steps) {
                        panic!("injected fault: panic_at_step {}", out.total_steps);
                    }
                    out.commands.copy_from_slice(commands);
                    out.feedback.copy_from_slice(feedback);
                    // The runner has stepped already: the commands were those of the step before.
                    out.record_commands(tissue.step_index() - 1);
                    out.after_step(tissue);
                    if last_frame.elapsed() >= frame_every {
                        out.publish_frame(tissue);
                        last_frame = Instant::now();
                    }
                    if events.is_closed() || out.session.is_closed() {
                        return std::ops::ControlFlow::Break(());
                    }
                    std::ops::ControlFlow::Continue(())
                },
            )
        };
        let outcome = if realtime {
            std::thread::scope(|scope| match std::thread::Builder::new().name("script".into()).spawn_scoped(scope, run) {
                Ok(helper) => helper.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic)),
                Err(e) => panic!("cannot start a script thread: {e}"),
            })
        } else {
            run()
        };
        let (step, hash) = (self.tissue.step_index(), self.tissue.state_hash());
        self.out.record(RecordEvent::Checkpoint { step, hash });
        self.out.status = previous_status;
        self.update_stats();
        self.out.publish_frame(self.tissue.as_ref());
        let _ = events.send(match outcome {
            Ok(report) => ScriptEvent::Report(Box::new(report)),
            Err(stopped) => ScriptEvent::Failed(format!("the script stopped after {} of {steps} steps: its client went away or the session closed", stopped.at_step)),
        });
    }

    /// Rebuilds the tissue from the scene; viewers get the new surface as a snapshot.
    fn reset(&mut self) -> Result<(), String> {
        let tissue = cutsim_sim::build_tissue(&self.scene).map_err(|e| e.to_string())?;
        self.out.record(RecordEvent::Reset { step: self.tissue.step_index() });
        if let Some(assess) = &mut self.out.assess {
            assess.reset();
        }
        self.replace_tissue(tissue);
        self.out.recorded.iter_mut().for_each(|c| *c = ToolCommand::default());
        self.out.commands.iter_mut().for_each(|c| *c = ToolCommand::default());
        Ok(())
    }

    /// Puts another tissue in place (a script's reset): viewers get its surface as a
    /// snapshot.
    pub(super) fn replace_tissue(&mut self, tissue: Box<dyn Tissue>) {
        self.tissue = tissue;
        self.republish();
    }

    /// Sends viewers the current surface as a snapshot under versions they have never
    /// seen (after the tissue was replaced or fast-forwarded without publishing).
    pub(super) fn republish(&mut self) {
        self.out.epoch_version = self.out.max_published + 1;
        self.out.pieces = self.tissue.pieces() as u64;
        let snapshot = self.snapshot();
        self.out.max_published = snapshot.version;
        let _ = self.out.hub.send(HubEvent::Reset(snapshot, self.out.epoch_version));
    }

    pub(super) fn finish(mut self, reason: CloseReason) {
        let (step, hash) = (self.tissue.step_index(), self.tissue.state_hash());
        self.out.record(RecordEvent::End { step, hash, reason });
        self.out.status = Status::Closed;
        self.out.publish_frame(self.tissue.as_ref());
    }
}

impl Outputs {
    pub(super) fn record(&mut self, event: RecordEvent) {
        if let Some(r) = self.recording.as_mut() {
            r.push(event);
        }
    }

    /// Records the commands of step `step` that differ from the last recorded ones.
    fn record_commands(&mut self, step: u64) {
        let Some(recording) = self.recording.as_mut() else { return };
        for (tool, (command, recorded)) in self.commands.iter().zip(self.recorded.iter_mut()).enumerate() {
            if command != recorded {
                recording.push(RecordEvent::Command { step, tool: tool as u32, command: *command });
                *recorded = *command;
            }
        }
    }

    /// Publishes what a step changed: its topology deltas (only after a cut).
    pub(super) fn after_step(&mut self, tissue: &mut dyn Tissue) {
        self.total_steps += 1;
        if let Some(assess) = &mut self.assess {
            // A script waits for the assessor rather than lose a step of its metrics.
            let samples = self.commands.iter().zip(&self.feedback).map(|(c, f)| ToolSample::new(c, f));
            assess.push_step(samples, self.status == Status::RunningScript);
        }
        tissue.drain_deltas(&mut self.deltas);
        if !self.deltas.is_empty() {
            for mut delta in self.deltas.drain(..) {
                delta.version += self.epoch_version;
                self.max_published = delta.version;
                let _ = self.hub.send(HubEvent::Delta(delta, tissue.step_index()));
            }
            self.pieces = tissue.pieces() as u64;
        }
    }

    /// Drops the deltas a step made without publishing them (a replay fast-forwarding to
    /// a seek target ends with a snapshot instead).
    pub(super) fn discard_deltas(&mut self, tissue: &mut dyn Tissue) {
        tissue.drain_deltas(&mut self.deltas);
        self.deltas.clear();
    }

    pub(super) fn publish_frame(&mut self, tissue: &dyn Tissue) {
        let (session, stats, status, pieces, playback) = (&self.session, self.stats, self.status, self.pieces, self.playback);
        let (commands, feedback) = (&self.commands, &self.feedback);
        let (epoch, total) = (self.epoch_version, self.total_steps);
        self.frames.publish(&session.frame, |f| {
            // Copied only when it changed (before the epoch is stamped): the list only grows
            // while the tissue lives, so a frame of the same tissue with as many entries and
            // the same last one holds it already, and copying would allocate.
            let fallbacks = tissue.cut_fallbacks();
            if f.epoch_version != epoch || f.fallbacks.len() != fallbacks.len() || f.fallbacks.last() != fallbacks.last() {
                f.fallbacks.clear();
                f.fallbacks.extend_from_slice(fallbacks);
            }
            f.step = tissue.step_index();
            f.total_steps = total;
            f.topology_version = epoch + tissue.topology_version();
            f.epoch_version = epoch;
            f.session_time_ns = session.now_ns();
            f.unix_ms = unix_ms();
            f.positions.resize(tissue.vertex_capacity(), [0.0; 3]);
            tissue.write_positions(&mut f.positions);
            f.tools.resize(commands.len(), ToolFrame::default());
            for (t, tool) in f.tools.iter_mut().enumerate() {
                *tool = ToolFrame { command: commands[t], feedback: feedback[t], jaws_half_gap_m: tissue.jaws_half_gap_m(t) };
            }
            f.stats = stats;
            f.counters = tissue.counters();
            f.pieces = pieces;
            f.status = status;
            f.playback = playback;
        });
    }
}

fn unix_ms() -> f64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64() * 1e3)
}

/// Sleeps until `deadline` (an unpark only shortens one wait).
fn park_until(deadline: Instant) {
    loop {
        let now = Instant::now();
        if now >= deadline {
            return;
        }
        std::thread::park_timeout(deadline - now);
    }
}
