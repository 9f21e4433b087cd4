//! Lock-free single-value handoffs between networking and the physics thread.
//!
//! A [`SeqSlot`] holds the newest value of a small record as atomic words with a
//! sequence number (a seqlock): writing never allocates; reading never blocks the
//! reader for long — and the physics thread, which only reads commands and only writes
//! feedback, never waits on a network task: if a network writer is caught mid-write
//! (it was preempted), the physics thread keeps the previous command for this step.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering, fence};

use futures_util::task::AtomicWaker;

/// The newest value of a `W`-word record.
pub struct SeqSlot<const W: usize> {
    seq: AtomicU64,
    words: [AtomicU64; W],
}

impl<const W: usize> Default for SeqSlot<W> {
    fn default() -> Self {
        Self { seq: AtomicU64::new(0), words: std::array::from_fn(|_| AtomicU64::new(0)) }
    }
}

impl<const W: usize> SeqSlot<W> {
    /// Writes a new value. Several writers may race: they take turns (on the networking
    /// side only). Returns the new sequence number (even, ≥ 2).
    pub fn write(&self, data: [u64; W]) -> u64 {
        let mut current = self.seq.load(Ordering::Relaxed);
        loop {
            if current & 1 == 1 {
                std::hint::spin_loop();
                current = self.seq.load(Ordering::Relaxed);
                continue;
            }
            match self.seq.compare_exchange_weak(current, current + 1, Ordering::Acquire, Ordering::Relaxed) {
                Ok(_) => break,
                Err(seen) => current = seen,
            }
        }
        fence(Ordering::Release);
        for (w, d) in self.words.iter().zip(data) {
            w.store(d, Ordering::Relaxed);
        }
        self.seq.store(current + 2, Ordering::Release);
        current + 2
    }

    /// Reads the value, retrying at most `attempts` times while a write is in progress.
    /// Returns the value and its sequence number (0: never written), or `None` when a
    /// writer held the slot through every attempt.
    pub fn try_read(&self, attempts: u32) -> Option<([u64; W], u64)> {
        for _ in 0..attempts {
            let before = self.seq.load(Ordering::Acquire);
            if before & 1 == 1 {
                std::hint::spin_loop();
                continue;
            }
            let data: [u64; W] = std::array::from_fn(|i| self.words[i].load(Ordering::Relaxed));
            fence(Ordering::Acquire);
            if self.seq.load(Ordering::Relaxed) == before {
                return Some((data, before));
            }
        }
        None
    }

    /// Reads the value, waiting as long as it takes (networking side only).
    pub fn read(&self) -> ([u64; W], u64) {
        loop {
            if let Some(v) = self.try_read(64) {
                return v;
            }
            std::thread::yield_now();
        }
    }

    /// Sequence number of the newest value (0: never written).
    pub fn version(&self) -> u64 {
        self.seq.load(Ordering::Acquire) & !1
    }
}

/// Wakers of the async tasks that stream feedback to haptic clients. The physics
/// thread wakes every registered task after each step; registering and waking are
/// lock-free.
pub struct Subscribers {
    slots: Vec<Subscriber>,
}

struct Subscriber {
    in_use: AtomicBool,
    waker: AtomicWaker,
}

impl Subscribers {
    pub fn new(capacity: usize) -> Self {
        Self { slots: (0..capacity).map(|_| Subscriber { in_use: AtomicBool::new(false), waker: AtomicWaker::new() }).collect() }
    }

    /// Takes a free slot; `None` when all are taken.
    pub fn join(&self) -> Option<usize> {
        self.slots.iter().position(|s| s.in_use.compare_exchange(false, true, Ordering::AcqRel, Ordering::Relaxed).is_ok())
    }

    pub fn leave(&self, slot: usize) {
        self.slots[slot].waker.take();
        self.slots[slot].in_use.store(false, Ordering::Release);
    }

    pub fn register(&self, slot: usize, waker: &std::task::Waker) {
        self.slots[slot].waker.register(waker);
    }

    /// Wakes one subscriber (its reader hit an error or finished).
    pub fn wake(&self, slot: usize) {
        self.slots[slot].waker.wake();
    }

    pub fn count(&self) -> usize {
        self.slots.iter().filter(|s| s.in_use.load(Ordering::Relaxed)).count()
    }

    /// Wakes every subscriber (from the physics thread, after a step).
    pub fn wake_all(&self) {
        for s in &self.slots {
            if s.in_use.load(Ordering::Relaxed) {
                s.waker.wake();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn reads_see_whole_writes_only() {
        let slot = Arc::new(SeqSlot::<4>::default());
        assert_eq!(slot.try_read(1), Some(([0; 4], 0)));
        let writer = {
            let slot = slot.clone();
            std::thread::spawn(move || {
                for i in 1..=100_000u64 {
                    slot.write([i; 4]);
                }
            })
        };
        let mut last = 0;
        while last < 100_000 {
            let (data, _) = slot.read();
            assert!(data.iter().all(|&w| w == data[0]), "torn read {data:?}");
            assert!(data[0] >= last, "went back in time");
            last = data[0];
        }
        writer.join().unwrap();
        assert_eq!(slot.version(), 200_000);
    }

    #[test]
    fn subscribers_take_and_free_slots() {
        let subs = Subscribers::new(2);
        let a = subs.join().unwrap();
        let b = subs.join().unwrap();
        assert_ne!(a, b);
        assert!(subs.join().is_none());
        subs.leave(a);
        assert_eq!(subs.count(), 1);
        assert_eq!(subs.join(), Some(a));
    }
}
