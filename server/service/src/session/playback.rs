//! Replay sessions: the physics thread plays a recording — the recorded commands at their
//! steps, through every reset — with play, pause, speed and seek. It first plays the
//! whole recording through once without showing it (the index), to draw the timeline's
//! force and metric curves and keep a copy of the state every 1,000 steps; seeking
//! then restarts from the nearest kept copy, so scrubbing costs at most 1,000 steps of
//! physics.

use std::sync::Arc;
use std::time::{Duration, Instant};

use cutsim_sim::assessment::{Assessor, Timeline, ToolSample, fill_samples};
use cutsim_sim::tissue::Tissue;
use cutsim_sim::tool::ToolCommand;

use super::hub::PlaybackState;
use super::physics::Physics;
use super::recording::{EpochEvent, Recording};
use super::{CloseReason, Control, PlaybackCommand, Status};

const KEYFRAME_EVERY: u64 = 1000;
const MAX_KEYFRAMES: usize = 256;
/// Steps the first pass through the recording (its index) plays between looks at the
/// control channel.
const INDEX_CHUNK_STEPS: u64 = 500;
/// While playing, the report's history is published this often (steps).
const HISTORY_EVERY_STEPS: u64 = 500;

/// A copy of the replay's state at a step.
struct Keyframe {
    global: u64,
    epoch: usize,
    cursor: usize,
    commands: Vec<ToolCommand>,
    tissue: Box<dyn Tissue>,
    assessor: Assessor,
}

struct Player {
    recording: Arc<Recording>,
    /// Tissue lifetime (between resets) being played, and the next event in it.
    epoch: usize,
    cursor: usize,
    /// Steps played over the whole recording.
    global: u64,
    total: u64,
    playing: bool,
    speed: f64,
    keyframes: Vec<Keyframe>,
    /// The metrics of the steps replayed (as the live session computed them).
    assessor: Assessor,
    samples: Vec<ToolSample>,
}

impl Physics {
    /// The body of a replay session's thread.
    pub fn run_replay(mut self, recording: Arc<Recording>) {
        let total = recording.total_steps();
        let tools = self.out.commands.len();
        let assessor = Assessor::new(self.scene.task(), tools, self.tissue.time_step_s());
        let start = Keyframe { global: 0, epoch: 0, cursor: 0, commands: self.out.commands.clone(), tissue: self.tissue.clone_box(), assessor: assessor.clone() };
        let mut player = Player {
            recording,
            epoch: 0,
            cursor: 0,
            global: 0,
            total,
            playing: false,
            speed: 1.0,
            keyframes: vec![start],
            assessor,
            samples: vec![ToolSample::default(); tools],
        };
        let period = self.tissue.time_step_s();
        self.show(&player);
        match self.index(&mut player, period) {
            Err(reason) => return self.finish(reason),
            Ok(deferred) => {
                for message in deferred {
                    if let Some(reason) = self.handle_replay(&mut player, message) {
                        return self.finish(reason);
                    }
                }
            }
        }
        let mut next = Instant::now();
        loop {
            while let Ok(message) = self.control.try_recv() {
                if let Some(reason) = self.handle_replay(&mut player, message) {
                    return self.finish(reason);
                }
                next = Instant::now();
            }
            if self.out.session.is_closed() {
                return self.finish(super::CloseReason::Closed);
            }
            if !player.playing {
                std::thread::park_timeout(Duration::from_millis(20));
                continue;
            }
            if player.global >= player.total {
                player.playing = false;
                self.show(&player);
                continue;
            }
            let now = Instant::now();
            if next > now {
                std::thread::park_timeout(next - now);
                continue;
            }
            self.play_step(&mut player, true);
            next += Duration::from_secs_f64(period / player.speed);
            if Instant::now() > next + Duration::from_secs_f64(5.0 * period) {
                next = Instant::now();
            }
            if player.global % self.out.publish_every == 0 {
                self.show(&player);
            }
        }
    }

    /// Answers a control message; `Some` when the session must close.
    fn handle_replay(&mut self, player: &mut Player, message: Control) -> Option<CloseReason> {
        match message {
            Control::Close(reason) => return Some(reason),
            Control::Playback(command, done) => {
                self.command(player, command);
                let _ = done.send(());
            }
            Control::Snapshot(reply) => {
                let _ = reply.send((self.snapshot(), self.tissue.step_index()));
            }
            Control::StateHash(reply) => {
                let _ = reply.send((self.tissue.step_index(), self.tissue.state_hash()));
            }
            Control::RunScript { events, .. } => {
                let _ = events.send(super::ScriptEvent::Failed("a replay session plays its recording; run scripts on another session".into()));
            }
        }
        None
    }

