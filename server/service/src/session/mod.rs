//! Sessions: one tissue, one physics thread, its viewers, haptic clients and recording.

pub mod admission;
pub mod assessing;
pub mod hub;
pub mod physics;
mod playback;
pub mod retention;
pub mod records;
pub mod recording;
pub mod slots;

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Instant;

use arc_swap::ArcSwap;
use cutsim_sim::math::Vec3;
use cutsim_sim::runner::{Progress, RunReport};
use cutsim_sim::scene::{Scene, resolve_bundled_scene, resolve_scene_path};
use cutsim_sim::script::CompiledScript;
use cutsim_sim::surface::SurfaceSnapshot;
use cutsim_sim::tool::ToolShape;
use tokio::sync::{mpsc, oneshot};

use crate::auth::{Operators, Role, Token, authorize};
use crate::config::ServerConfig;
use crate::error::ApiError;
use admission::{Admission, Slot};
use hub::{Frame, Hub};
use records::{COMMAND_WORDS, FEEDBACK_WORDS, StampedCommand};
use recording::{Recorder, Recording};
use slots::{SeqSlot, Subscribers};

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Status {
    #[default]
    Running,
    Idle,
    RunningScript,
    Closed,
    Degraded,
    /// The physics thread panicked: the session stopped (see `Session::failure`).
    Failed,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    Realtime,
    Lockstep,
    /// Plays a recording.
    Replay,
}

/// What a replay viewer asks of the playback.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PlaybackCommand {
    Play,
    Pause,
    /// Go to this step of the recording (over all its resets).
    Seek(u64),
    /// Replay speed relative to the recorded rate.
    Speed(f64),
}

/// Requests to the physics thread (answered between two steps).
pub enum Control {
    Snapshot(oneshot::Sender<(SurfaceSnapshot, u64)>),
    StateHash(oneshot::Sender<(u64, u64)>),
    RunScript { script: CompiledScript, progress_every: u64, events: mpsc::UnboundedSender<ScriptEvent> },
    /// Answered once the command is applied (and the new state published).
    Playback(PlaybackCommand, oneshot::Sender<()>),
    Close(CloseReason),
}

/// What a script run streams back.
pub enum ScriptEvent {
    Progress(Progress),
    Report(Box<RunReport>),
    Failed(String),
}

/// Why a session closed (written at the end of its recording).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CloseReason {
    /// A client or an operator closed it.
    Closed,
    /// Nobody used it for `idle_session_timeout_s`.
    Expired,
    /// The server shut down.
    Shutdown,
}

impl CloseReason {
    pub fn as_str(self) -> &'static str {
        match self {
            CloseReason::Closed => "closed",
            CloseReason::Expired => "expired",
            CloseReason::Shutdown => "shutdown",
        }
    }
}

/// Who asked for a session, and whether it may expire.
#[derive(Debug, Clone)]
pub struct Creator {
    /// How the creator authenticated (logged; never shown to other clients).
    pub who: String,
    /// Sessions opened by the operator on the command line stay until closed.
    pub expires: bool,
}

/// Where a session's scene comes from.
pub enum SceneSource {
    Bundled(String),
    /// A bundled scene name or a scene file path, from the operator's command line.
    Operator(String),
    Inline(String),
}

