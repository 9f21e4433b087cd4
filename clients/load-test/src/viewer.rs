//! A viewer as a client program: a real WebSocket connection that decodes ViewerFrames and
//! keeps a replica of the surface from the snapshot, the deltas and the positions (what
//! the web viewer does), so that its surface hash can be checked against the server's.
//! Used by the load test and the end-to-end tests.

use std::time::{Duration, Instant};

use cutsim_proto::v1 as pb;
use cutsim_sim::surface::{SurfaceReplica, SurfaceSnapshot, SurfaceTriangle, SurfaceVertex, TopologyDelta};
use futures_util::StreamExt;
use prost::Message;
use tokio_tungstenite::tungstenite;

type Socket = tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

pub struct Viewer {
    socket: Socket,
    pub replica: Option<SurfaceReplica>,
    pub snapshots: u32,
    pub deltas: u32,
    pub positions_frames: u32,
    pub hello: Option<pb::Hello>,
    /// The newest tools' states.
    pub last_tools: Option<pb::ToolStates>,
    pub closed: Option<String>,
    /// Frames received.
    pub frames: u64,
    /// What did not decode or apply (empty for a correct server).
    pub errors: Vec<String>,
}

pub fn snapshot_from(s: &pb::Snapshot) -> SurfaceSnapshot {
    SurfaceSnapshot {
        version: s.version,
        vertices: s
            .vertex_ids
            .iter()
            .enumerate()
            .map(|(k, &id)| SurfaceVertex { id, position_m: [s.positions_m[3 * k], s.positions_m[3 * k + 1], s.positions_m[3 * k + 2]], material: s.materials[k] as u16 })
            .collect(),
        triangles: s
            .triangle_ids
            .iter()
            .enumerate()
            .map(|(k, &id)| SurfaceTriangle { id, vertices: [s.triangle_vertices[3 * k], s.triangle_vertices[3 * k + 1], s.triangle_vertices[3 * k + 2]] })
            .collect(),
    }
}

fn delta_from(d: &pb::TopologyDelta) -> TopologyDelta {
    TopologyDelta {
        version: d.version,
        removed_triangles: d.removed_triangle_ids.clone(),
        removed_vertices: d.removed_vertex_ids.clone(),
        added_vertices: d
            .added_vertex_ids
            .iter()
            .enumerate()
            .map(|(k, &id)| SurfaceVertex { id, position_m: [d.added_positions_m[3 * k], d.added_positions_m[3 * k + 1], d.added_positions_m[3 * k + 2]], material: d.added_materials[k] as u16 })
            .collect(),
        added_triangles: d
            .added_triangle_ids
            .iter()
            .enumerate()
            .map(|(k, &id)| SurfaceTriangle { id, vertices: [d.added_triangle_vertices[3 * k], d.added_triangle_vertices[3 * k + 1], d.added_triangle_vertices[3 * k + 2]] })
            .collect(),
    }
}

impl Viewer {
    pub async fn connect(http: &str, session: &str, token: &str) -> Result<Viewer, tungstenite::Error> {
        let url = format!("ws://{http}/ws/sessions/{session}?token={token}");
        let (socket, _) = tokio_tungstenite::connect_async(url).await?;
        Ok(Self::over(socket))
    }

    /// The same over TLS (`wss://`), trusting what `tls` trusts.
    pub async fn connect_tls(http: &str, session: &str, token: &str, tls: std::sync::Arc<tokio_rustls::rustls::ClientConfig>) -> Result<Viewer, tungstenite::Error> {
        let url = format!("wss://{http}/ws/sessions/{session}?token={token}");
        let (socket, _) = tokio_tungstenite::connect_async_tls_with_config(url, None, false, Some(tokio_tungstenite::Connector::Rustls(tls))).await?;
        Ok(Self::over(socket))
    }

    fn over(socket: Socket) -> Viewer {
        Viewer { socket, replica: None, snapshots: 0, deltas: 0, positions_frames: 0, hello: None, last_tools: None, closed: None, frames: 0, errors: Vec::new() }
    }

    /// Reads and applies frames until `done` holds (true) or `timeout` passes (false).
    pub async fn pump_until(&mut self, timeout: Duration, done: impl Fn(&Viewer) -> bool) -> bool {
        let deadline = Instant::now() + timeout;
        while !done(self) {
            let left = deadline.saturating_duration_since(Instant::now());
            match tokio::time::timeout(left, self.socket.next()).await {
                Ok(Some(Ok(tungstenite::Message::Binary(bytes)))) => self.apply(&bytes),
                Ok(Some(Ok(tungstenite::Message::Close(frame)))) => {
                    self.closed = Some(frame.map(|f| f.reason.to_string()).unwrap_or_default());
                    return done(self);
                }
                Ok(Some(Ok(_))) => {}
                Ok(Some(Err(_))) | Ok(None) => return done(self),
                Err(_) => return false,
            }
        }
        true
    }

    fn apply(&mut self, bytes: &[u8]) {
        let Ok(pb::ViewerFrame { frame: Some(frame) }) = pb::ViewerFrame::decode(bytes) else {
            self.errors.push(format!("frame {} is not a ViewerFrame", self.frames));
            return;
        };
        self.frames += 1;
        match frame {
            pb::viewer_frame::Frame::Hello(h) => self.hello = Some(h),
            pb::viewer_frame::Frame::Snapshot(s) => {
                self.replica = Some(SurfaceReplica::from_snapshot(&snapshot_from(&s)));
                self.snapshots += 1;
            }
            pb::viewer_frame::Frame::Delta(d) => {
                let Some(replica) = self.replica.as_mut() else { return self.errors.push("a delta before the snapshot".into()) };
                if let Err(e) = replica.apply(&delta_from(&d)) {
                    self.errors.push(format!("delta {} does not apply: {e}", d.version));
                }
                self.deltas += 1;
            }
            pb::viewer_frame::Frame::Positions(p) => {
                let Some(replica) = self.replica.as_mut() else { return self.errors.push("positions before the snapshot".into()) };
                if p.positions_m.len() != 3 * p.id_deltas.len() {
                    return self.errors.push(format!("positions frame with {} ids and {} coordinates", p.id_deltas.len(), p.positions_m.len()));
                }
                let mut id = 0u32;
                for (k, delta) in p.id_deltas.iter().enumerate() {
                    id = id.wrapping_add(*delta);
                    replica.set_position(id, [p.positions_m[3 * k], p.positions_m[3 * k + 1], p.positions_m[3 * k + 2]]);
                }
                self.positions_frames += 1;
            }
            pb::viewer_frame::Frame::Tools(t) => self.last_tools = Some(t),
            pb::viewer_frame::Frame::Stats(_) => {}
        }
    }

    pub fn surface_hash(&self) -> Option<String> {
        self.replica.as_ref().map(|r| cutsim_sim::hash::hash_hex(r.surface_hash()))
    }

    pub fn triangles(&self) -> usize {
        self.replica.as_ref().map_or(0, |r| r.triangle_count())
    }
}
