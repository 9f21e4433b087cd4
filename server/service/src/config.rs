//! Server configuration: listening addresses, directories and limits, from flags and an
//! optional JSON config file (docs/server.md).

use std::net::SocketAddr;
use std::path::PathBuf;

use serde::Deserialize;

/// Limits, each refused with a clear status when exceeded.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Limits {
    /// Sessions the server holds at once.
    pub max_sessions: usize,
    /// WebSocket viewers per session.
    pub max_viewers_per_session: usize,
    /// Haptic streams per session.
    pub max_haptic_clients_per_session: usize,
    /// Largest gRPC message the server accepts, bytes.
    pub max_message_bytes: usize,
    /// Largest inline scene JSON, bytes.
    pub max_scene_bytes: usize,
    /// Largest cut script JSON, bytes.
    pub max_script_bytes: usize,
    /// Most steps a script may run.
    pub max_script_steps: u64,
    /// How far outside the tissue's bounding box a tool may be, m.
    pub pose_margin_m: f64,
    /// Requests (gRPC calls, HTTP requests, WebSocket upgrades) per second per client
    /// address, sustained …
    pub requests_per_second_per_client: f64,
    /// … and at once.
    pub request_burst_per_client: f64,
    /// Tool commands per second on one haptic stream (two seconds' worth may arrive at once).
    pub tool_commands_per_second: f64,
    /// Requests per second from one WebSocket viewer (resync, set rate).
    pub viewer_requests_per_second: f64,
    /// Proxies (addresses or CIDR blocks) whose `X-Forwarded-For` names the client that
    /// the request rate is kept for; any other peer is the client itself.
    pub trusted_proxies: Vec<String>,
    /// Real-time sessions at once: each holds a core (default: the machine's cores).
    pub max_realtime_sessions: Option<usize>,
    /// Memory kept free for the server and the machine, MiB: a session whose estimated
    /// size does not fit in the memory available beyond it is refused.
    pub memory_reserve_mib: u64,
    /// A session with no viewer, haptic client, script or API call for this long is
    /// closed, s (0: never). Sessions opened from the command line never expire.
    pub idle_session_timeout_s: f64,
    /// A tool whose haptic client sent no command for this long is lifted out of the
    /// tissue (it stops pressing and cutting) until commands come again, ms.
    pub stale_command_ms: f64,
    /// HTTP/2 keepalive pings on gRPC connections every this many seconds; a peer that
    /// does not answer within `keepalive_timeout_s` is disconnected.
    pub keepalive_interval_s: f64,
    pub keepalive_timeout_s: f64,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_sessions: 16,
            max_viewers_per_session: 32,
            max_haptic_clients_per_session: 8,
            max_message_bytes: 4 << 20,
            max_scene_bytes: 1 << 20,
            max_script_bytes: 4 << 20,
            max_script_steps: 2_000_000,
            pose_margin_m: 1.0,
            requests_per_second_per_client: 50.0,
            request_burst_per_client: 200.0,
            tool_commands_per_second: 4000.0,
            viewer_requests_per_second: 20.0,
            trusted_proxies: Vec::new(),
            max_realtime_sessions: None,
            memory_reserve_mib: 512,
            idle_session_timeout_s: 1800.0,
            stale_command_ms: 50.0,
            keepalive_interval_s: 10.0,
            keepalive_timeout_s: 10.0,
        }
    }
}

impl Limits {
    /// Rates must be positive and finite (a zero rate would refuse everything forever).
    fn check(&self) -> Result<(), String> {
        let rates = [
            ("requests_per_second_per_client", self.requests_per_second_per_client),
            ("request_burst_per_client", self.request_burst_per_client),
            ("tool_commands_per_second", self.tool_commands_per_second),
            ("viewer_requests_per_second", self.viewer_requests_per_second),
        ];
        for (name, value) in rates {
            if !(value.is_finite() && value >= 1.0) {
                return Err(format!("{name}: must be a finite number ≥ 1, got {value}"));
            }
        }
        let ranges = [
            ("idle_session_timeout_s", self.idle_session_timeout_s, 0.0, 1e7),
            ("stale_command_ms", self.stale_command_ms, 5.0, 60_000.0),
            ("keepalive_interval_s", self.keepalive_interval_s, 1.0, 3600.0),
            ("keepalive_timeout_s", self.keepalive_timeout_s, 1.0, 3600.0),
        ];
        for (name, value, lo, hi) in ranges {
            if !(value.is_finite() && (lo..=hi).contains(&value)) {
                return Err(format!("{name}: must be within [{lo}, {hi}], got {value}"));
            }
        }
        if self.max_realtime_sessions == Some(0) {
            return Err("max_realtime_sessions: must be at least 1 (leave it out for one per core)".into());
        }
        self.trusted_proxy_blocks()?;
        Ok(())
    }

    /// Real-time sessions the machine holds: the configured number, else one per core.
    pub fn realtime_capacity(&self) -> usize {
        self.max_realtime_sessions.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
    }

    pub fn trusted_proxy_blocks(&self) -> Result<Vec<crate::rate::IpBlock>, String> {
        self.trusted_proxies.iter().enumerate().map(|(i, text)| crate::rate::IpBlock::parse(text).map_err(|e| format!("trusted_proxies[{i}]: {e}"))).collect()
    }
}

