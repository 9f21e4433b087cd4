#![allow(dead_code)] // shared by several test binaries; each uses a part
//! Starting the real `cutsim-server` binary on free loopback ports, and small client
//! helpers shared by the end-to-end tests.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use cutsim_proto::v1 as pb;
use cutsim_proto::v1::sessions_client::SessionsClient;
use tonic::transport::Channel;

/// The cutsim-server binary: cargo's, in the server's own tests; otherwise the one
/// `cargo test --workspace` built beside this test binary.
pub fn server_binary() -> PathBuf {
    if let Some(path) = option_env!("CARGO_BIN_EXE_cutsim-server") {
        return PathBuf::from(path);
    }
    let exe = std::env::current_exe().expect("the test binary's path");
    let dir = exe.parent().and_then(Path::parent).expect("target/<profile>/deps");
    let server = dir.join("cutsim-server");
    assert!(server.is_file(), "{} not found: run the tests with `cargo test --workspace` (or `cargo build -p cutsim-server` first)", server.display());
    server
}

pub fn repo(relative: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..").join(relative)
}

/// A fresh directory under the system temp dir, removed when dropped.
pub struct TempDir(pub PathBuf);

impl TempDir {
    pub fn new(tag: &str) -> Self {
        static COUNT: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let n = COUNT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.subsec_nanos());
        let dir = std::env::temp_dir().join(format!("cutsim-{tag}-{}-{n}-{nanos}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        Self(dir)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// The operator token every test server is started with ($CUTSIM_OPERATOR_TOKEN):
/// creating, listing and closing sessions need it.
pub const OPERATOR: &str = "e2e-operator-token-0123456789abcdef";

/// A request with the operator token in its metadata.
pub fn operator<T>(message: T) -> tonic::Request<T> {
    authed(message, OPERATOR)
}

/// A running server process, killed when dropped.
pub struct Server {
    child: Child,
    pub grpc: String,
    pub http: String,
    pub recordings: TempDir,
    /// The server's stdout lines (kept so that the reader thread keeps draining the pipe).
    pub _lines: mpsc::Receiver<String>,
}

impl Server {
    /// Starts the server with no session open.
    pub fn start() -> Self {
        Self::start_with(&["--no-session"])
    }

    pub fn start_with(extra: &[&str]) -> Self {
        Self::start_with_env(extra, &[])
    }

    /// Starts the server with more environment variables (e.g. fault injection).
    pub fn start_with_env(extra: &[&str], env: &[(&str, &str)]) -> Self {
        let recordings = TempDir::new("recordings");
        let mut child = Command::new(server_binary())
            .args(["serve", "--grpc-addr", "127.0.0.1:0", "--http-addr", "127.0.0.1:0", "--recordings-dir"])
            .arg(&recordings.0)
            .args(extra)
            .env("RUST_LOG", "warn")
            .env("CUTSIM_OPERATOR_TOKEN", OPERATOR)
            .envs(env.iter().copied())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("the server binary starts");
        let stdout = child.stdout.take().unwrap();
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let (mut grpc, mut http) = (None, None);
        while grpc.is_none() || http.is_none() {
            let line = lines.recv_timeout(Duration::from_secs(60)).expect("the server prints its addresses");
            if let Some(a) = line.strip_prefix("grpc listening on ") {
                grpc = Some(a.trim().to_owned());
            }
            if let Some(a) = line.strip_prefix("http listening on ") {
                http = Some(a.trim().to_owned());
            }
        }
        Self { child, grpc: grpc.unwrap(), http: http.unwrap(), recordings, _lines: lines }
    }

    pub async fn channel(&self) -> Channel {
        Channel::from_shared(format!("http://{}", self.grpc)).unwrap().connect().await.expect("gRPC connects")
    }

    pub async fn sessions(&self) -> SessionsClient<Channel> {
        SessionsClient::new(self.channel().await)
    }

    /// SIGKILL: no cleanup at all.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A request with the token in its metadata.
pub fn authed<T>(message: T, token: &str) -> tonic::Request<T> {
    let mut r = tonic::Request::new(message);
    r.metadata_mut().insert("cutsim-token", token.parse().unwrap());
    r
}

#[derive(Debug)]
pub struct Created {
    pub id: String,
    pub control: String,
    pub observe: String,
    pub info: pb::SessionInfo,
}

pub async fn create(server: &Server, scene: &str, mode: pb::SessionMode) -> Created {
    let r = server
        .sessions()
        .await
        .create_session(operator(pb::CreateSessionRequest {
            scene: Some(pb::create_session_request::Scene::SceneName(scene.into())),
            mode: mode as i32,
            label: "e2e".into(),
        }))
        .await
        .expect("session created")
        .into_inner();
    let info = r.session.unwrap();
    Created { id: info.id.clone(), control: r.control_token, observe: r.observe_token, info }
}

/// A bundled scene's JSON, edited.
pub fn inline(scene: &str, edit: impl FnOnce(&mut serde_json::Value)) -> String {
    let mut value: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(repo(&format!("server/scenes/{scene}.json"))).unwrap()).unwrap();
    edit(&mut value);
    value.to_string()
}

/// A session on an inline scene.
pub async fn create_inline(server: &Server, json: String, mode: pb::SessionMode) -> Result<Created, tonic::Status> {
    let r = server
        .sessions()
        .await
        .create_session(operator(pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneJson(json)), mode: mode as i32, label: "e2e".into() }))
        .await?
        .into_inner();
    let info = r.session.unwrap();
    Ok(Created { id: info.id.clone(), control: r.control_token, observe: r.observe_token, info })
}

pub fn pose(x: f64, y: f64, z: f64) -> pb::Pose {
    pb::Pose { position_m: Some(pb::Vec3 { x, y, z }), orientation: Some(pb::Quaternion { w: 1.0, x: 0.0, y: 0.0, z: 0.0 }) }
}

pub fn example_script(name: &str) -> String {
    std::fs::read_to_string(repo(&format!("clients/cut-bot/examples/{name}"))).unwrap()
}

/// Runs a script over gRPC and returns its report (the last event).
pub async fn run_script(server: &Server, session: &Created, script: &str) -> Result<pb::ScriptReport, tonic::Status> {
    let mut client = cutsim_proto::v1::scripts_client::ScriptsClient::new(server.channel().await);
    let request = authed(pb::RunScriptRequest { session_id: session.id.clone(), script_json: script.into(), progress_every_steps: 0 }, &session.control);
    let mut events = client.run_script(request).await?.into_inner();
    let mut report = None;
    let mut progress = 0;
    while let Some(event) = events.message().await? {
        match event.event {
            Some(pb::script_event::Event::Progress(_)) => progress += 1,
            Some(pb::script_event::Event::Report(r)) => report = Some(r),
            None => {}
        }
    }
    assert!(progress > 0, "progress events stream while the script runs");
    Ok(report.expect("the last event is the report"))
}

/// An HTTP/1.1 response as a test reads it.
pub struct HttpResponse {
    pub status: u16,
    /// The header block, as sent.
    pub head: String,
    pub body: String,
}

impl HttpResponse {
    /// A header's value (case-insensitive name).
    pub fn header(&self, name: &str) -> Option<&str> {
        self.head.lines().find_map(|l| l.split_once(':').filter(|(n, _)| n.trim().eq_ignore_ascii_case(name)).map(|(_, v)| v.trim()))
    }
}

/// A plain HTTP/1.1 request over a TCP socket (no HTTP client dependency needed).
pub async fn http_call(addr: &str, method: &str, path: &str, headers: &[(&str, &str)], body: &str) -> HttpResponse {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    let extra: String = headers.iter().map(|(n, v)| format!("{n}: {v}\r\n")).collect();
    let request = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n{extra}content-length: {}\r\n\r\n{body}", body.len());
    stream.write_all(request.as_bytes()).await.unwrap();
    let mut buf = Vec::new();
    stream.read_to_end(&mut buf).await.unwrap();
    let text = String::from_utf8_lossy(&buf).into_owned();
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let status = head.split_whitespace().nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    HttpResponse { status, head: head.to_owned(), body: body.to_owned() }
}

/// `method path` with a token in the `cutsim-token` header: (status, body).
pub async fn http_request(addr: &str, method: &str, path: &str, token: Option<&str>) -> (u16, String) {
    let headers: Vec<(&str, &str)> = token.map(|t| ("cutsim-token", t)).into_iter().collect();
    let r = http_call(addr, method, path, &headers, "").await;
    (r.status, r.body)
}

/// Waits until a session's recording holds the checkpoint of `step` (at most 10 s). The
/// recorder's thread flushes every few milliseconds, but on a loaded two-core machine it
/// can be held up longer than any fixed wait (a fixed 200 ms once lost the checkpoint).
pub async fn wait_for_checkpoint(recording: &Path, step: u64) {
    let holds_it = |text: String| {
        text.lines().filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok()).any(|l| l["t"] == "check" && l["step"] == step)
    };
    let waited = std::time::Instant::now();
    while !std::fs::read_to_string(recording).is_ok_and(holds_it) {
        assert!(waited.elapsed() < Duration::from_secs(10), "the checkpoint of step {step} never reached the recording {}", recording.display());
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Waits until a real-time session's step is past `target` (at most 10 s) and returns the
/// step read. "The session still steps" is a fact about behaviour; how many steps a fixed
/// sleep sees is one about the machine's load, so the tests poll for it instead.
pub async fn wait_for_step_past(server: &Server, session: &Created, target: u64) -> u64 {
    let waited = std::time::Instant::now();
    loop {
        let request = pb::GetSessionRequest { session_id: session.id.clone(), with_state_hash: false };
        let step = server.sessions().await.get_session(authed(request, &session.observe)).await.expect("the session answers").into_inner().step;
        if step > target {
            return step;
        }
        assert!(waited.elapsed() < Duration::from_secs(10), "session {} stopped stepping: at step {step} after 10 s, waiting for {target}", session.id);
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}
