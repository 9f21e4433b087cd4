//! Admission: a session is let in only when the machine has room for it — a slot among
//! `max_sessions`, a core for a real-time session, and memory for its tissue — and the
//! room is reserved before the tissue is built, so that concurrent requests cannot all
//! pass the check and then all be built.

use std::sync::{Arc, Mutex};

use cutsim_sim::scene::Footprint;

use crate::error::ApiError;

/// What the server admits.
#[derive(Debug, Clone, Copy)]
pub struct Capacity {
    pub max_sessions: usize,
    pub max_realtime_sessions: usize,
    /// Memory left to the machine and the server, bytes.
    pub memory_reserve_bytes: u64,
}

#[derive(Debug, Default)]
struct Held {
    sessions: usize,
    realtime: usize,
    /// Tissues being built: their memory does not show as used yet.
    building_bytes: u64,
}

/// The room the server's sessions hold.
pub struct Admission {
    capacity: Capacity,
    held: Mutex<Held>,
    /// Memory the machine has available now, bytes (None: unknown, not checked).
    available_memory: Box<dyn Fn() -> Option<u64> + Send + Sync>,
}

impl std::fmt::Debug for Admission {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Admission").field("capacity", &self.capacity).field("held", &self.held).finish_non_exhaustive()
    }
}

/// A session's room; given back when dropped (the session closed, failed or was never
/// built).
#[derive(Debug)]
pub struct Slot {
    admission: Arc<Admission>,
    realtime: bool,
    building_bytes: u64,
}

impl Admission {
    pub fn new(capacity: Capacity) -> Arc<Self> {
        Self::with_memory_probe(capacity, Box::new(available_memory_bytes))
    }

    pub fn with_memory_probe(capacity: Capacity, probe: Box<dyn Fn() -> Option<u64> + Send + Sync>) -> Arc<Self> {
        Arc::new(Self { capacity, held: Mutex::new(Held::default()), available_memory: probe })
    }

    /// Reserves room for a session, or says what is full.
    pub fn admit(self: &Arc<Self>, realtime: bool, footprint: &Footprint) -> Result<Slot, ApiError> {
        let mut held = self.held.lock().expect("admission lock");
        let c = &self.capacity;
        if held.sessions >= c.max_sessions {
            return Err(ApiError::exhausted("sessions", format!("sessions: the server holds its maximum of {} sessions; close one first", c.max_sessions)));
        }
        if realtime && held.realtime >= c.max_realtime_sessions {
            return Err(ApiError::exhausted("cores", format!(
                "cores: {} real-time sessions already run, one per core this server has for them (max_realtime_sessions); \
                 close one, or use a lockstep session for scripts",
                held.realtime
            )));
        }
        if let Some(available) = (self.available_memory)() {
            let free = available.saturating_sub(held.building_bytes).saturating_sub(c.memory_reserve_bytes);
            if footprint.bytes > free {
                return Err(ApiError::exhausted("memory", format!(
                    "memory: the scene needs about {} MiB ({}), and {} MiB are available beyond the {} MiB kept free",
                    footprint.bytes >> 20,
                    footprint.basis,
                    free >> 20,
                    c.memory_reserve_bytes >> 20
                )));
            }
        }
        held.sessions += 1;
        held.realtime += usize::from(realtime);
        held.building_bytes += footprint.bytes;
        Ok(Slot { admission: self.clone(), realtime, building_bytes: footprint.bytes })
    }

    /// (sessions, real-time sessions) holding room now.
    pub fn held(&self) -> (usize, usize) {
        let held = self.held.lock().expect("admission lock");
        (held.sessions, held.realtime)
    }
}

impl Slot {
    /// The tissue is built: its memory now shows as used, no longer as reserved.
    pub fn built(&mut self) {
        let mut held = self.admission.held.lock().expect("admission lock");
        held.building_bytes -= std::mem::take(&mut self.building_bytes);
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        let mut held = self.admission.held.lock().expect("admission lock");
        held.sessions -= 1;
        held.realtime -= usize::from(self.realtime);
        held.building_bytes -= self.building_bytes;
    }
}

/// MemAvailable from /proc/meminfo (Linux), bytes.
fn available_memory_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn footprint(mib: u64) -> Footprint {
        Footprint { bytes: mib << 20, basis: format!("{mib} MiB of test") }
    }

    #[test]
    fn room_is_reserved_before_the_build_and_given_back_on_drop() {
        let capacity = Capacity { max_sessions: 3, max_realtime_sessions: 1, memory_reserve_bytes: 100 << 20 };
        let admission = Admission::with_memory_probe(capacity, Box::new(|| Some(1000 << 20)));
        let realtime = admission.admit(true, &footprint(10)).unwrap();
        let refused = admission.admit(true, &footprint(10)).unwrap_err();
        assert!(matches!(&refused, ApiError::ResourceExhausted { message: m, .. } if m.starts_with("cores:")), "{refused}");
        // 1000 available − 100 kept − 10 being built − 850 being built: the next 100 do not fit.
        let mut big = admission.admit(false, &footprint(850)).unwrap();
        let refused = admission.admit(false, &footprint(100)).unwrap_err();
        assert!(matches!(&refused, ApiError::ResourceExhausted { message: m, .. } if m.starts_with("memory:") && m.contains("40 MiB are available")), "{refused}");
        big.built();
        let third = admission.admit(false, &footprint(100)).unwrap();
        let refused = admission.admit(false, &footprint(1)).unwrap_err();
        assert!(matches!(&refused, ApiError::ResourceExhausted { message: m, .. } if m.starts_with("sessions:")), "{refused}");
        assert_eq!(admission.held(), (3, 1));
        drop((realtime, big, third));
        assert_eq!(admission.held(), (0, 0));
        admission.admit(true, &footprint(10)).expect("room again");
    }
}
