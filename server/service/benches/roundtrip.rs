//! The whole haptic loop through the real server over loopback: a client sends a pose
//! every millisecond for 10 s and measures the round trip to the force that answers it
//! (transport, the wait for the step, the physics step itself), with 0, 1 and 20 viewers
//! attached, on the default scene; with 0 and 20 viewers on the CT liver at level 2 under
//! a multirate schedule (deformation every 33 ms; needs the shared data); then the
//! lockstep script throughput. The client paces its poses like the haptic bridge's servo
//! loop and prints that pacing (the interval between poses, p1 and p99).
//!
//! Run: `cargo bench -p cutsim-server --bench roundtrip` (add `-- --quick` for 2 s runs).

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use cutsim_proto::v1 as pb;
use cutsim_proto::v1::haptics_client::HapticsClient;
use cutsim_proto::v1::scripts_client::ScriptsClient;
use cutsim_proto::v1::sessions_client::SessionsClient;
use cutsim_sim::stats::LatencyHistogram;
use futures_util::StreamExt;
use std::io::BufRead;

/// The server's thread-scheduling helpers (the client paces and reads as the server's own
/// threads are told to).
#[path = "../src/priority.rs"]
#[allow(dead_code, unused_imports)]
mod priority;

fn start_server() -> (std::process::Child, String, String) {
    let recordings = std::env::temp_dir().join(format!("cutsim-bench-{}", std::process::id()));
    let mut child = Command::new(env!("CARGO_BIN_EXE_cutsim-server"))
        .args(["serve", "--no-session", "--grpc-addr", "127.0.0.1:0", "--http-addr", "127.0.0.1:0", "--recordings-dir"])
        .arg(&recordings)
        .env("RUST_LOG", "warn")
        .env("CUTSIM_OPERATOR_TOKEN", OPERATOR)
        .stdout(Stdio::piped())
        .spawn()
        .expect("server starts");
    let mut lines = std::io::BufReader::new(child.stdout.take().unwrap()).lines();
    let (mut grpc, mut http) = (String::new(), String::new());
    while grpc.is_empty() || http.is_empty() {
        let line = lines.next().unwrap().unwrap();
        if let Some(a) = line.strip_prefix("grpc listening on ") {
            grpc = a.to_owned();
        }
        if let Some(a) = line.strip_prefix("http listening on ") {
            http = a.to_owned();
        }
    }
    std::thread::spawn(move || for _ in lines {});
    (child, grpc, http)
}

/// The operator token the benchmark's server is started with.
const OPERATOR: &str = "roundtrip-bench-operator-0123456789";

fn authed<T>(m: T, token: &str) -> tonic::Request<T> {
    let mut r = tonic::Request::new(m);
    r.metadata_mut().insert("cutsim-token", token.parse().unwrap());
    r
}

/// What a round-trip run presses on: the session's scene and where the probe (tool 1)
/// rests, its tip moving ±2 mm along x around there so that every step works.
#[derive(Clone)]
struct Target {
    name: String,
    scene: pb::create_session_request::Scene,
    tip: [f64; 3],
}

/// The default scene: the probe resting 1.5 mm into the skin.
fn skin_patch() -> Target {
    Target { name: "skin-patch".into(), scene: pb::create_session_request::Scene::SceneName("skin-patch".into()), tip: [0.01, 0.01, -0.0015] }
}

/// The CT liver at level 2 under a multirate schedule (deformation every 33 ms,
/// multigrid), the probe pressed 1 mm into its broad top; None without the shared data.
fn liver_multirate() -> Option<Target> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/liver.json");
    let mut json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let spec = &mut json["model"]["branched-grid"];
    spec["level"] = 2.into();
    spec["solver"]["preconditioner"] = "multigrid".into();
    spec["schedule"] = serde_json::json!({ "multirate": { "deformation_every_steps": 33 } });
    let text = json.to_string();
    let scene = cutsim_sim::scene::Scene::from_json_str(&text, "liver (multirate)", path.parent()).ok()?;
    let cutsim_sim::scene::ModelSpec::BranchedGrid(spec) = &scene.model else { return None };
    let top = cutsim_sim::grid::build_from_scene(&scene, spec).ok()?.broad_top()?;
    Some(Target { name: "liver L2, deformation every 33 ms".into(), scene: pb::create_session_request::Scene::SceneJson(text), tip: [top.x, top.y, top.z + 0.005 - 0.001] })
}

