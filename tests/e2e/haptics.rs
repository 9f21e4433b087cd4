//! A haptic stream of 2,000 poses through the tissue: force when in contact, none when not.

use std::time::{Duration, Instant};

use cutsim_proto::v1 as pb;
use cutsim_proto::v1::haptics_client::HapticsClient;
use tokio::sync::mpsc;
use tokio_stream_shim::ReceiverStream;

use crate::harness::*;

/// Opens a haptics stream on a session with a token; returns the sender and the response.
pub async fn open(server: &Server, session: &str, token: &str) -> (mpsc::Sender<pb::ToolCommand>, Result<tonic::Streaming<pb::ForceFeedback>, tonic::Status>) {
    open_on(server.channel().await, session, token).await
}

/// The same on a given channel.
pub async fn open_on(channel: tonic::transport::Channel, session: &str, token: &str) -> (mpsc::Sender<pb::ToolCommand>, Result<tonic::Streaming<pb::ForceFeedback>, tonic::Status>) {
    let mut client = HapticsClient::new(channel);
    let (tx, rx) = mpsc::channel(16);
    let mut request = tonic::Request::new(ReceiverStream::new(rx));
    request.metadata_mut().insert("cutsim-session", session.parse().unwrap());
    request.metadata_mut().insert("cutsim-token", token.parse().unwrap());
    let response = client.stream(request).await.map(|r| r.into_inner());
    (tx, response)
}

#[derive(Clone, Copy, PartialEq, Debug)]
enum Phase {
    Above,
    Pressing,
}

#[tokio::test]
async fn stream_of_2000_poses_gets_force_in_contact_and_none_outside() {
    let server = Server::start();
    let session = create(&server, "skin-patch", pb::SessionMode::Realtime).await;
    let (tx, response) = open(&server, &session.id, &session.control).await;
    let mut feedback = response.expect("the stream opens");

    // The probe (tool 1) at (1 cm, 1 cm): 500 poses above the skin, 1,000 pressing 3 mm
    // down and holding, 500 back above. One pose per millisecond; the pose index is
    // encoded in client_time_ns so that each feedback names the pose it answers.
    let start = Instant::now();
    let phases: Vec<(f64, Phase)> = (0..2000)
        .map(|i| match i {
            0..500 => (0.004, Phase::Above),
            500..1500 => (0.003 - 0.006 * ((i - 500) as f64 / 300.0).min(1.0), Phase::Pressing),
            _ => (0.004, Phase::Above),
        })
        .collect();
    let sender = {
        let phases = phases.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_millis(1));
            for (i, &(z, _)) in phases.iter().enumerate() {
                tick.tick().await;
                let command = pb::ToolCommand { tool: 1, pose: Some(pose(0.01, 0.01, z)), active: true, cut: false, client_time_ns: i as u64 + 1, feedback_every_steps: 1, grip: None };
                if tx.send(command).await.is_err() {
                    break;
                }
            }
            tx
        })
    };
    let mut in_contact = 0;
    let mut pressed_force: f64 = 0.0;
    let mut above_checked = 0;
    let mut received = 0;
    let (mut first_step, mut last_step) = (None, 0);
    while let Ok(Some(f)) = tokio::time::timeout(Duration::from_secs(5), feedback.message()).await.unwrap_or(Ok(None)) {
        received += 1;
        first_step.get_or_insert(f.step);
        last_step = f.step;
        assert_eq!(f.tool, 1);
        let index = f.echo_client_time_ns as usize;
        if index == 0 {
            continue;
        }
        let (z, phase) = phases[index - 1];
        let force = f.force_n.unwrap_or_default();
        match phase {
            // Above the skin after it has had time to spring back: exactly no force.
            Phase::Above if index > 1 && (index < 480 || index > 1900) => {
                assert_eq!((force.x, force.y, force.z, f.contacts), (0.0, 0.0, 0.0, 0), "pose {index} at z = {z}: {f:?}");
                above_checked += 1;
            }
            // Pressed 3 mm in and held: the skin pushes the probe back up.
            Phase::Pressing if index > 900 => {
                assert!(f.contacts > 0 && force.z > 0.0, "pose {index} at z = {z}: {f:?}");
                // Mostly vertical: the contact still acts on the nodes radially, and the few
                // nodes under the probe on the skin's foundation sit unevenly around it
                // (docs/tool-tissue.md, known gaps), which leaves a sideways share.
                assert!(force.x.hypot(force.y) < 0.25 * force.z, "pressing straight down gives a mostly vertical force: {f:?}");
                in_contact += 1;
                pressed_force = pressed_force.max(force.z);
            }
            _ => {}
        }
        if index == 2000 && f.step > 0 {
            break;
        }
    }
    let tx = sender.await.unwrap();
    drop(tx);
    let elapsed = start.elapsed();
    // One feedback per step the server took meanwhile (however fast this machine steps).
    let steps = last_step - first_step.unwrap_or(last_step) + 1;
    assert!(received as f64 >= 0.9 * steps as f64 && steps > 200, "feedback about every step: {received} for {steps} steps in {elapsed:?}");
    // Feedback follows the server's steps, not the poses: on a loaded machine the session steps
    // slower than the poses come (some are answered twice, some not at all), so each phase's
    // count scales with the steps taken. Each checked phase is about 30 % of the stream's poses
    // (pressing 901–1499, above 1–479 and 1901–2000); asking for half of that share shows both
    // were seen without asserting how fast this machine steps (an absolute 300 failed on a
    // loaded CI machine at 238 and 249).
    let share = |count: usize| count as f64 / steps as f64;
    assert!(share(in_contact) > 0.15 && share(above_checked) > 0.15, "contact {in_contact}, above {above_checked} of {steps} steps");
    assert!(pressed_force > 0.05 && pressed_force < 10.0, "pressing 3 mm into skin gives a force of {pressed_force} N");
}

/// Minimal stand-in for tokio-stream's ReceiverStream.
mod tokio_stream_shim {
    use std::pin::Pin;
    use std::task::{Context, Poll};

    pub struct ReceiverStream<T>(tokio::sync::mpsc::Receiver<T>);

    impl<T> ReceiverStream<T> {
        pub fn new(rx: tokio::sync::mpsc::Receiver<T>) -> Self {
            Self(rx)
        }
    }

    impl<T> futures_util::Stream for ReceiverStream<T> {
        type Item = T;
        fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<T>> {
            self.0.poll_recv(cx)
        }
    }
}
