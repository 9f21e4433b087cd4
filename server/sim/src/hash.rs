//! Deterministic 64-bit state hashing (FNV-1a over exact bit patterns).
//!
//! The same scene and the same tool inputs give the same bits, so the same hash: CI
//! bots and replays compare it. Floats are hashed by their bits, so −0.0 ≠ 0.0 and
//! any drift, however small, changes the hash.

/// FNV-1a, 64-bit. Simple, stable across platforms and Rust versions.
#[derive(Debug, Clone)]
pub struct StateHasher(u64);

impl Default for StateHasher {
    fn default() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }
}

impl StateHasher {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn write_u8(&mut self, byte: u8) {
        self.0 ^= u64::from(byte);
        self.0 = self.0.wrapping_mul(0x0000_0100_0000_01b3);
    }

    pub fn write_bytes(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u8(b);
        }
    }

    pub fn write_u32(&mut self, v: u32) {
        self.write_bytes(&v.to_le_bytes());
    }

    pub fn write_u64(&mut self, v: u64) {
        self.write_bytes(&v.to_le_bytes());
    }

    pub fn write_f64(&mut self, v: f64) {
        self.write_u64(v.to_bits());
    }

    pub fn write_f32(&mut self, v: f32) {
        self.write_u32(v.to_bits());
    }

    pub fn finish(&self) -> u64 {
        self.0
    }
}

/// What a step carries over to the next besides the nodes and the topology — the tools'
/// contact memory: friction anchors, grasps, jaws, where each tool was — written into a
/// model's state hash (crate::tissue::Tissue::state_hash), so that two states that step
/// on differently never hash the same. Lengths and `None` are written too.
pub trait HashState {
    fn hash_state(&self, h: &mut StateHasher);
}

impl HashState for f64 {
    fn hash_state(&self, h: &mut StateHasher) {
        h.write_f64(*self);
    }
}

impl HashState for bool {
    fn hash_state(&self, h: &mut StateHasher) {
        h.write_u8(u8::from(*self));
    }
}

impl HashState for u32 {
    fn hash_state(&self, h: &mut StateHasher) {
        h.write_u32(*self);
    }
}

impl HashState for u64 {
    fn hash_state(&self, h: &mut StateHasher) {
        h.write_u64(*self);
    }
}

impl HashState for usize {
    fn hash_state(&self, h: &mut StateHasher) {
        h.write_u64(*self as u64);
    }
}

impl HashState for crate::math::Vec3 {
    fn hash_state(&self, h: &mut StateHasher) {
        self.iter().for_each(|c| h.write_f64(*c));
    }
}

impl<T: HashState + ?Sized> HashState for &T {
    fn hash_state(&self, h: &mut StateHasher) {
        (**self).hash_state(h);
    }
}

impl<T: HashState> HashState for Option<T> {
    fn hash_state(&self, h: &mut StateHasher) {
        match self {
            None => h.write_u8(0),
            Some(v) => {
                h.write_u8(1);
                v.hash_state(h);
            }
        }
    }
}

impl<T: HashState> HashState for [T] {
    fn hash_state(&self, h: &mut StateHasher) {
        h.write_u64(self.len() as u64);
        self.iter().for_each(|v| v.hash_state(h));
    }
}

impl<T: HashState> HashState for Vec<T> {
    fn hash_state(&self, h: &mut StateHasher) {
        self.as_slice().hash_state(h);
    }
}

impl<T: HashState, const N: usize> HashState for [T; N] {
    fn hash_state(&self, h: &mut StateHasher) {
        self.iter().for_each(|v| v.hash_state(h));
    }
}

impl<A: HashState, B: HashState> HashState for (A, B) {
    fn hash_state(&self, h: &mut StateHasher) {
        self.0.hash_state(h);
        self.1.hash_state(h);
    }
}

impl<A: HashState, B: HashState, C: HashState> HashState for (A, B, C) {
    fn hash_state(&self, h: &mut StateHasher) {
        self.0.hash_state(h);
        self.1.hash_state(h);
        self.2.hash_state(h);
    }
}

/// The hash as the 16 hexadecimal digits reports and scripts use.
pub fn hash_hex(hash: u64) -> String {
    format!("{hash:016x}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fnv1a_reference_value() {
        // FNV-1a 64 of "a" is a published test vector.
        let mut h = StateHasher::new();
        h.write_bytes(b"a");
        assert_eq!(h.finish(), 0xaf63_dc4c_8601_ec8c);
    }

    #[test]
    fn float_bits_matter() {
        let mut a = StateHasher::new();
        a.write_f64(0.0);
        let mut b = StateHasher::new();
        b.write_f64(-0.0);
        assert_ne!(a.finish(), b.finish());
    }
}