/// One training session. Networking holds it through an `Arc`; only its physics thread
/// touches the tissue.
pub struct Session {
    pub id: String,
    pub label: String,
    pub scene_name: String,
    pub model: &'static str,
    /// How "fidelity": "auto" chose the grid's level (empty: the scene's own level).
    pub fidelity: String,
    pub mode: Mode,
    pub rate_hz: f64,
    /// Under a multirate schedule, the deformation's rate, Hz (0: single-rate).
    pub deformation_rate_hz: f64,
    pub tools: Vec<ToolShape>,
    /// Bounding box of the tissue at the start, m.
    pub bounds: (Vec3, Vec3),
    created: Instant,
    control_token: Token,
    observe_token: Token,
    /// Newest command per tool (written by haptic streams, read by the physics thread).
    pub commands: Vec<SeqSlot<COMMAND_WORDS>>,
    /// Newest feedback per tool (written by the physics thread).
    pub feedback: Vec<SeqSlot<FEEDBACK_WORDS>>,
    /// Haptic streams waiting for feedback.
    pub subscribers: Subscribers,
    /// The newest frame for viewers.
    pub frame: ArcSwap<Frame>,
    pub hub: Arc<Hub>,
    pub viewers: AtomicU32,
    pub bytes_sent: AtomicU64,
    closed: AtomicBool,
    control_tx: Mutex<std::sync::mpsc::Sender<Control>>,
    physics_thread: std::thread::Thread,
    physics_join: Mutex<Option<std::thread::JoinHandle<()>>>,
    /// Every session records itself, except replays.
    recorder: Mutex<Option<Recorder>>,
    pub creator: Creator,
    /// Session clock (ms) of the last call, command or script that used the session.
    last_activity_ms: AtomicU64,
    /// Why the physics thread stopped, when it panicked.
    failure: OnceLock<String>,
    /// Tools lifted because their haptic client went quiet (`stale_command_ms`).
    pub stale_lifts: AtomicU64,
    /// The room the session holds; given back when it closes or fails.
    admission: Mutex<Option<Slot>>,
    /// The trainee's metrics against the scene's task, as last published.
    pub assessment: Arc<assessing::AssessmentCell>,
}

impl Session {
    pub fn authorize(&self, token: Option<&str>, needed: Role) -> Result<Role, ApiError> {
        authorize(token, &self.control_token, &self.observe_token, needed)
    }

    /// Nanoseconds since the session was created (the session clock).
    pub fn now_ns(&self) -> u64 {
        self.created.elapsed().as_nanos() as u64
    }

    pub fn age_s(&self) -> f64 {
        self.created.elapsed().as_secs_f64()
    }

    pub fn is_closed(&self) -> bool {
        self.closed.load(Ordering::Acquire)
    }

    /// Notes that someone used the session (it is not idle).
    pub fn touch(&self) {
        self.last_activity_ms.store(self.now_ns() / 1_000_000, Ordering::Relaxed);
    }

    /// Seconds since anyone used the session, counting attached viewers, haptic
    /// clients and running scripts as use.
    pub fn idle_s(&self) -> f64 {
        let busy = self.viewers.load(Ordering::Relaxed) > 0 || self.subscribers.count() > 0 || self.frame.load().status == Status::RunningScript;
        if busy {
            self.touch();
            return 0.0;
        }
        (self.now_ns() / 1_000_000).saturating_sub(self.last_activity_ms.load(Ordering::Relaxed)) as f64 / 1e3
    }

    /// Why the physics failed, if it did.
    pub fn failure(&self) -> Option<&str> {
        self.failure.get().map(String::as_str)
    }

    /// Waits (up to a second) until the session has either failed or closed: when its
    /// physics thread dies, the channels it held close a moment before the session is
    /// marked failed, and whoever notices first should still tell the reason.
    pub async fn settled(&self) {
        for _ in 0..100 {
            if self.failure().is_some() || self.is_closed() {
                return;
            }
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        }
    }

    /// The error a request on a failed session gets.
    pub fn failed_error(&self) -> Option<ApiError> {
        self.failure().map(|reason| ApiError::Internal(format!("session {} failed: {reason}; close it and start another", self.id)))
    }

    /// Marks the session failed (its physics thread panicked): haptic streams, scripts and
    /// viewers end with the reason, its room is given back, its recording says so.
    fn fail(&self, reason: String) {
        if self.failure.set(reason.clone()).is_err() {
            return;
        }
        tracing::error!(session = %self.id, %reason, "session failed; its physics stopped (other sessions go on)");
        self.subscribers.wake_all();
        self.hub.close();
        if let Some(r) = self.recorder.lock().unwrap_or_else(|e| e.into_inner()).as_mut() {
            r.finish_failed(&reason);
        }
        drop(self.admission.lock().unwrap_or_else(|e| e.into_inner()).take());
    }

    /// Hands a command to the physics thread (newest wins) and wakes it.
    pub fn submit(&self, tool: usize, command: StampedCommand) {
        self.commands[tool].write(command.to_words());
        self.physics_thread.unpark();
    }