async fn round_trips(grpc: &str, http: &str, target: &Target, viewers: usize, seconds: f64, browsers: &tokio::runtime::Handle) {
    let channel = tonic::transport::Channel::from_shared(format!("http://{grpc}")).unwrap().connect().await.unwrap();
    let created = SessionsClient::new(channel.clone())
        .create_session(authed(pb::CreateSessionRequest { scene: Some(target.scene.clone()), mode: 1, label: "bench".into() }, OPERATOR))
        .await
        .unwrap()
        .into_inner();
    let id = created.session.unwrap().id;
    let mut viewer_tasks = Vec::new();
    for _ in 0..viewers {
        let url = format!("ws://{http}/ws/sessions/{id}?token={}", created.observe_token);
        let (mut socket, _) = tokio_tungstenite::connect_async(url).await.unwrap();
        viewer_tasks.push(browsers.spawn(async move {
            let mut bytes = 0usize;
            while let Some(Ok(m)) = socket.next().await {
                bytes += m.len();
            }
            bytes
        }));
    }
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    let mut request = tonic::Request::new(futures_util::stream::unfold(rx, |mut rx| async move { rx.recv().await.map(|c| (c, rx)) }));
    request.metadata_mut().insert("cutsim-session", id.parse().unwrap());
    request.metadata_mut().insert("cutsim-token", created.control_token.parse().unwrap());
    let mut feedback = HapticsClient::new(channel.clone()).stream(request).await.unwrap().into_inner();
    let origin = Instant::now();
    let tip = target.tip;
    // The poses are paced like a device bridge's servo loop (clients/haptic-bridge): a
    // thread of its own with precise timers against absolute 1 ms deadlines, not a
    // runtime's timer wheel (whose millisecond ticks come in pairs and gaps).
    let sender = std::thread::spawn(move || {
        priority::precise_timers();
        let period = Duration::from_millis(1);
        let end = Instant::now() + Duration::from_secs_f64(seconds);
        let mut pacing = LatencyHistogram::new();
        let (mut next, mut previous) = (Instant::now(), None::<Instant>);
        let mut i = 0u64;
        while next < end {
            let now = Instant::now();
            if next > now {
                std::thread::sleep(next - now);
            }
            let x = tip[0] + 0.002 * ((i as f64) * 0.01).sin();
            let pose = pb::Pose { position_m: Some(pb::Vec3 { x, y: tip[1], z: tip[2] }), orientation: Some(pb::Quaternion { w: 1.0, x: 0.0, y: 0.0, z: 0.0 }) };
            let sent = Instant::now();
            let sent_ns = (sent - origin).as_nanos() as u64 + 1;
            if let Some(p) = previous.replace(sent) {
                pacing.record_ns((sent - p).as_nanos() as u64);
            }
            if tx.blocking_send(pb::ToolCommand { tool: 1, pose: Some(pose), active: true, cut: false, client_time_ns: sent_ns, feedback_every_steps: 1, grip: None }).is_err() {
                break;
            }
            i += 1;
            next += period;
        }
        (i, pacing)
    });
    let mut rtt = LatencyHistogram::new();
    let mut server_side = LatencyHistogram::new();
    let mut last_echo = 0;
    let mut answers = 0u64;
    loop {
        let Ok(Ok(Some(f))) = tokio::time::timeout(Duration::from_millis(500), feedback.message()).await else { break };
        answers += 1;
        if f.echo_client_time_ns != 0 && f.echo_client_time_ns != last_echo {
            // First feedback that used this pose: its round trip.
            last_echo = f.echo_client_time_ns;
            rtt.record_ns(origin.elapsed().as_nanos() as u64 + 1 - f.echo_client_time_ns);
            server_side.record_ns((f.server_latency_us * 1e3) as u64);
        }
        if sender.is_finished() && answers > 0 && f.echo_client_time_ns == last_echo && rtt.count() > 100 {
            // Drain a little after the last pose, then stop.
            if tokio::time::timeout(Duration::from_millis(20), feedback.message()).await.is_err() {
                break;
            }
        }
    }
    let (sent, pacing) = sender.join().unwrap();
    let info = SessionsClient::new(channel.clone())
        .get_session(authed(pb::GetSessionRequest { session_id: id.clone(), with_state_hash: false }, &created.observe_token))
        .await
        .unwrap()
        .into_inner();
    let waits = info.counters.as_ref().map_or(0, |c| c.solver_waits);
    let stats = info.stats.unwrap();
    SessionsClient::new(channel).close_session(authed(pb::CloseSessionRequest { session_id: id }, &created.control_token)).await.unwrap();
    let mut viewer_bytes = 0;
    for t in viewer_tasks {
        viewer_bytes += t.await.unwrap();
    }
    let us = |ns: u64| ns as f64 / 1e3;
    println!(
        "{}, {viewers:>2} viewers: {sent} poses (interval p1 {:.0} µs, p99 {:.0} µs), {} answered | round trip p50 {:.0} µs, p99 {:.0} µs, max {:.0} µs | server part p50 {:.0} µs, p99 {:.0} µs | step p50 {:.0} µs, p99 {:.0} µs, missed deadlines {} of {}, steps that waited for background work {waits} | {:.0} Hz | viewers received {:.1} MB",
        target.name,
        us(pacing.quantile_ns(0.01)),
        us(pacing.quantile_ns(0.99)),
        rtt.count(),
        us(rtt.quantile_ns(0.5)),
        us(rtt.quantile_ns(0.99)),
        us(rtt.max_ns()),
        us(server_side.quantile_ns(0.5)),
        us(server_side.quantile_ns(0.99)),
        stats.p50_us,
        stats.p99_us,
        stats.missed_deadlines,
        stats.steps,
        stats.achieved_rate_hz,
        viewer_bytes as f64 / 1e6
    );
}

