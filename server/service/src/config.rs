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
        self.trusted_proxy_blocks()?;
        Ok(())
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
    /// Lets its holder list recordings and replay them (they hold every trainee's
    /// actions). When not given, one is made up at start and printed.
    pub admin_token: Option<String>,
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
            admin_token: None,
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
        Ok(config)
    }
}