    pub fn send_control(&self, message: Control) -> Result<(), ApiError> {
        if let Some(e) = self.failed_error() {
            return Err(e);
        }
        if self.is_closed() {
            return Err(ApiError::FailedPrecondition(format!("session {} is closed", self.id)));
        }
        self.control_tx
            .lock()
            .expect("control lock")
            .send(message)
            .map_err(|_| self.stopped_error())?;
        self.physics_thread.unpark();
        Ok(())
    }

    /// The error for a request the physics thread did not answer: it failed, or the
    /// session closed meanwhile.
    pub fn stopped_error(&self) -> ApiError {
        self.failed_error().unwrap_or_else(|| ApiError::Unavailable(format!("session {} closed while the request was handled", self.id)))
    }

    /// The surface now, from the physics thread (between two steps).
    pub async fn snapshot(&self) -> Result<(SurfaceSnapshot, u64), ApiError> {
        let (tx, rx) = oneshot::channel();
        self.send_control(Control::Snapshot(tx))?;
        rx.await.map_err(|_| self.stopped_error())
    }

    /// (steps since the tissue was built, full state hash), also written as a checkpoint.
    pub async fn state_hash(&self) -> Result<(u64, u64), ApiError> {
        let (tx, rx) = oneshot::channel();
        self.send_control(Control::StateHash(tx))?;
        rx.await.map_err(|_| self.stopped_error())
    }

    /// Recording losses so far: (events the ring could not take, write failures).
    pub fn recording_losses(&self) -> (u64, u64) {
        self.recorder.lock().expect("recorder lock").as_ref().map_or((0, 0), Recorder::losses)
    }

    /// What went wrong with the recording (a full disk…), reported in SessionInfo.
    pub fn recording_problem(&self) -> Option<String> {
        self.recorder.lock().expect("recorder lock").as_ref().and_then(Recorder::problem)
    }

    pub fn recording_path(&self) -> Option<std::path::PathBuf> {
        self.recorder.lock().expect("recorder lock").as_ref().map(|r| r.path.clone())
    }

    /// Stops the physics thread, tells viewers, finishes the recording and gives the
    /// session's room back.
    pub fn close(&self, reason: CloseReason) {
        if self.closed.swap(true, Ordering::AcqRel) {
            return;
        }
        let _ = self.control_tx.lock().expect("control lock").send(Control::Close(reason));
        self.physics_thread.unpark();
        if let Some(join) = self.physics_join.lock().expect("join lock").take() {
            let _ = join.join();
        }
        self.hub.close();
        if let Some(r) = self.recorder.lock().unwrap_or_else(|e| e.into_inner()).as_mut() {
            r.finish();
        }
        drop(self.admission.lock().unwrap_or_else(|e| e.into_inner()).take());
    }

    pub fn tokens(&self) -> (&str, &str) {
        (self.control_token.as_str(), self.observe_token.as_str())
    }
}

/// All sessions of the server.
pub struct Registry {
    sessions: Mutex<BTreeMap<String, Arc<Session>>>,
    pub config: Arc<ServerConfig>,
    pub operators: Operators,
    pub admission: Arc<Admission>,
    pub created_total: AtomicU64,
    pub failed_total: AtomicU64,
    pub expired_total: AtomicU64,
    /// Where sessions' health changes go (the gRPC health service, set up by `serve`).
    health: Mutex<Option<mpsc::UnboundedSender<(String, SessionHealth)>>>,
}

/// A session as the gRPC health service shows it (`cutsim.v1.Session/<id>`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SessionHealth {
    Serving,
    /// Its physics failed.
    Failed,
    /// Closed: no longer listed.
    Gone,
}

/// The environment variable that lets scenes inject faults (tests only).
pub const FAULT_INJECTION_ENV: &str = "CUTSIM_FAULT_INJECTION";

/// Faults a test may ask for in an inline scene, under `"fault_injection"`, when the server
/// runs with $CUTSIM_FAULT_INJECTION=1.
#[derive(Debug, Clone, Copy, Default, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaultInjection {
    /// The physics thread panics when the session has taken this many steps.
    pub panic_at_step: Option<u64>,
}

