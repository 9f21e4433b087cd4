//! The network side: a tokio runtime on its own thread that keeps a haptics stream to
//! the server open (reconnecting with backoff), sends the newest tool pose whenever the
//! device loop publishes one, and keeps the newest feedback for the device loop. The
//! device loop never waits for it.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use arc_swap::ArcSwapOption;
use cutsim_proto::v1 as pb;
use cutsim_proto::v1::haptics_client::HapticsClient;
use tokio::sync::watch;

use crate::vec::V3;

/// The newest answer from the server.
#[derive(Debug, Clone, Copy)]
pub struct Answer {
    /// Force of the tissue on the tool, scene frame, N.
    pub force: V3,
    /// The dissipative share of `force` (the cutting resistance), N.
    pub resistance: V3,
    /// The tool grasps tissue (forceps stopped on what they hold).
    pub grasping: bool,
    /// How hard what lies between the forceps' jaws pushes them apart, N (0: other tools).
    pub jaws_force_n: f64,
    /// `client_time_ns` of the command whose pose the answer is for (0: none yet).
    pub echo_client_time_ns: u64,
    pub received: Instant,
}

pub struct Link {
    pose_tx: watch::Sender<Option<pb::ToolCommand>>,
    pub answer: Arc<ArcSwapOption<Answer>>,
    pub connected: Arc<AtomicBool>,
    pub reconnects: Arc<AtomicU64>,
    /// Round trips (µs) of every pose answered, for the report.
    pub round_trips_us: Arc<std::sync::Mutex<Vec<u32>>>,
    shutdown: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

pub struct Target {
    /// The server, checked (`cutsim_proto::endpoint`) before the link starts.
    pub server: tonic::transport::Endpoint,
    pub session: String,
    pub token: String,
    pub tool: u32,
}

impl Link {
    pub fn start(target: Target, origin: Instant) -> Self {
        let (pose_tx, pose_rx) = watch::channel(None);
        let answer = Arc::new(ArcSwapOption::empty());
        let connected = Arc::new(AtomicBool::new(false));
        let reconnects = Arc::new(AtomicU64::new(0));
        let round_trips_us = Arc::new(std::sync::Mutex::new(Vec::new()));
        let shutdown = Arc::new(AtomicBool::new(false));
        let thread = {
            let (answer, connected, reconnects, round_trips_us, shutdown) =
                (answer.clone(), connected.clone(), reconnects.clone(), round_trips_us.clone(), shutdown.clone());
            std::thread::Builder::new()
                .name("bridge-network".into())
                .spawn(move || {
                    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().expect("a tokio runtime");
                    runtime.block_on(run(target, origin, pose_rx, answer, connected, reconnects, round_trips_us, shutdown));
                })
                .expect("the network thread starts")
        };
        Self { pose_tx, answer, connected, reconnects, round_trips_us, shutdown, thread: Some(thread) }
    }

    /// Publishes the newest tool command (the previous one, if not yet sent, is dropped).
    pub fn send(&self, command: pb::ToolCommand) {
        self.pose_tx.send_replace(Some(command));
    }

    pub fn stop(&mut self) {
        self.shutdown.store(true, Ordering::Release);
        self.pose_tx.send_replace(None);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

#[allow(clippy::too_many_arguments)]
async fn run(
    target: Target,
    origin: Instant,
    pose_rx: watch::Receiver<Option<pb::ToolCommand>>,
    answer: Arc<ArcSwapOption<Answer>>,
    connected: Arc<AtomicBool>,
    reconnects: Arc<AtomicU64>,
    round_trips_us: Arc<std::sync::Mutex<Vec<u32>>>,
    shutdown: Arc<AtomicBool>,
) {
    let mut backoff = Duration::from_millis(100);
    let mut first = true;
    while !shutdown.load(Ordering::Acquire) {
        if !first {
            reconnects.fetch_add(1, Ordering::Relaxed);
            tokio::time::sleep(backoff).await;
            backoff = (backoff * 2).min(Duration::from_secs(2));
        }
        first = false;
        let Ok(channel) = target.server.clone().connect_timeout(Duration::from_millis(500)).connect().await else { continue };
        // Each pose the device loop publishes, once; a newer one replaces an unsent one.
        let outgoing = futures_util::stream::unfold(pose_rx.clone(), |mut rx| async move {
            loop {
                rx.changed().await.ok()?;
                let command = *rx.borrow_and_update();
                if let Some(command) = command {
                    return Some((command, rx));
                }
            }
        });
        let mut request = tonic::Request::new(outgoing);
        let (Ok(session), Ok(token)) = (target.session.parse(), target.token.parse()) else { return };
        request.metadata_mut().insert("cutsim-session", session);
        request.metadata_mut().insert("cutsim-token", token);
        let Ok(response) = HapticsClient::new(channel).stream(request).await else { continue };
        let mut feedback = response.into_inner();
        connected.store(true, Ordering::Release);
        backoff = Duration::from_millis(100);
        let mut last_echo = 0;
        loop {
            let next = tokio::time::timeout(Duration::from_millis(100), feedback.message()).await;
            if shutdown.load(Ordering::Acquire) {
                break;
            }
            match next {
                Ok(Ok(Some(f))) if f.tool == target.tool => {
                    let now = Instant::now();
                    let force = f.force_n.map_or(V3::default(), |v| V3(v.x, v.y, v.z));
                    let resistance = f.resistance_n.map_or(V3::default(), |v| V3(v.x, v.y, v.z));
                    answer.store(Some(Arc::new(Answer { force, resistance, grasping: f.grasping, jaws_force_n: f.jaws_force_n, echo_client_time_ns: f.echo_client_time_ns, received: now })));
                    if f.echo_client_time_ns != 0 && f.echo_client_time_ns != last_echo {
                        last_echo = f.echo_client_time_ns;
                        let rtt = (now.duration_since(origin).as_nanos() as u64).saturating_sub(f.echo_client_time_ns) / 1000;
                        round_trips_us.lock().expect("rtt lock").push(rtt.min(u64::from(u32::MAX)) as u32);
                    }
                }
                Ok(Ok(Some(_))) | Err(_) => {} // another tool's feedback, or a quiet moment
                Ok(Ok(None)) | Ok(Err(_)) => break,
            }
        }
        connected.store(false, Ordering::Release);
    }
}
