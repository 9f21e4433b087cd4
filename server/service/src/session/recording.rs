//! Session recordings: an append-only, flushed log of the scene and every tool command
//! with its step index, from which a session replays bit-exactly.
//!
//! The physics thread pushes fixed-size events into a lock-free ring (no allocation, no
//! lock, no I/O on the 1 kHz path); a recorder thread writes them as JSON lines and
//! flushes them to the operating system every 5 ms, so a recording survives the server
//! being killed (at most the last few milliseconds are lost), and forces them to the
//! disk (fdatasync) every `sync_every` (1 s by default) and at the end, so that a power
//! cut loses at most that much. If the ring overflows or the disk fails, the loss is
//! counted and written down, never silent.
//!
//! Format (one JSON object per line; floats in their shortest exact form):
//! ```text
//! {"format":"cutsim-recording","version":1,"session":"…","build":"cutsim-server 0.1.0 (git 1a2b3c4d5e6f)",
//!  "scene_sha256":"…","checkpoint_every_steps":10000,"scene_origin":"…","base_dir":"…","scene":{…}}
//! {"t":"cmd","step":12,"tool":0,"p":[x,y,z],"q":[w,x,y,z],"active":true,"cut":false}
//!                                           (+ "grip":0.4 where an analog gripper sent one)
//! {"t":"reset","step":500}                 tissue rebuilt from the scene (script start)
//! {"t":"check","step":900,"hash":"…"}      state hash after `step` steps
//! {"t":"lost","count":3}                    events that could not be recorded
//! {"t":"end","step":1200,"hash":"…","reason":"closed"}   session closed (or "expired", "shutdown")
//! {"t":"failed","reason":"…"}               the session's physics failed; nothing follows
//! ```
//! A command line's `step` is the index of the first step that used it; a checkpoint's
//! is the number of steps taken since the last reset.

use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use cutsim_sim::hash::hash_hex;
use cutsim_sim::math::{Pose, Vec3, quat_from_wxyz_exact};
use cutsim_sim::scene::Scene;
use cutsim_sim::tool::{ToolCommand, ToolFeedback};
use serde::{Deserialize, Serialize};

/// Events the physics thread records.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RecordEvent {
    Command { step: u64, tool: u32, command: ToolCommand },
    Reset { step: u64 },
    Checkpoint { step: u64, hash: u64 },
    /// The session closed: steps since the last reset and the final state hash.
    End { step: u64, hash: u64, reason: super::CloseReason },
}

/// How a recorder writes.
#[derive(Debug, Clone, Copy)]
pub struct RecorderSettings {
    /// Forced to the disk (fdatasync) at least this often.
    pub sync_every: Duration,
}

/// The server build that writes recordings: version and git commit.
pub const BUILD: &str = concat!("cutsim-server ", env!("CARGO_PKG_VERSION"), " (git ", env!("CUTSIM_GIT_COMMIT"), ")");

/// Ring capacity: about a minute of one tool changing every step at 1 kHz.
const RING_CAPACITY: usize = 1 << 16;

/// The physics thread's end of a recording.
pub struct RecordingProducer {
    ring: rtrb::Producer<RecordEvent>,
    lost: Arc<AtomicU64>,
}