/// Everything `cutsim-server serve` needs.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ServerConfig {
    pub grpc_addr: SocketAddr,
    pub http_addr: SocketAddr,
    /// Directories of bundled scenes.
    pub scene_dirs: Vec<PathBuf>,
    /// Where session recordings are written.
    pub recordings_dir: PathBuf,
    /// The web viewer's files.
    pub viewer_dir: PathBuf,
    /// Position frames per second sent to a viewer that asks for nothing else.
    pub viewer_rate_hz: f64,
    /// Operators by name: their tokens create, list and close sessions and read
    /// recordings. When none is configured (here, as `admin_token` or in
    /// $CUTSIM_OPERATOR_TOKEN), one is made up at start and printed.
    pub operator_tokens: std::collections::BTreeMap<String, String>,
    /// The older name of an operator token (named "admin").
    pub admin_token: Option<String>,
    /// Development mode: every caller on loopback is an operator. Refused unless both
    /// listeners are on loopback addresses; said loudly at start.
    pub development_mode: bool,
    /// Origins (`https://host:port`) whose pages may open viewer WebSockets besides the
    /// server's own; a browser's upgrade from any other origin is refused.
    pub allowed_origins: Vec<String>,
    /// What is kept of recordings, and how they are written.
    pub recordings: RecordingPolicy,
    /// TLS for both listeners; plain TCP when absent (fine on loopback only).
    pub tls: Option<crate::tls::TlsConfig>,
    pub limits: Limits,
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            grpc_addr: "127.0.0.1:50051".parse().expect("valid address"),
            http_addr: "127.0.0.1:8080".parse().expect("valid address"),
            scene_dirs: crate::scene_dirs(&[]),
            recordings_dir: PathBuf::from("recordings"),
            viewer_dir: default_viewer_dir(),
            viewer_rate_hz: 60.0,
            operator_tokens: Default::default(),
            admin_token: None,
            development_mode: false,
            allowed_origins: Vec::new(),
            recordings: RecordingPolicy::default(),
            tls: None,
            limits: Limits::default(),
        }
    }
}

fn default_viewer_dir() -> PathBuf {
    let root = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../web-viewer"));
    let dist = root.join("dist");
    if dist.join("index.html").is_file() { dist } else { root }
}

impl ServerConfig {
    /// Reads a JSON config file; unknown keys are errors.
    pub fn load(path: &std::path::Path) -> Result<Self, String> {
        let text = std::fs::read_to_string(path).map_err(|e| format!("cannot read config {}: {e}", path.display()))?;
        let de = &mut serde_json::Deserializer::from_str(&text);
        let config: Self = serde_path_to_error::deserialize(de).map_err(|e| format!("{}: {}: {}", path.display(), e.path(), e.inner()))?;
        config.limits.check().map_err(|e| format!("{}: limits.{e}", path.display()))?;
        config.recordings.check().map_err(|e| format!("{}: recordings.{e}", path.display()))?;
        Ok(config)
    }

    /// The operators' tokens by name: the configured ones, `admin_token` (as "admin")
    /// and $CUTSIM_OPERATOR_TOKEN (as "env").
    pub fn operator_token_list(&self) -> Vec<(String, String)> {
        let mut list: Vec<(String, String)> = self.operator_tokens.iter().map(|(n, t)| (n.clone(), t.clone())).collect();
        if let Some(admin) = &self.admin_token {
            list.push(("admin".into(), admin.clone()));
        }
        if let Ok(token) = std::env::var(OPERATOR_TOKEN_ENV) {
            if !token.is_empty() {
                list.push(("env".into(), token));
            }
        }
        list
    }

    /// Development mode opens operator calls to loopback callers: only when nobody
    /// else can reach the listeners.
    pub fn check_development_mode(&self) -> Result<(), String> {
        if self.development_mode && !(self.grpc_addr.ip().is_loopback() && self.http_addr.ip().is_loopback()) {
            return Err(format!(
                "development mode needs both listeners on loopback (127.0.0.1 or ::1); grpc_addr is {} and http_addr {}",
                self.grpc_addr, self.http_addr
            ));
        }
        Ok(())
    }
}

/// The environment variable that gives the server (and cut-bot) an operator token.
pub const OPERATOR_TOKEN_ENV: &str = "CUTSIM_OPERATOR_TOKEN";

/// Recordings: how long they are kept, how much disk they may take, how they are written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RecordingPolicy {
    /// Recordings of closed sessions older than this are deleted, days (0: kept forever).
    pub max_age_days: f64,
    /// When recordings take more than this, the oldest of closed sessions are deleted, MiB
    /// (0: no limit).
    pub max_total_mib: f64,
    /// Written data is forced to the disk (fdatasync) at least this often, ms: at most
    /// this much is lost in a power cut (a killed server loses at most 5 ms).
    pub sync_every_ms: f64,
    /// A real-time session writes its state hash into its recording every this many
    /// steps, so that a replay checks it got there (0: only at the end).
    pub checkpoint_every_steps: u64,
}

impl Default for RecordingPolicy {
    fn default() -> Self {
        Self { max_age_days: 30.0, max_total_mib: 10240.0, sync_every_ms: 1000.0, checkpoint_every_steps: 10_000 }
    }
}

impl RecordingPolicy {
    fn check(&self) -> Result<(), String> {
        let ranges = [
            ("max_age_days", self.max_age_days, 0.0, 1e5),
            ("max_total_mib", self.max_total_mib, 0.0, 1e9),
            ("sync_every_ms", self.sync_every_ms, 5.0, 3_600_000.0),
        ];
        for (name, value, lo, hi) in ranges {
            if !(value.is_finite() && (lo..=hi).contains(&value)) {
                return Err(format!("{name}: must be within [{lo}, {hi}], got {value}"));
            }
        }
        if self.checkpoint_every_steps != 0 && self.checkpoint_every_steps < 100 {
            return Err(format!("checkpoint_every_steps: 0 (end only) or at least 100, got {}", self.checkpoint_every_steps));
        }
        Ok(())
    }
}
