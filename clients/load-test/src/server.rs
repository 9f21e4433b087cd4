//! The server under test: the real `cutsim-server` binary, started on free loopback ports
//! with a config of the load test's own, killed with SIGKILL when asked or dropped.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use anyhow::{Context, anyhow, bail};
use cutsim_proto::v1 as pb;
use cutsim_proto::v1::sessions_client::SessionsClient;
use tonic::transport::Channel;

/// The operator token the load test configures (it creates sessions and replays
/// recordings after a restart).
pub const OPERATOR_TOKEN: &str = "cutsim-load-operator-token-0123456789";

/// Writes the server config: every client of the test comes from 127.0.0.1, so the
/// per-client request rate is raised out of the way (the rate limits have tests of their own).
pub fn write_config(dir: &Path) -> anyhow::Result<PathBuf> {
    let path = dir.join("server.json");
    let config = serde_json::json!({
        "operator_tokens": {"cutsim-load": OPERATOR_TOKEN},
        "limits": {
            "max_sessions": 64,
            // The capacity search adds real-time sessions past one per core on purpose.
            "max_realtime_sessions": 64,
            "requests_per_second_per_client": 100_000,
            "request_burst_per_client": 100_000,
        },
        "recordings": {"checkpoint_every_steps": crate::faults::CHECKPOINT_EVERY_STEPS},
    });
    std::fs::write(&path, serde_json::to_string_pretty(&config)?).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

pub struct ServerProcess {
    child: Child,
    pub grpc: String,
    pub http: String,
    _lines: mpsc::Receiver<String>,
}

/// How the full-disk fault fills the disk under the server's recordings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FullDisk {
    /// A real filesystem of this many bytes: a tmpfs mounted over the recordings directory
    /// in the server's own mount namespace (nobody else sees it). Writes past it fail with
    /// ENOSPC. Needs CAP_SYS_ADMIN (root).
    Tmpfs(u64),
    /// A file-size limit (RLIMIT_FSIZE) of this many bytes on the server process: writes
    /// past it fail with EFBIG where a full disk fails them with ENOSPC.
    FileSize(u64),
}