impl Registry {
    pub fn new(config: Arc<ServerConfig>, operators: Operators) -> Arc<Self> {
        let limits = &config.limits;
        let capacity = admission::Capacity {
            max_sessions: limits.max_sessions,
            max_realtime_sessions: limits.realtime_capacity(),
            memory_reserve_bytes: limits.memory_reserve_mib << 20,
        };
        Arc::new(Self {
            sessions: Mutex::new(BTreeMap::new()),
            admission: Admission::new(capacity),
            config,
            operators,
            created_total: AtomicU64::new(0),
            failed_total: AtomicU64::new(0),
            expired_total: AtomicU64::new(0),
            health: Mutex::new(None),
        })
    }

    /// Where sessions' health changes are sent.
    pub fn report_health_to(&self, tx: mpsc::UnboundedSender<(String, SessionHealth)>) {
        *self.health.lock().expect("health lock") = Some(tx);
    }

    fn report_health(&self, id: &str, health: SessionHealth) {
        if let Some(tx) = self.health.lock().expect("health lock").as_ref() {
            let _ = tx.send((id.to_owned(), health));
        }
    }

    pub fn get(&self, id: &str) -> Result<Arc<Session>, ApiError> {
        self.sessions.lock().expect("registry lock").get(id).cloned().ok_or_else(|| ApiError::UnknownSession(id.to_owned()))
    }

    pub fn list(&self) -> Vec<Arc<Session>> {
        self.sessions.lock().expect("registry lock").values().cloned().collect()
    }

    /// Creates a session and starts its physics.
    pub async fn create(self: &Arc<Self>, source: SceneSource, mode: Mode, label: String, creator: Creator) -> Result<Arc<Session>, ApiError> {
        let limits = &self.config.limits;
        if label.len() > 200 {
            return Err(ApiError::InvalidArgument(format!("label is {} bytes; at most 200", label.len())));
        }
        let (scene_json, origin, base_dir) = match source {
            SceneSource::Bundled(name) => {
                let path = resolve_bundled_scene(&name, &self.config.scene_dirs).map_err(|e| ApiError::BadField { request_field: "scene_name", field: String::new(), message: e.to_string() })?;
                let text = std::fs::read_to_string(&path).map_err(|e| ApiError::Internal(format!("cannot read {}: {e}", path.display())))?;
                (text, path.display().to_string(), path.parent().map(|p| p.to_path_buf()))
            }
            SceneSource::Operator(name_or_path) => {
                let path = resolve_scene_path(&name_or_path, &self.config.scene_dirs).map_err(|e| ApiError::InvalidArgument(e.to_string()))?;
                let text = std::fs::read_to_string(&path).map_err(|e| ApiError::Internal(format!("cannot read {}: {e}", path.display())))?;
                (text, path.display().to_string(), path.parent().map(|p| p.to_path_buf()))
            }
            SceneSource::Inline(text) => {
                if text.len() > limits.max_scene_bytes {
                    return Err(ApiError::exhausted(
                        "scene size",
                        format!("scene_json is {} bytes; at most {} are allowed", text.len(), limits.max_scene_bytes),
                    ));
                }
                (text, "inline scene".to_owned(), None)
            }
        };
        let inline = base_dir.is_none();
        let (scene_json, faults) = if inline { take_fault_injection(&scene_json)? } else { (scene_json, FaultInjection::default()) };
        let scene = Scene::from_json_str(&scene_json, &origin, base_dir.as_deref())?;
        if inline {
            scene.check_network_file_references(&origin)?;
        }
        self.start(scene, Some(scene_json), mode, label, None, creator, faults).await
    }

