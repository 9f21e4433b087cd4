//! What viewers see of a session, kept off the physics thread.
//!
//! The physics thread publishes two things: topology deltas (never dropped, through an
//! unbounded channel, only when a cut happens) and, a few hundred times a second, a
//! [`Frame`] with every vertex position, the tools and the statistics (through a
//! lock-free latest-value cell, reusing a small pool of frames so that publishing
//! allocates nothing). The hub task applies each delta to a replica of the surface and
//! broadcasts it, encoded once, to every viewer; a viewer that connects (or falls
//! behind) gets a snapshot built from the replica and the newest frame.

use std::sync::{Arc, Mutex};

use arc_swap::ArcSwap;
use cutsim_sim::surface::{SurfaceReplica, SurfaceSnapshot, TopologyDelta};
use cutsim_sim::tissue::{CutFallback, TissueCounters};
use cutsim_sim::tool::{ToolCommand, ToolFeedback};
use prost::Message;
use tokio::sync::{broadcast, mpsc};

use crate::convert;

/// Per-session step statistics as published.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StepStats {
    pub p50_us: f64,
    pub p99_us: f64,
    pub max_us: f64,
    pub steps: u64,
    pub missed_deadlines: u64,
    pub achieved_rate_hz: f64,
}

/// One tool as the physics thread last saw it.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ToolFrame {
    pub command: ToolCommand,
    pub feedback: ToolFeedback,
    /// Forceps' jaws' half gap, m (None for a tool without jaws).
    pub jaws_half_gap_m: Option<f64>,
}

/// The newest state of a session for viewers and the API.
#[derive(Debug, Clone, Default)]
pub struct Frame {
    /// One more for every frame published (a paused replay publishes without stepping).
    pub sequence: u64,
    /// Steps since the tissue was (re)built.
    pub step: u64,
    /// Steps since the session started (over resets).
    pub total_steps: u64,
    /// Published topology version the positions belong to.
    pub topology_version: u64,
    /// Published version of the current tissue's version 0 (it changes when the tissue is
    /// replaced): frames of another tissue do not apply to a viewer's surface.
    pub epoch_version: u64,
    pub session_time_ns: u64,
    pub unix_ms: f64,
    /// Position of every vertex slot, m (f32, what the wire carries).
    pub positions: Vec<[f32; 3]>,
    pub tools: Vec<ToolFrame>,
    pub stats: StepStats,
    pub counters: TissueCounters,
    /// The tissue's cut updates left as open holes, with their steps and reasons (copied
    /// only when the list changes: it grows on a fallback and empties with a new tissue).
    pub fallbacks: Vec<CutFallback>,
    pub pieces: u64,
    pub status: crate::session::Status,
    /// Replay sessions only.
    pub playback: Option<PlaybackState>,
}

/// Where a replay is.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PlaybackState {
    pub step: u64,
    pub total_steps: u64,
    pub playing: bool,
    pub speed: f64,
}

/// A few frames the physics thread fills in turn: a frame is reused once no reader
/// holds it any more, so publishing never allocates (unless a cut grew the surface).
pub struct FramePool {
    frames: Vec<Arc<Frame>>,
    published: u64,
}

impl FramePool {
    pub fn new(count: usize) -> Self {
        Self { frames: (0..count).map(|_| Arc::new(Frame::default())).collect(), published: 0 }
    }

    /// Fills a free frame with `fill` and publishes it; returns false (and publishes
    /// nothing) when every frame is still held by a reader.
    pub fn publish(&mut self, cell: &ArcSwap<Frame>, fill: impl FnOnce(&mut Frame)) -> bool {
        for frame in &mut self.frames {
            if let Some(f) = Arc::get_mut(frame) {
                fill(f);
                self.published += 1;
                f.sequence = self.published;
                cell.store(frame.clone());
                return true;
            }
        }
        false
    }
}

