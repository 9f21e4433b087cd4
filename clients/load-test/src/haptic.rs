//! A haptic client as a device bridge runs it: one tool command per millisecond on a
//! gRPC stream (a scalpel cutting lanes across the tissue, over and over), the force
//! feedback read as it comes, and the round trip of each command measured by its echo.

use std::time::{Duration, Instant};

use cutsim_proto::v1 as pb;
use cutsim_proto::v1::haptics_client::HapticsClient;
use tokio::sync::mpsc;

/// Where the scalpel goes, from the session's bounds: lanes across x at a few y, cutting
/// to half the tissue's depth (at least 1 cm; z up), four seconds a lane.
#[derive(Clone, Copy)]
pub struct Trajectory {
    min: [f64; 3],
    max: [f64; 3],
}

const LANE_S: f64 = 4.0;

impl Trajectory {
    pub fn from_info(info: &pb::SessionInfo) -> Self {
        let v = |v: &Option<pb::Vec3>| v.as_ref().map_or([0.0; 3], |v| [v.x, v.y, v.z]);
        Self { min: v(&info.bounds_min_m), max: v(&info.bounds_max_m) }
    }

    /// (position, cutting) at `t` seconds.
    pub fn at(&self, t: f64) -> ([f64; 3], bool) {
        let lane = (t / LANE_S).floor() as i64;
        let phase = t - lane as f64 * LANE_S;
        let size = [0, 1, 2].map(|k| self.max[k] - self.min[k]);
        let y = self.min[1] + size[1] * (0.2 + 0.15 * (lane.rem_euclid(5)) as f64);
        let (x0, x1) = (self.min[0] + 0.2 * size[0], self.max[0] - 0.2 * size[0]);
        // Inside: half the tissue's depth, and at least 1 cm below its top, so that a
        // scalpel pressed into a thin skin punctures it (at about 7 mm of indentation,
        // docs/tool-tissue.md) before it is drawn along its lane.
        let (above, inside) = (self.max[2] + 0.01, (self.max[2] - 0.5 * size[2]).min(self.max[2] - 0.01));
        let lerp = |a: f64, b: f64, s: f64| a + (b - a) * s.clamp(0.0, 1.0);
        if phase < 0.5 {
            ([x0, y, lerp(above, inside, phase / 0.5)], true)
        } else if phase < 3.0 {
            ([lerp(x0, x1, (phase - 0.5) / 2.5), y, inside], true)
        } else {
            ([x1, y, lerp(inside, above, phase - 3.0)], false)
        }
    }
}

#[derive(Default, Debug)]
pub struct HapticStats {
    pub commands_sent: u64,
    /// Commands not sent because the stream's buffer was full (the server fell behind).
    pub commands_dropped: u64,
    pub feedback: u64,
    pub round_trips_us: Vec<u32>,
    pub errors: Vec<String>,
    /// When the client vanished on purpose (a fault case), and when it came back.
    pub vanished: Option<(Instant, Instant)>,
}

pub struct HapticTarget {
    pub grpc: String,
    pub session: String,
    pub token: String,
    pub trajectory: Trajectory,
}

struct Stream {
    // Dropping the channel closes the TCP connection: no end of stream is ever sent.
    _channel: tonic::transport::Channel,
    tx: mpsc::Sender<pb::ToolCommand>,
    feedback: tonic::Streaming<pb::ForceFeedback>,
}

async fn open(target: &HapticTarget) -> Result<Stream, String> {
    let channel = tonic::transport::Channel::from_shared(format!("http://{}", target.grpc)).map_err(|e| e.to_string())?.connect().await.map_err(|e| format!("connect: {e}"))?;
    let (tx, rx) = mpsc::channel(64);
    let mut request = tonic::Request::new(futures_util::stream::unfold(rx, |mut rx| async move { rx.recv().await.map(|c| (c, rx)) }));
    request.metadata_mut().insert("cutsim-session", target.session.parse().map_err(|_| "bad session id")?);
    request.metadata_mut().insert("cutsim-token", target.token.parse().map_err(|_| "bad token")?);
    let feedback = HapticsClient::new(channel.clone()).stream(request).await.map_err(|s| format!("open: {}", s.message()))?.into_inner();
    Ok(Stream { _channel: channel, tx, feedback })
}

fn command(position: [f64; 3], active: bool, cut: bool, client_time_ns: u64) -> pb::ToolCommand {
    pb::ToolCommand {
        tool: 0,
        pose: Some(pb::Pose { position_m: Some(pb::Vec3 { x: position[0], y: position[1], z: position[2] }), orientation: Some(pb::Quaternion { w: 1.0, x: 0.0, y: 0.0, z: 0.0 }) }),
        active,
        cut,
        client_time_ns,
        feedback_every_steps: 1,
        grip: None,
    }
}