    /// Creates a session that replays a recording (from the recordings directory).
    pub async fn create_replay(self: &Arc<Self>, recorded_session: &str, creator: Creator) -> Result<Arc<Session>, ApiError> {
        let path = self.recording_path(recorded_session)?;
        if let Ok(live) = self.get(recorded_session) {
            // A live session: everything it recorded so far goes into the replay.
            tokio::task::spawn_blocking(move || {
                if let Some(r) = live.recorder.lock().unwrap_or_else(|e| e.into_inner()).as_ref() {
                    r.sync();
                }
            })
            .await
            .map_err(|e| ApiError::Internal(e.to_string()))?;
        }
        let recording = tokio::task::spawn_blocking(move || Recording::read(&path))
            .await
            .map_err(|e| ApiError::Internal(e.to_string()))?
            .map_err(ApiError::FailedPrecondition)?;
        let scene = recording.scene.clone();
        self.start(scene, None, Mode::Replay, format!("replay of {recorded_session}"), Some(Arc::new(recording)), creator, FaultInjection::default()).await
    }

    /// The recording file of a session id (only names of the recordings directory).
    pub fn recording_path(&self, session: &str) -> Result<std::path::PathBuf, ApiError> {
        if session.is_empty() || !session.chars().all(|c| c.is_ascii_hexdigit()) {
            return Err(ApiError::InvalidArgument(format!("{session:?} is not a session id (hexadecimal digits)")));
        }
        let path = self.config.recordings_dir.join(format!("{session}.jsonl"));
        if !path.is_file() {
            return Err(ApiError::UnknownSession(format!("{session} (no recording of it)")));
        }
        Ok(path)
    }