/// What the physics thread sends the hub.
pub enum HubEvent {
    /// A cut update, with its published version.
    Delta(TopologyDelta, u64),
    /// The tissue was replaced (a script starts, a replay seeks): its whole surface, and
    /// the published version of that tissue's version 0.
    Reset(SurfaceSnapshot, u64),
}

/// What the hub broadcasts to viewers.
#[derive(Clone)]
pub enum HubMessage {
    /// A delta and its encoded ViewerFrame.
    Delta(Arc<TopologyDelta>, Arc<Vec<u8>>),
    /// The surface was replaced: take a fresh snapshot.
    Reset,
    /// The session closed.
    Closed,
}

struct HubState {
    replica: SurfaceReplica,
    epoch_version: u64,
}

/// The viewer side of a session.
pub struct Hub {
    session_id: String,
    state: Mutex<HubState>,
    messages: broadcast::Sender<HubMessage>,
}

/// Deltas a viewer may be behind before it is resynchronised with a snapshot.
const VIEWER_BACKLOG: usize = 256;

impl Hub {
    pub fn new(session_id: &str, initial: &SurfaceSnapshot) -> Arc<Self> {
        let (messages, _) = broadcast::channel(VIEWER_BACKLOG);
        Arc::new(Self {
            session_id: session_id.to_owned(),
            state: Mutex::new(HubState { replica: SurfaceReplica::from_snapshot(initial), epoch_version: initial.version }),
            messages,
        })
    }

    /// Runs until the physics thread hangs up: applies and broadcasts its events.
    pub async fn run(self: Arc<Self>, mut events: mpsc::UnboundedReceiver<HubEvent>) {
        while let Some(event) = events.recv().await {
            match event {
                HubEvent::Delta(delta, step) => {
                    let bytes = Arc::new(convert::delta_frame(&delta, step).encode_to_vec());
                    let mut state = self.state.lock().expect("hub lock");
                    if let Err(e) = state.replica.apply(&delta) {
                        // Cannot happen unless the model broke its own contract; viewers
                        // are told to resynchronise from a rebuilt replica.
                        tracing::error!(session = %self.session_id, error = %e, "topology delta does not apply");
                        continue;
                    }
                    let _ = self.messages.send(HubMessage::Delta(Arc::new(delta), bytes));
                }
                HubEvent::Reset(snapshot, epoch_version) => {
                    let mut state = self.state.lock().expect("hub lock");
                    state.replica = SurfaceReplica::from_snapshot(&snapshot);
                    state.epoch_version = epoch_version;
                    let _ = self.messages.send(HubMessage::Reset);
                }
            }
        }
        let _ = self.messages.send(HubMessage::Closed);
    }

    /// A snapshot for a viewer, and its subscription to everything after it: taken under
    /// the hub's lock, so that no delta falls between the two. Positions come from the
    /// newest frame where it holds them.
    /// Also returns the first version of the current tissue (frames of other tissues do
    /// not apply to this snapshot).
    pub fn subscribe(&self, frame: &Frame) -> (SurfaceSnapshot, broadcast::Receiver<HubMessage>, u64) {
        let state = self.state.lock().expect("hub lock");
        let mut snapshot = state.replica.to_snapshot();
        overlay_positions(&mut snapshot, frame, state.epoch_version);
        (snapshot, self.messages.subscribe(), state.epoch_version)
    }

    pub fn close(&self) {
        let _ = self.messages.send(HubMessage::Closed);
    }
}

/// Replaces snapshot positions by the frame's, when the frame belongs to the same
/// tissue (not from before a reset) and holds the vertex.
pub fn overlay_positions(snapshot: &mut SurfaceSnapshot, frame: &Frame, epoch_version: u64) {
    if frame.epoch_version != epoch_version {
        return;
    }
    for v in &mut snapshot.vertices {
        if let Some(p) = frame.positions.get(v.id as usize) {
            v.position_m = *p;
        }
    }
}