async fn script_throughput(grpc: &str) {
    let channel = tonic::transport::Channel::from_shared(format!("http://{grpc}")).unwrap().connect().await.unwrap();
    let created = SessionsClient::new(channel.clone())
        .create_session(authed(pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneName("skin-patch".into())), mode: 2, label: "bench".into() }, OPERATOR))
        .await
        .unwrap()
        .into_inner();
    let id = created.session.unwrap().id;
    let script = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../../clients/cut-bot/examples/skin-patch-straight.json")).unwrap();
    let start = Instant::now();
    let mut events = ScriptsClient::new(channel)
        .run_script(authed(pb::RunScriptRequest { session_id: id, script_json: script, progress_every_steps: 0 }, &created.control_token))
        .await
        .unwrap()
        .into_inner();
    let mut report = None;
    while let Some(e) = events.message().await.unwrap() {
        if let Some(pb::script_event::Event::Report(r)) = e.event {
            report = Some(r);
        }
    }
    let r = report.unwrap();
    println!(
        "lockstep script (skin-patch straight incision, {} steps): {:.0} steps/s in the physics, {:.0} steps/s end to end over gRPC ({:.2} s), step p50 {:.0} µs, p99 {:.0} µs",
        r.steps,
        r.steps_per_second,
        r.steps as f64 / start.elapsed().as_secs_f64(),
        start.elapsed().as_secs_f64(),
        r.step_time_p50_us,
        r.step_time_p99_us
    );
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let seconds = if quick { 2.0 } else { 10.0 };
    let (mut child, grpc, http) = start_server();
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    // The viewers stand in for browsers on other machines: their reading runs on a thread
    // of its own in the idle class, taking only the CPU the server and the device leave
    // (on their own machines it would take none of it).
    let browsers = tokio::runtime::Builder::new_multi_thread().worker_threads(1).on_thread_start(priority::yield_to_real_time).enable_all().build().unwrap();
    println!("haptic round trip through cutsim-server over loopback, 1 kHz poses for {seconds} s (release)");
    let skin = skin_patch();
    let liver = liver_multirate();
    runtime.block_on(async {
        for viewers in [0, 1, 20] {
            round_trips(&grpc, &http, &skin, viewers, seconds, browsers.handle()).await;
        }
        match &liver {
            Some(liver) => {
                for viewers in [0, 20] {
                    round_trips(&grpc, &http, liver, viewers, seconds, browsers.handle()).await;
                }
            }
            None => println!("liver (multirate): skipped, the shared data is not there"),
        }
        script_throughput(&grpc).await;
    });
    let _ = child.kill();
}