    /// Builds the tissue and starts a session's physics thread, once the machine has
    /// room for it (reserved before the build).
    #[allow(clippy::too_many_arguments)]
    async fn start(
        self: &Arc<Self>,
        scene: Scene,
        scene_json: Option<String>,
        mode: Mode,
        label: String,
        replay: Option<Arc<Recording>>,
        creator: Creator,
        faults: FaultInjection,
    ) -> Result<Arc<Session>, ApiError> {
        let footprint = scene.footprint()?;
        let mut slot = self.admission.admit(mode == Mode::Realtime, &footprint)?;
        let building = scene.clone();
        let tissue = tokio::task::spawn_blocking(move || cutsim_sim::build_tissue(&building))
            .await
            .map_err(|e| ApiError::Internal(e.to_string()))?
            .map_err(|e| ApiError::InvalidArgument(e.to_string()))?;
        slot.built();

        let id = random_id();
        // A level (and deformation rate) chosen by "fidelity": "auto" depends on this machine: the recording
        // pins it, so that a replay builds the same grid.
        let fidelity = tissue.fidelity();
        let (scene, scene_json) = match &fidelity {
            Some(chosen) => {
                use cutsim_sim::grid::fidelity::{pin_choice, pin_scene};
                tracing::info!(session = %id, "{}", chosen.summary);
                (pin_scene(&scene, chosen), scene_json.map(|j| pin_choice(&j, chosen)).transpose().map_err(ApiError::Internal)?)
            }
            None => (scene, scene_json),
        };
        let initial = tissue.snapshot();
        let bounds = bounding_box(&initial);
        let tools = tissue.tools().to_vec();
        let policy = &self.config.recordings;
        let (recorder, producer) = match &scene_json {
            Some(json) => {
                let settings = recording::RecorderSettings { sync_every: std::time::Duration::from_secs_f64(policy.sync_every_ms / 1e3) };
                let checkpoint_every = if mode == Mode::Realtime { policy.checkpoint_every_steps } else { 0 };
                let (recorder, producer) = Recorder::start(&self.config.recordings_dir, &id, &scene, json, checkpoint_every, settings)
                    .map_err(|e| ApiError::Internal(format!("cannot record the session in {}: {e}", self.config.recordings_dir.display())))?;
                (Some(recorder), Some(producer))
            }
            None => (None, None),
        };
        let hub = Hub::new(&id, &initial);
        let (hub_tx, hub_rx) = mpsc::unbounded_channel();
        let (control_tx, control_rx) = std::sync::mpsc::channel();
        let rate_hz = 1.0 / tissue.time_step_s();
        let deformation_rate_hz = tissue.deformation_rate_hz().unwrap_or(0.0);
        let model = tissue.model_name();
        let settings = physics::Settings {
            stale_after: std::time::Duration::from_secs_f64(self.config.limits.stale_command_ms / 1e3),
            checkpoint_every: if mode == Mode::Realtime { policy.checkpoint_every_steps } else { 0 },
            panic_at_step: faults.panic_at_step,
        };
        let registry = Arc::downgrade(self);
        let description = scene.task.as_ref().map(|t| t.description.clone()).unwrap_or_default();
        let checked = scene.task();
        let assessment = assessing::AssessmentCell::new(assessing::TaskInfo::new(&description, &checked), checked);
        // Replays assess on their physics thread (with a copy per kept state, to seek).
        let assess = match &replay {
            Some(_) => None,
            None => Some(
                assessing::start(&id, scene.task(), tools.len(), tissue.time_step_s(), assessment.clone())
                    .map_err(|e| ApiError::Internal(format!("cannot start an assessor thread: {e}")))?,
            ),
        };

        // The physics thread starts parked until the session is assembled.
        let (start_tx, start_rx) = std::sync::mpsc::channel::<Arc<Session>>();
        let scene_for_thread = scene.clone();
        let join = std::thread::Builder::new()
            .name(format!("physics-{}", &id[..8]))
            .spawn(move || {
                let Ok(session) = start_rx.recv() else { return };
                // Lockstep scripts and replays run as fast as they can; only a real-time
                // session has deadlines, so the others take the CPU time it leaves, and a
                // real-time one preempts bulk work as soon as it wakes.
                if mode == Mode::Realtime {
                    crate::priority::short_slices();
                } else {
                    crate::priority::yield_to_real_time();
                }
                let run = {
                    let session = session.clone();
                    move || {
                        let physics = physics::Physics::new(session, scene_for_thread, tissue, control_rx, hub_tx, producer, assess, settings);
                        match replay {
                            Some(recording) => physics.run_replay(recording),
                            None => physics.run(),
                        }
                    }
                };
                // A panic in the physics stops this session only: it is marked failed
                // and everything waiting on it is told why.
                if let Err(panic) = std::panic::catch_unwind(std::panic::AssertUnwindSafe(run)) {
                    // Counted and sent to the health service before the session says
                    // FAILED, so whoever sees the status finds the count already
                    // there; the health service applies it moments later (its own task).
                    let step = session.frame.load().total_steps;
                    if let Some(registry) = registry.upgrade() {
                        registry.failed_total.fetch_add(1, Ordering::Relaxed);
                        registry.report_health(&session.id, SessionHealth::Failed);
                    }
                    session.fail(format!("the physics stopped at step {step}: {}", panic_message(panic.as_ref())));
                }
            })
            .map_err(|e| ApiError::Internal(format!("cannot start a physics thread: {e}")))?;
        let session = Arc::new(Session {
            id: id.clone(),
            label,
            scene_name: scene.name.clone(),
            model,
            fidelity: fidelity.map(|chosen| chosen.summary).unwrap_or_default(),
            mode,
            rate_hz,
            deformation_rate_hz,
            commands: (0..tools.len()).map(|_| SeqSlot::default()).collect(),
            feedback: (0..tools.len()).map(|_| SeqSlot::default()).collect(),
            tools,
            bounds,
            created: Instant::now(),
            control_token: Token::generate(),
            observe_token: Token::generate(),
            subscribers: Subscribers::new(self.config.limits.max_haptic_clients_per_session),
            frame: ArcSwap::from_pointee(Frame::default()),
            hub: hub.clone(),
            viewers: AtomicU32::new(0),
            bytes_sent: AtomicU64::new(0),
            closed: AtomicBool::new(false),
            control_tx: Mutex::new(control_tx),
            physics_thread: join.thread().clone(),
            physics_join: Mutex::new(Some(join)),
            recorder: Mutex::new(recorder),
            creator,
            last_activity_ms: AtomicU64::new(0),
            failure: OnceLock::new(),
            stale_lifts: AtomicU64::new(0),
            admission: Mutex::new(Some(slot)),
            assessment,
        });
        tokio::spawn(hub.run(hub_rx));
        start_tx.send(session.clone()).map_err(|_| ApiError::Internal("the physics thread did not start".into()))?;
        self.sessions.lock().expect("registry lock").insert(id.clone(), session.clone());
        self.created_total.fetch_add(1, Ordering::Relaxed);
        self.report_health(&id, SessionHealth::Serving);
        tracing::info!(session = %id, scene = %session.scene_name, ?mode, by = %session.creator.who, "session created");
        Ok(session)
    }

