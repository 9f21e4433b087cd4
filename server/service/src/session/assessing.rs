//! A live session's assessor, off the physics thread.
//!
//! After each step the physics thread pushes every tool's sample (tip, force, contacts,
//! cutting) into a lock-free ring: a few stores a tool, no allocation, no lock, no wait
//! in real time (a full ring counts the step as lost and the metrics say so). The
//! assessor thread folds the samples into the metrics ([`cutsim_sim::assessment`]) and
//! publishes them about 20 times a second through a lock-free cell that the API and the
//! viewers read. Lockstep scripts wait for room instead of losing steps, so a script's
//! metrics are always complete. Replays assess on their own thread (they keep a copy
//! of the assessor with each kept state, to seek).

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use arc_swap::{ArcSwap, ArcSwapOption};
use cutsim_sim::assessment::{Assessment, Assessor, History, Task, Timeline, ToolSample};

/// Ring capacity, in tool samples: several seconds of three tools at 1 kHz.
const RING_CAPACITY: usize = 1 << 14;
/// The assessor thread looks for samples this often…
const POLL: Duration = Duration::from_millis(2);
/// …and publishes the metrics this often while they change…
const PUBLISH_EVERY: Duration = Duration::from_millis(50);
/// …and the history (the report's figures; a larger copy) this often.
const PUBLISH_HISTORY_EVERY: Duration = Duration::from_secs(1);

/// What the physics thread sends.
#[derive(Debug, Clone, Copy)]
enum Item {
    /// Tool `tool` after a step; `last` closes the step.
    Tool { tool: u16, last: bool, sample: ToolSample },
    /// The tissue was rebuilt (a script starts): the metrics start again.
    Reset,
}

/// What viewers show of a task beside its metrics.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TaskInfo {
    pub description: String,
    /// The planned incision's points, m, flattened (x, y, z, …).
    pub plan_points_m: Vec<f32>,
    pub band_mm: f64,
}

impl TaskInfo {
    pub fn new(description: &str, task: &Task) -> Self {
        let plan = task.plan.as_ref();
        Self {
            description: description.to_owned(),
            plan_points_m: plan.map_or_else(Vec::new, |p| p.points().iter().flat_map(|q| [q.x as f32, q.y as f32, q.z as f32]).collect()),
            band_mm: plan.map_or(0.0, |p| p.band_m * 1e3),
        }
    }
}

/// The metrics as last published, with what the assessor missed.
pub struct AssessmentCell {
    current: ArcSwap<Assessment>,
    history: ArcSwap<History>,
    /// A replay's curves over its whole recording (none for live sessions).
    timeline: ArcSwapOption<Timeline>,
    lost: AtomicU64,
    /// The task, shown beside the metrics.
    pub task: TaskInfo,
    /// The task as checked against the scene (the report draws it).
    pub checked: Task,
}

impl AssessmentCell {
    pub fn new(task: TaskInfo, checked: Task) -> Arc<Self> {
        Arc::new(Self {
            current: ArcSwap::from_pointee(Assessment::default()),
            history: ArcSwap::from_pointee(History::default()),
            timeline: ArcSwapOption::empty(),
            lost: AtomicU64::new(0),
            task,
            checked,
        })
    }

    /// The newest history (at most a second older than the metrics).
    pub fn history(&self) -> Arc<History> {
        self.history.load_full()
    }

    pub fn publish_history(&self, history: &History) {
        self.history.store(Arc::new(history.clone()));
    }

    /// A replay's timeline as far as it is built.
    pub fn timeline(&self) -> Option<Arc<Timeline>> {
        self.timeline.load_full()
    }

    pub fn publish_timeline(&self, timeline: &Timeline) {
        self.timeline.store(Some(Arc::new(timeline.clone())));
    }

    /// The newest metrics.
    pub fn load(&self) -> Arc<Assessment> {
        self.current.load_full()
    }

    pub fn publish(&self, assessment: Assessment) {
        self.current.store(Arc::new(assessment));
    }

    /// Empty while every step was assessed; otherwise what was missed.
    pub fn problem(&self) -> String {
        match self.lost.load(Ordering::Relaxed) {
            0 => String::new(),
            n => format!("{n} tool samples were not assessed (the assessor fell behind the physics): the metrics are approximate"),
        }
    }
}

/// The physics thread's end.
pub struct AssessProducer {
    ring: rtrb::Producer<Item>,
    cell: Arc<AssessmentCell>,
}

impl AssessProducer {
    /// Pushes one step's samples. `wait`: wait for room (lockstep) instead of counting the
    /// step as lost (real time).
    pub fn push_step(&mut self, samples: impl ExactSizeIterator<Item = ToolSample>, wait: bool) {
        let count = samples.len();
        if !wait && self.ring.slots() < count {
            self.cell.lost.fetch_add(count as u64, Ordering::Relaxed);
            return;
        }
        for (tool, sample) in samples.enumerate() {
            self.push(Item::Tool { tool: tool as u16, last: tool + 1 == count, sample });
        }
    }

    /// The metrics start again (the tissue was rebuilt). Waits for room: a reset is rare.
    pub fn reset(&mut self) {
        self.push(Item::Reset);
    }

    fn push(&mut self, mut item: Item) {
        loop {
            match self.ring.push(item) {
                Ok(()) => return,
                Err(rtrb::PushError::Full(back)) => {
                    item = back;
                    std::thread::sleep(Duration::from_micros(200));
                }
            }
        }
    }
}

/// Starts the assessor thread of a session; it ends once the producer is dropped (the
/// physics thread ended) and the ring is drained, publishing the final metrics.
pub fn start(session_id: &str, task: Task, tools: usize, time_step_s: f64, cell: Arc<AssessmentCell>) -> std::io::Result<AssessProducer> {
    let (producer, mut consumer) = rtrb::RingBuffer::new(RING_CAPACITY);
    let published = cell.clone();
    std::thread::Builder::new().name(format!("assess-{}", &session_id[..8.min(session_id.len())])).spawn(move || {
        let mut assessor = Assessor::new(task, tools, time_step_s);
        let mut step = vec![ToolSample::default(); tools];
        let mut changed = false;
        let mut history_changed = false;
        let mut last_publish = std::time::Instant::now();
        let mut last_history = std::time::Instant::now();
        loop {
            let abandoned = consumer.is_abandoned();
            while let Ok(item) = consumer.pop() {
                match item {
                    Item::Tool { tool, last, sample } => {
                        if let Some(slot) = step.get_mut(usize::from(tool)) {
                            *slot = sample;
                        }
                        if last {
                            assessor.observe(&step);
                            changed = true;
                            history_changed = true;
                        }
                    }
                    Item::Reset => {
                        assessor.reset();
                        changed = true;
                        history_changed = true;
                    }
                }
            }
            if changed && (abandoned || last_publish.elapsed() >= PUBLISH_EVERY) {
                published.publish(assessor.assessment());
                changed = false;
                last_publish = std::time::Instant::now();
            }
            if history_changed && (abandoned || last_history.elapsed() >= PUBLISH_HISTORY_EVERY) {
                published.publish_history(assessor.history());
                history_changed = false;
                last_history = std::time::Instant::now();
            }
            if abandoned {
                return;
            }
            std::thread::sleep(POLL);
        }
    })?;
    Ok(AssessProducer { ring: producer, cell })
}