impl RecordingProducer {
    /// Records an event; never blocks: a full ring counts the event as lost.
    pub fn push(&mut self, event: RecordEvent) {
        if self.ring.push(event).is_err() {
            self.lost.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// Failed writes (a full disk…): how many, and the first one's error, which the
/// session reports until it closes.
#[derive(Default)]
struct WriteFailures {
    count: AtomicU64,
    first: std::sync::OnceLock<String>,
}

impl WriteFailures {
    fn record(&self, error: &std::io::Error, path: &Path) {
        self.count.fetch_add(1, Ordering::Relaxed);
        if self.first.set(error.to_string()).is_ok() {
            tracing::error!(recording = %path.display(), %error, "a recording write failed: the session goes on, its recording is incomplete from here");
        }
    }
}

/// The recorder thread and what it reports.
pub struct Recorder {
    pub path: PathBuf,
    lost: Arc<AtomicU64>,
    write_errors: Arc<WriteFailures>,
    stop: Arc<AtomicBool>,
    /// Why the session failed, written last.
    failure: Arc<std::sync::Mutex<Option<String>>>,
    sync_tx: std::sync::mpsc::Sender<std::sync::mpsc::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

#[derive(Serialize, Deserialize)]
struct Header {
    format: String,
    version: u32,
    session: String,
    /// The server that wrote it (absent in recordings of older servers).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    build: String,
    /// SHA-256 of the scene JSON as written below, hex.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    scene_sha256: String,
    /// A real-time session's checkpoint interval (0: none; absent in older recordings).
    #[serde(default)]
    checkpoint_every_steps: u64,
    scene_origin: String,
    base_dir: Option<PathBuf>,
    scene: serde_json::Value,
}

#[derive(Serialize, Deserialize, Debug, PartialEq)]
#[serde(tag = "t", rename_all = "lowercase")]
enum Line {
    Cmd {
        step: u64,
        tool: u32,
        p: [f64; 3],
        q: [f64; 4],
        active: bool,
        cut: bool,
        /// Forceps' squeeze (a fraction of their grip), where the device sent one.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        grip: Option<f64>,
    },
    Reset { step: u64 },
    Check { step: u64, hash: String },
    Lost { count: u64 },
    End {
        step: u64,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        hash: Option<String>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        reason: Option<String>,
    },
    Failed { reason: String },
}

impl Recorder {
    /// Creates the recording file with its header and starts the recorder thread.
    pub fn start(
        dir: &Path,
        session: &str,
        scene: &Scene,
        scene_json: &str,
        checkpoint_every_steps: u64,
        settings: RecorderSettings,
    ) -> std::io::Result<(Recorder, RecordingProducer)> {
        std::fs::create_dir_all(dir)?;
        let path = dir.join(format!("{session}.jsonl"));
        let mut file = std::fs::OpenOptions::new().create_new(true).append(true).open(&path)?;
        let scene_value: serde_json::Value = serde_json::from_str(scene_json).map_err(std::io::Error::other)?;
        let header = Header {
            format: "cutsim-recording".into(),
            version: 1,
            session: session.to_owned(),
            build: BUILD.to_owned(),
            scene_sha256: sha256_hex(scene_value.to_string().as_bytes()),
            checkpoint_every_steps,
            scene_origin: scene.origin.clone(),
            base_dir: scene.base_dir.clone(),
            scene: scene_value,
        };
        writeln!(file, "{}", serde_json::to_string(&header).map_err(std::io::Error::other)?)?;
        file.flush()?;
        file.sync_data()?;
        let (producer, mut consumer) = rtrb::RingBuffer::new(RING_CAPACITY);
        let lost = Arc::new(AtomicU64::new(0));
        let write_errors = Arc::new(WriteFailures::default());
        let stop = Arc::new(AtomicBool::new(false));
        let failure = Arc::new(std::sync::Mutex::new(None::<String>));
        let (sync_tx, sync_rx) = std::sync::mpsc::channel::<std::sync::mpsc::Sender<()>>();
        let thread = {
            let (lost, write_errors, stop, path, failure) = (lost.clone(), write_errors.clone(), stop.clone(), path.clone(), failure.clone());
            let name = format!("record-{}", &session[..session.len().min(8)]);
            std::thread::Builder::new().name(name).spawn(move || {
                let mut out = std::io::BufWriter::with_capacity(1 << 16, file);
                let mut reported_lost = 0;
                let mut waiting: Vec<std::sync::mpsc::Sender<()>> = Vec::new();
                let mut last_sync = std::time::Instant::now();
                let mut unsynced = false;
                loop {
                    let stopping = stop.load(Ordering::Acquire);
                    let mut wrote = false;
                    while let Ok(event) = consumer.pop() {
                        wrote = true;
                        let line = match event {
                            RecordEvent::Command { step, tool, command } => {
                                let p = command.pose.position_m;
                                let q = command.pose.orientation.quaternion();
                                Line::Cmd { step, tool, p: [p.x, p.y, p.z], q: [q.w, q.i, q.j, q.k], active: command.active, cut: command.cut, grip: command.grip }
                            }
                            RecordEvent::Reset { step } => Line::Reset { step },
                            RecordEvent::Checkpoint { step, hash } => Line::Check { step, hash: hash_hex(hash) },
                            RecordEvent::End { step, hash, reason } => Line::End { step, hash: Some(hash_hex(hash)), reason: Some(reason.as_str().into()) },
                        };
                        write_line(&mut out, &line, &write_errors, &path);
                    }
                    let now_lost = lost.load(Ordering::Relaxed);
                    if now_lost > reported_lost {
                        write_line(&mut out, &Line::Lost { count: now_lost - reported_lost }, &write_errors, &path);
                        reported_lost = now_lost;
                        wrote = true;
                    }
                    if stopping && let Some(reason) = failure.lock().unwrap_or_else(|e| e.into_inner()).take() {
                        write_line(&mut out, &Line::Failed { reason }, &write_errors, &path);
                        wrote = true;
                    }
                    if wrote && let Err(e) = out.flush() {
                        write_errors.record(&e, &path);
                    }
                    unsynced |= wrote;
                    // A power cut loses what the page cache holds: force it to the disk
                    // every `sync_every`, and before the thread ends.
                    if unsynced && (stopping || last_sync.elapsed() >= settings.sync_every) {
                        if let Err(e) = out.get_ref().sync_data() {
                            write_errors.record(&e, &path);
                        }
                        last_sync = std::time::Instant::now();
                        unsynced = false;
                    }
                    for ack in waiting.drain(..) {
                        let _ = ack.send(());
                    }
                    if stopping {
                        break;
                    }
                    // Every 5 ms, or at once when someone needs the file up to date.
                    if let Ok(ack) = sync_rx.recv_timeout(Duration::from_millis(5)) {
                        waiting.push(ack);
                    }
                }
            })?
        };
        let recorder = Recorder { path, lost: lost.clone(), write_errors, stop, failure, sync_tx, thread: Some(thread) };
        Ok((recorder, RecordingProducer { ring: producer, lost }))
    }

    /// Events the ring could not take, and write failures (disk full…), so far.
    pub fn losses(&self) -> (u64, u64) {
        (self.lost.load(Ordering::Relaxed), self.write_errors.count.load(Ordering::Relaxed))
    }

    /// What went wrong with this recording, if anything: a replay cannot be exact past it.
    pub fn problem(&self) -> Option<String> {
        let (lost, failed) = self.losses();
        let mut problems = Vec::new();
        if failed > 0 {
            let first = self.write_errors.first.get().map_or("", String::as_str);
            problems.push(format!("{failed} writes to {} failed (first: {first}); the recording is incomplete from there", self.path.display()));
        }
        if lost > 0 {
            problems.push(format!("{lost} events could not be recorded (the recorder fell behind)"));
        }
        (!problems.is_empty()).then(|| problems.join("; "))
    }

    /// Waits (up to a second) until everything recorded so far is written to the file.
    pub fn sync(&self) {
        let (ack_tx, ack_rx) = std::sync::mpsc::channel();
        if self.sync_tx.send(ack_tx).is_ok() {
            let _ = ack_rx.recv_timeout(Duration::from_secs(1));
        }
    }

    /// Writes what is left, then that the session failed and why, and stops the thread.
    pub fn finish_failed(&mut self, reason: &str) {
        *self.failure.lock().unwrap_or_else(|e| e.into_inner()) = Some(reason.to_owned());
        self.finish();
    }

    /// Writes what is left and stops the thread.
    pub fn finish(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        self.finish();
    }
}

fn write_line(out: &mut impl Write, line: &Line, failures: &WriteFailures, path: &Path) {
    let written = serde_json::to_writer(&mut *out, line).map_err(std::io::Error::from).and_then(|()| out.write_all(b"\n"));
    if let Err(e) = written {
        failures.record(&e, path);
    }
}

/// A recording read back: its scene and, per tissue lifetime (a reset starts a new one),
/// the events by step.
#[derive(Debug, Clone)]
pub struct Recording {
    pub session: String,
    pub scene: Scene,
    pub epochs: Vec<Epoch>,
    /// Events the recording says it lost: a replay cannot be exact past them.
    pub lost_events: u64,
    /// Whether it ends with an `end` line (false after a crash).
    pub ended_cleanly: bool,
    /// Why the session's physics failed, when it did.
    pub failure: Option<String>,
    /// The server that wrote it ("" for older recordings).
    pub build: String,
    /// Its real-time checkpoint interval (0: none or unknown).
    pub checkpoint_every_steps: u64,
}

/// The events of one tissue lifetime, sorted by step.
#[derive(Debug, Clone, Default)]
pub struct Epoch {
    pub events: Vec<(u64, EpochEvent)>,
    /// Steps this tissue took (the last step recorded for it).
    pub steps: u64,
}

#[derive(Debug, Clone, PartialEq)]
pub enum EpochEvent {
    Command { tool: usize, command: ToolCommand },
    Checkpoint { hash: String },
}

impl Recording {
    /// Reads a recording; a last line cut short by a crash ends it, anything else that
    /// is not a recording event is an error naming the line.
    pub fn read(path: &Path) -> Result<Recording, String> {
        let file = std::fs::File::open(path).map_err(|e| format!("cannot open recording {}: {e}", path.display()))?;
        let mut lines = std::io::BufReader::new(file).lines();
        let header_line = lines
            .next()
            .ok_or_else(|| format!("{}: empty recording", path.display()))?
            .map_err(|e| format!("{}: {e}", path.display()))?;
        let header: Header = serde_json::from_str(&header_line).map_err(|e| format!("{}: line 1: not a cutsim recording header: {e}", path.display()))?;
        if header.format != "cutsim-recording" || header.version != 1 {
            return Err(format!("{}: unsupported recording format {:?} version {}", path.display(), header.format, header.version));
        }
        let scene = Scene::from_json_str(&header.scene.to_string(), &header.scene_origin, header.base_dir.as_deref()).map_err(|e| e.to_string())?;
        let tools = scene.tools.len();
        if !header.scene_sha256.is_empty() && header.scene_sha256 != sha256_hex(header.scene.to_string().as_bytes()) {
            return Err(format!("{}: line 1: the scene does not match its scene_sha256 (the recording was altered)", path.display()));
        }
        let mut recording = Recording {
            session: header.session,
            scene,
            epochs: vec![Epoch::default()],
            lost_events: 0,
            ended_cleanly: false,
            failure: None,
            build: header.build,
            checkpoint_every_steps: header.checkpoint_every_steps,
        };
        for (index, line) in lines.enumerate() {
            let number = index + 2;
            let Ok(text) = line else { break };
            let Ok(line) = serde_json::from_str::<Line>(&text) else {
                if text.trim_end().ends_with('}') {
                    return Err(format!("{}: line {number}: not a recording event: {text:?}", path.display()));
                }
                break;
            };
            let epoch = recording.epochs.last_mut().expect("there is always an epoch");
            match line {
                Line::Cmd { step, tool, p, q, active, cut, grip } => {
                    if tool as usize >= tools {
                        return Err(format!("{}: line {number}: tool {tool} does not exist in the scene", path.display()));
                    }
                    if let Some(message) = grip.and_then(cutsim_sim::tool::grip_error) {
                        return Err(format!("{}: line {number}: {message}", path.display()));
                    }
                    let pose = Pose::new(Vec3::new(p[0], p[1], p[2]), quat_from_wxyz_exact(q[0], q[1], q[2], q[3]));
                    epoch.events.push((step, EpochEvent::Command { tool: tool as usize, command: ToolCommand { pose, active, cut, grip } }));
                    epoch.steps = epoch.steps.max(step);
                }
                Line::Check { step, hash } => {
                    epoch.events.push((step, EpochEvent::Checkpoint { hash }));
                    epoch.steps = epoch.steps.max(step);
                }
                Line::Reset { step } => {
                    epoch.steps = epoch.steps.max(step);
                    recording.epochs.push(Epoch::default());
                }
                Line::Lost { count } => recording.lost_events += count,
                Line::End { step, hash, .. } => {
                    epoch.steps = epoch.steps.max(step);
                    if let Some(hash) = hash {
                        epoch.events.push((step, EpochEvent::Checkpoint { hash }));
                    }
                    recording.ended_cleanly = true;
                }
                Line::Failed { reason } => recording.failure = Some(reason),
            }
        }
        Ok(recording)
    }

    /// Steps over all epochs.
    pub fn total_steps(&self) -> u64 {
        self.epochs.iter().map(|e| e.steps).sum()
    }
}

/// What a replay did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReplayReport {
    pub recording: String,
    pub session: String,
    pub scene: String,
    /// Steps replayed (over all resets).
    pub steps: u64,
    pub resets: u64,
    pub commands: u64,
    pub checkpoints_verified: u64,
    /// Checkpoints whose hash differed: (step, recorded, replayed).
    pub checkpoint_mismatches: Vec<(u64, String, String)>,
    /// Events the recording says it lost: the replay cannot be exact past them.
    pub lost_events: u64,
    /// Whether the recording ends with an `end` line (false after a crash).
    pub ended_cleanly: bool,
    /// The session's physics failed (the recording says why).
    pub failure: Option<String>,
    /// The server build that wrote the recording.
    pub build: String,
    /// Checkpoints the recording must have at least: its end (a clean end carries the
    /// final hash) and one per checkpoint interval of its first tissue's steps.
    pub checkpoints_expected: u64,
    /// Steps since the last reset, and the state hash there.
    pub final_step: u64,
    pub final_state_hash: String,
    pub passed: bool,
}

/// Replays a recording: rebuilds the scene, applies every command at its step, checks
/// every checkpoint, and stops at the last recorded step.
pub fn replay(path: &Path) -> Result<ReplayReport, String> {
    let recording = Recording::read(path)?;
    let build = || cutsim_sim::build_tissue(&recording.scene).map_err(|e| e.to_string());
    let mut tissue = build()?;
    let tools = tissue.tools().len();
    let mut feedback = vec![ToolFeedback::default(); tools];
    let mut report = ReplayReport {
        recording: path.display().to_string(),
        session: recording.session.clone(),
        scene: recording.scene.name.clone(),
        steps: 0,
        resets: recording.epochs.len() as u64 - 1,
        commands: 0,
        checkpoints_verified: 0,
        checkpoint_mismatches: Vec::new(),
        lost_events: recording.lost_events,
        ended_cleanly: recording.ended_cleanly,
        failure: recording.failure.clone(),
        build: recording.build.clone(),
        checkpoints_expected: expected_checkpoints(&recording),
        final_step: 0,
        final_state_hash: String::new(),
        passed: false,
    };
    for (index, epoch) in recording.epochs.iter().enumerate() {
        if index > 0 {
            tissue = build()?;
        }
        let mut commands = vec![ToolCommand::default(); tools];
        for (step, event) in &epoch.events {
            while tissue.step_index() < *step {
                tissue.step(&commands, &mut feedback);
                report.steps += 1;
            }
            match event {
                EpochEvent::Command { tool, command } => {
                    commands[*tool] = *command;
                    report.commands += 1;
                }
                EpochEvent::Checkpoint { hash } => {
                    let replayed = hash_hex(tissue.state_hash());
                    if &replayed == hash {
                        report.checkpoints_verified += 1;
                    } else {
                        report.checkpoint_mismatches.push((*step, hash.clone(), replayed));
                    }
                }
            }
        }
        while tissue.step_index() < epoch.steps {
            tissue.step(&commands, &mut feedback);
            report.steps += 1;
        }
    }
    report.final_step = tissue.step_index();
    report.final_state_hash = hash_hex(tissue.state_hash());
    report.passed = report.checkpoint_mismatches.is_empty() && report.lost_events == 0 && report.checkpoints_verified >= report.checkpoints_expected;
    Ok(report)
}

/// Checkpoints a recording must hold: its clean end's hash, and the periodic ones of a
/// real-time session's first tissue (scripts reset the tissue; their checkpoints come
/// at their ends).
fn expected_checkpoints(recording: &Recording) -> u64 {
    let periodic = match recording.checkpoint_every_steps {
        0 => 0,
        every => recording.epochs.first().map_or(0, |e| e.steps / every),
    };
    u64::from(recording.ended_cleanly) + periodic
}

/// SHA-256 of `bytes`, as 64 hex digits.
pub fn sha256_hex(bytes: &[u8]) -> String {
    ring::digest::digest(&ring::digest::SHA256, bytes).as_ref().iter().map(|b| format!("{b:02x}")).collect()
}