/// Runs until `until`; at `vanish_at` it drops its connection mid-cut without a word,
/// waits half a second and comes back on a new one.
pub async fn run(target: HapticTarget, until: Instant, vanish_at: Option<Instant>) -> HapticStats {
    let mut stats = HapticStats::default();
    let origin = Instant::now();
    let mut stream = match open(&target).await {
        Ok(s) => s,
        Err(e) => {
            stats.errors.push(e);
            return stats;
        }
    };
    let mut tick = tokio::time::interval(Duration::from_millis(1));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut last_echo = 0;
    let mut vanish_at = vanish_at;
    loop {
        tokio::select! {
            _ = tick.tick() => {
                let now = Instant::now();
                if now >= until {
                    break;
                }
                if vanish_at.is_some_and(|t| now >= t) {
                    vanish_at = None;
                    drop(stream);
                    tokio::time::sleep(Duration::from_millis(500)).await;
                    stats.vanished = Some((now, Instant::now()));
                    stream = match open(&target).await {
                        Ok(s) => s,
                        Err(e) => {
                            stats.errors.push(format!("after vanishing: {e}"));
                            return stats;
                        }
                    };
                    continue;
                }
                let t = now.duration_since(origin);
                let (position, cut) = target.trajectory.at(t.as_secs_f64());
                match stream.tx.try_send(command(position, true, cut, t.as_nanos() as u64 + 1)) {
                    Ok(()) => stats.commands_sent += 1,
                    Err(mpsc::error::TrySendError::Full(_)) => stats.commands_dropped += 1,
                    Err(mpsc::error::TrySendError::Closed(_)) => {
                        stats.errors.push("the command stream closed".into());
                        return stats;
                    }
                }
            }
            message = stream.feedback.message() => match message {
                Ok(Some(f)) => {
                    stats.feedback += 1;
                    if f.echo_client_time_ns != last_echo && f.echo_client_time_ns != 0 {
                        last_echo = f.echo_client_time_ns;
                        let now = origin.elapsed().as_nanos() as u64 + 1;
                        stats.round_trips_us.push((now.saturating_sub(f.echo_client_time_ns) / 1000) as u32);
                    }
                }
                Ok(None) => {
                    stats.errors.push("the server ended the feedback stream".into());
                    return stats;
                }
                Err(status) => {
                    stats.errors.push(format!("feedback stream: {}", status.message()));
                    return stats;
                }
            }
        }
    }
    // Leave: the tool lifts out of the tissue, then the stream ends properly.
    let t = origin.elapsed();
    let (position, _) = target.trajectory.at(t.as_secs_f64());
    let _ = stream.tx.send(command(position, false, false, t.as_nanos() as u64 + 1)).await;
    drop(stream.tx);
    let drain = async { while let Ok(Some(_)) = stream.feedback.message().await {} };
    let _ = tokio::time::timeout(Duration::from_secs(2), drain).await;
    stats
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scalpel_descends_cuts_across_and_lifts_inside_the_bounds() {
        let t = Trajectory { min: [-0.05, -0.05, -0.01], max: [0.05, 0.05, 0.0] };
        let (start, cut) = t.at(0.0);
        assert!(cut && (start[2] - 0.01).abs() < 1e-12, "starts 1 cm above the top: {start:?}");
        let (inside, _) = t.at(1.0);
        assert!((inside[2] + 0.01).abs() < 1e-12, "in 1 cm thin tissue it cuts 1 cm below the top (half would not puncture skin): {inside:?}");
        let deep = Trajectory { min: [-0.05, -0.05, -0.1], max: [0.05, 0.05, 0.0] };
        assert!((deep.at(1.0).0[2] + 0.05).abs() < 1e-12, "in deep tissue at half the depth: {:?}", deep.at(1.0).0);
        let (end, _) = t.at(2.999);
        assert!(end[0] > inside[0] && end[0] <= 0.03 + 1e-12, "moves across x within the middle: {end:?}");
        let (lifted, cut) = t.at(3.999);
        assert!(!cut && lifted[2] > 0.009, "lifts out without cutting: {lifted:?}");
        let (next, _) = t.at(4.0 + 1.0);
        assert_ne!(next[1], inside[1], "the next lane is elsewhere");
        for k in 0..400 {
            let (p, _) = t.at(f64::from(k) * 0.05);
            assert!((0..2).all(|a| p[a] >= t.min[a] && p[a] <= t.max[a]), "{p:?}");
        }
    }
}