    /// Plays the whole recording through once, as fast as the CPU allows and without
    /// publishing, to draw its timeline (force and metric curves, published as they
    /// grow: the viewer shows the progress) and keep the states that make seeking
    /// quick; then goes back to the start. Meanwhile viewers are answered with the start
    /// and playback commands wait (they are returned, to apply in order).
    fn index(&mut self, player: &mut Player, period: f64) -> Result<Vec<Control>, CloseReason> {
        let cell = std::sync::Arc::clone(&self.out.session.assessment);
        let mut timeline = Timeline::new(player.total, period);
        cell.publish_timeline(&timeline);
        let mut deferred = Vec::new();
        while player.global < player.total {
            let end = (player.global + INDEX_CHUNK_STEPS).min(player.total);
            while player.global < end {
                self.play_step(player, false);
                timeline.observe(&player.assessor);
            }
            cell.publish_timeline(&timeline);
            let start = &player.keyframes[0].tissue;
            let mut closed = self.out.session.is_closed().then_some(CloseReason::Closed);
            while let Ok(message) = self.control.try_recv() {
                match message {
                    Control::Close(reason) => closed = Some(reason),
                    Control::Snapshot(reply) => {
                        let _ = reply.send((self.snapshot_of(start.as_ref()), start.step_index()));
                    }
                    Control::StateHash(reply) => {
                        let _ = reply.send((start.step_index(), start.state_hash()));
                    }
                    other => deferred.push(other),
                }
            }
            if let Some(reason) = closed {
                // The session ends showing what its viewers saw: the start.
                self.tissue = start.clone_box();
                return Err(reason);
            }
        }
        self.seek(player, 0);
        self.show(player);
        Ok(deferred)
    }

    fn command(&mut self, player: &mut Player, command: PlaybackCommand) {
        match command {
            PlaybackCommand::Play => player.playing = player.global < player.total,
            PlaybackCommand::Pause => player.playing = false,
            PlaybackCommand::Speed(speed) => player.speed = speed.clamp(0.05, 20.0),
            PlaybackCommand::Seek(target) => self.seek(player, target),
        }
        self.show(player);
    }

    /// Publishes a frame with the playback's state, and the metrics up to it.
    fn show(&mut self, player: &Player) {
        let cell = &self.out.session.assessment;
        cell.publish(player.assessor.assessment());
        // The history is a larger copy: twice a second while playing.
        if !player.playing || player.global % HISTORY_EVERY_STEPS == 0 {
            cell.publish_history(player.assessor.history());
        }
        self.out.status = if player.playing { Status::Running } else { Status::Idle };
        self.out.playback = Some(PlaybackState { step: player.global, total_steps: player.total, playing: player.playing, speed: player.speed });
        self.out.publish_frame(self.tissue.as_ref());
    }

    /// One recorded step: the next tissue lifetime when this one is over, the commands
    /// recorded for this step, the step. `publish`: send its deltas to viewers (false
    /// while fast-forwarding: a snapshot follows instead).
    fn play_step(&mut self, player: &mut Player, publish: bool) {
        while player.epoch + 1 < player.recording.epochs.len() && self.tissue.step_index() >= player.recording.epochs[player.epoch].steps {
            player.epoch += 1;
            player.cursor = 0;
            self.out.commands.iter_mut().for_each(|c| *c = ToolCommand::default());
            player.assessor.reset();
            let fresh = cutsim_sim::build_tissue(&self.scene).expect("the scene built when the replay started");
            if publish {
                self.replace_tissue(fresh);
            } else {
                self.tissue = fresh;
            }
        }
        let events = &player.recording.epochs[player.epoch].events;
        let step = self.tissue.step_index();
        while let Some((at, event)) = events.get(player.cursor) {
            if *at > step {
                break;
            }
            if let EpochEvent::Command { tool, command } = event {
                self.out.commands[*tool] = *command;
            }
            player.cursor += 1;
        }
        self.tissue.step(&self.out.commands, &mut self.out.feedback);
        player.global += 1;
        fill_samples(&mut player.samples, &self.out.commands, &self.out.feedback);
        player.assessor.observe(&player.samples);
        if publish {
            self.out.after_step(self.tissue.as_mut());
        } else {
            self.out.discard_deltas(self.tissue.as_mut());
        }
        if player.global % KEYFRAME_EVERY == 0
            && player.keyframes.len() < MAX_KEYFRAMES
            && player.keyframes.last().is_none_or(|k| k.global < player.global)
        {
            player.keyframes.push(Keyframe {
                global: player.global,
                epoch: player.epoch,
                cursor: player.cursor,
                commands: self.out.commands.clone(),
                tissue: self.tissue.clone_box(),
                assessor: player.assessor.clone(),
            });
        }
    }

    /// Goes to a step: from the nearest kept state at or before it, then fast-forward;
    /// viewers get the result as a snapshot.
    fn seek(&mut self, player: &mut Player, target: u64) {
        let target = target.min(player.total);
        let keyframe = player.keyframes.iter().rev().find(|k| k.global <= target).expect("the start is kept");
        if target < player.global || keyframe.global > player.global {
            self.tissue = keyframe.tissue.clone_box();
            self.out.commands.clone_from(&keyframe.commands);
            player.assessor.clone_from(&keyframe.assessor);
            (player.epoch, player.cursor, player.global) = (keyframe.epoch, keyframe.cursor, keyframe.global);
        }
        while player.global < target {
            self.play_step(player, false);
        }
        self.republish();
    }
}