impl ServerProcess {
    /// Starts `binary serve` with no session, its recordings on a disk that fills up at
    /// `full_disk` when given.
    pub fn start(binary: &Path, config: &Path, recordings: &Path, full_disk: Option<FullDisk>) -> anyhow::Result<Self> {
        let mut command = Command::new(binary);
        command
            .args(["serve", "--no-session", "--grpc-addr", "127.0.0.1:0", "--http-addr", "127.0.0.1:0", "--config"])
            .arg(config)
            .arg("--recordings-dir")
            .arg(recordings)
            .env("RUST_LOG", "warn")
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit());
        match full_disk {
            None => {}
            Some(FullDisk::FileSize(limit)) => limit_file_size(&mut command, limit),
            Some(FullDisk::Tmpfs(bytes)) => {
                std::fs::create_dir_all(recordings).with_context(|| format!("creating {}", recordings.display()))?;
                mount_tmpfs(&mut command, recordings, bytes)?;
            }
        }
        let mut child = command.spawn().with_context(|| format!("starting {}", binary.display()))?;
        let stdout = child.stdout.take().ok_or_else(|| anyhow!("no stdout"))?;
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
            let Ok(line) = lines.recv_timeout(Duration::from_secs(60)) else {
                let _ = child.kill();
                bail!("{} did not print its addresses within 60 s", binary.display());
            };
            if let Some(a) = line.strip_prefix("grpc listening on ") {
                grpc = Some(a.trim().to_owned());
            }
            if let Some(a) = line.strip_prefix("http listening on ") {
                http = Some(a.trim().to_owned());
            }
        }
        Ok(Self { child, grpc: grpc.unwrap_or_default(), http: http.unwrap_or_default(), _lines: lines })
    }

    pub async fn channel(&self) -> anyhow::Result<Channel> {
        Ok(Channel::from_shared(format!("http://{}", self.grpc))?.connect().await?)
    }

    pub async fn sessions(&self) -> anyhow::Result<SessionsClient<Channel>> {
        Ok(SessionsClient::new(self.channel().await?))
    }

    /// Still running?
    pub fn alive(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// SIGKILL: no cleanup at all.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A request with the token in its metadata.
pub fn authed<T>(message: T, token: &str) -> anyhow::Result<tonic::Request<T>> {
    let mut r = tonic::Request::new(message);
    r.metadata_mut().insert("cutsim-token", token.parse()?);
    Ok(r)
}

pub struct Created {
    pub id: String,
    pub control: String,
    pub observe: String,
    pub info: pb::SessionInfo,
}

/// Opens a session on `scene`: a bundled scene's name, or a scene file (`*.json`) sent inline.
pub async fn create(server: &ServerProcess, scene: &str, mode: pb::SessionMode, label: &str) -> anyhow::Result<Created> {
    let source = if scene.ends_with(".json") {
        let json = std::fs::read_to_string(scene).map_err(|e| anyhow!("cannot read the scene file {scene}: {e}"))?;
        pb::create_session_request::Scene::SceneJson(json)
    } else {
        pb::create_session_request::Scene::SceneName(scene.into())
    };
    let r = server
        .sessions()
        .await?
        .create_session(authed(pb::CreateSessionRequest { scene: Some(source), mode: mode as i32, label: label.into() }, OPERATOR_TOKEN)?)
        .await
        .map_err(|s| anyhow!("creating a session on {scene}: {}", s.message()))?
        .into_inner();
    let info = r.session.ok_or_else(|| anyhow!("no session in the answer"))?;
    Ok(Created { id: info.id.clone(), control: r.control_token, observe: r.observe_token, info })
}

pub async fn info(server: &ServerProcess, id: &str, token: &str, with_state_hash: bool) -> anyhow::Result<pb::SessionInfo> {
    let request = authed(pb::GetSessionRequest { session_id: id.into(), with_state_hash }, token)?;
    Ok(server.sessions().await?.get_session(request).await.map_err(|s| anyhow!("session {id}: {}", s.message()))?.into_inner())
}

/// How long an HTTP request may take. Some are long by nature: a playback seek replays
/// the recording up to its step (14,000 skin-patch steps after the SIGKILL case), which
/// on this project's 2-core host in a slow hour took over the 30 s this was before
/// (CI, 2026-11-27: both sessions' seeks timed out; a run minutes later passed).
const HTTP_DEADLINE: Duration = Duration::from_secs(120);

/// One HTTP/1.1 request on a fresh connection: (status, body).
pub async fn http(addr: &str, method: &str, path: &str, token: &str, body: &str) -> anyhow::Result<(u16, String)> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut stream = tokio::net::TcpStream::connect(addr).await?;
    let request = format!(
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\ncutsim-token: {token}\r\ncontent-type: application/json\r\ncontent-length: {}\r\n\r\n{body}",
        body.len()
    );
    stream.write_all(request.as_bytes()).await?;
    let mut buf = Vec::new();
    tokio::time::timeout(HTTP_DEADLINE, stream.read_to_end(&mut buf)).await??;
    let text = String::from_utf8_lossy(&buf).into_owned();
    let status = text.split_whitespace().nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    Ok((status, text.split("\r\n\r\n").nth(1).unwrap_or_default().to_owned()))
}

fn limit_file_size(command: &mut Command, limit: u64) {
    use std::os::unix::process::CommandExt;
    // SAFETY: setrlimit is async-signal-safe; nothing else runs between fork and exec.
    unsafe {
        command.pre_exec(move || {
            let rlimit = libc::rlimit { rlim_cur: limit, rlim_max: limit };
            if libc::setrlimit(libc::RLIMIT_FSIZE, &rlimit) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
}

/// Between fork and exec: a private mount namespace with a `bytes`-sized tmpfs over `dir`.
/// Spawning fails (EPERM) where the process may not mount.
fn mount_tmpfs(command: &mut Command, dir: &Path, bytes: u64) -> anyhow::Result<()> {
    use std::ffi::CString;
    use std::os::unix::ffi::OsStrExt;
    use std::os::unix::process::CommandExt;
    let target = CString::new(dir.as_os_str().as_bytes())?;
    let options = CString::new(format!("size={bytes}"))?;
    let check = |rc: libc::c_int| if rc == 0 { Ok(()) } else { Err(std::io::Error::last_os_error()) };
    // SAFETY: unshare and mount are plain system calls; the strings were made before fork.
    unsafe {
        command.pre_exec(move || {
            check(libc::unshare(libc::CLONE_NEWNS))?;
            // Mounts made here stay in this namespace.
            check(libc::mount(c"none".as_ptr(), c"/".as_ptr(), std::ptr::null(), libc::MS_REC | libc::MS_PRIVATE, std::ptr::null()))?;
            check(libc::mount(c"tmpfs".as_ptr(), target.as_ptr(), c"tmpfs".as_ptr(), 0, options.as_ptr().cast()))
        });
    }
    Ok(())
}