    /// Closes a session and forgets it.
    pub async fn close(&self, id: &str, reason: CloseReason) -> Result<(), ApiError> {
        let session = self.sessions.lock().expect("registry lock").remove(id).ok_or_else(|| ApiError::UnknownSession(id.to_owned()))?;
        tokio::task::spawn_blocking(move || session.close(reason)).await.map_err(|e| ApiError::Internal(e.to_string()))?;
        self.report_health(id, SessionHealth::Gone);
        tracing::info!(session = %id, reason = reason.as_str(), "session closed");
        Ok(())
    }

    /// Closes the sessions nobody used for `idle_session_timeout_s` (those opened from
    /// the command line excepted); returns their ids.
    pub async fn expire_idle(&self) -> Vec<String> {
        let timeout = self.config.limits.idle_session_timeout_s;
        if timeout <= 0.0 {
            return Vec::new();
        }
        let idle: Vec<String> = self.list().iter().filter(|s| s.creator.expires && s.idle_s() > timeout).map(|s| s.id.clone()).collect();
        for id in &idle {
            if self.close(id, CloseReason::Expired).await.is_ok() {
                self.expired_total.fetch_add(1, Ordering::Relaxed);
                tracing::info!(session = %id, timeout_s = timeout, "idle session expired");
            }
        }
        idle
    }

    /// Closes every session (server shutdown): recordings end cleanly.
    pub fn close_all(&self) {
        let sessions: Vec<_> = std::mem::take(&mut *self.sessions.lock().expect("registry lock")).into_values().collect();
        for s in sessions {
            s.close(CloseReason::Shutdown);
        }
    }
}

/// Takes `"fault_injection"` out of an inline scene: allowed only on a server started
/// with $CUTSIM_FAULT_INJECTION=1 (the end-to-end tests' panicking physics).
fn take_fault_injection(json: &str) -> Result<(String, FaultInjection), ApiError> {
    if !json.contains("\"fault_injection\"") {
        return Ok((json.to_owned(), FaultInjection::default()));
    }
    let bad = |message: String| ApiError::BadField { request_field: "scene_json", field: "fault_injection".into(), message };
    let mut value: serde_json::Value = match serde_json::from_str(json) {
        Ok(v) => v,
        Err(_) => return Ok((json.to_owned(), FaultInjection::default())), // the scene parser explains
    };
    let Some(faults) = value.as_object_mut().and_then(|o| o.remove("fault_injection")) else {
        return Ok((json.to_owned(), FaultInjection::default()));
    };
    if std::env::var(FAULT_INJECTION_ENV).as_deref() != Ok("1") {
        return Err(bad(format!("fault injection is a test feature: the server must run with {FAULT_INJECTION_ENV}=1")));
    }
    let faults: FaultInjection = serde_json::from_value(faults).map_err(|e| bad(e.to_string()))?;
    Ok((value.to_string(), faults))
}

/// The text of a panic's payload.
fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| (*s).to_owned())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "a panic without a message".into())
}

/// 16 hex digits from the operating system's random source.
fn random_id() -> String {
    let mut bytes = [0u8; 8];
    getrandom::fill(&mut bytes).expect("the operating system provides random bytes");
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn bounding_box(snapshot: &SurfaceSnapshot) -> (Vec3, Vec3) {
    let mut lo = Vec3::repeat(f64::INFINITY);
    let mut hi = Vec3::repeat(f64::NEG_INFINITY);
    for v in &snapshot.vertices {
        let p = Vec3::new(f64::from(v.position_m[0]), f64::from(v.position_m[1]), f64::from(v.position_m[2]));
        lo = lo.inf(&p);
        hi = hi.sup(&p);
    }
    if !lo.x.is_finite() {
        return (Vec3::zeros(), Vec3::zeros());
    }
    (lo, hi)
}
