//! A tiny 3-vector (the bridge needs no linear-algebra library).

use std::ops::{Add, Mul, Neg, Sub};

#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct V3(pub f64, pub f64, pub f64);

impl V3 {
    pub fn norm(self) -> f64 {
        (self.0 * self.0 + self.1 * self.1 + self.2 * self.2).sqrt()
    }
    pub fn dot(self, o: V3) -> f64 {
        self.0 * o.0 + self.1 * o.1 + self.2 * o.2
    }
    pub fn is_finite(self) -> bool {
        self.0.is_finite() && self.1.is_finite() && self.2.is_finite()
    }
}

impl Add for V3 {
    type Output = V3;
    fn add(self, o: V3) -> V3 {
        V3(self.0 + o.0, self.1 + o.1, self.2 + o.2)
    }
}

impl Sub for V3 {
    type Output = V3;
    fn sub(self, o: V3) -> V3 {
        V3(self.0 - o.0, self.1 - o.1, self.2 - o.2)
    }
}

impl Mul<f64> for V3 {
    type Output = V3;
    fn mul(self, s: f64) -> V3 {
        V3(self.0 * s, self.1 * s, self.2 * s)
    }
}

impl Neg for V3 {
    type Output = V3;
    fn neg(self) -> V3 {
        V3(-self.0, -self.1, -self.2)
    }
}

/// A unit quaternion (w, x, y, z).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Quat(pub f64, pub f64, pub f64, pub f64);

impl Default for Quat {
    fn default() -> Self {
        Quat(1.0, 0.0, 0.0, 0.0)
    }
}

impl Quat {
    pub fn mul(self, o: Quat) -> Quat {
        let Quat(a1, b1, c1, d1) = self;
        let Quat(a2, b2, c2, d2) = o;
        Quat(
            a1 * a2 - b1 * b2 - c1 * c2 - d1 * d2,
            a1 * b2 + b1 * a2 + c1 * d2 - d1 * c2,
            a1 * c2 - b1 * d2 + c1 * a2 + d1 * b2,
            a1 * d2 + b1 * c2 - c1 * b2 + d1 * a2,
        )
    }
    pub fn conjugate(self) -> Quat {
        Quat(self.0, -self.1, -self.2, -self.3)
    }
    pub fn normalized(self) -> Quat {
        let n = (self.0 * self.0 + self.1 * self.1 + self.2 * self.2 + self.3 * self.3).sqrt();
        if n > 0.0 && n.is_finite() { Quat(self.0 / n, self.1 / n, self.2 / n, self.3 / n) } else { Quat::default() }
    }
    /// Rotates a vector.
    pub fn rotate(self, v: V3) -> V3 {
        let p = self.mul(Quat(0.0, v.0, v.1, v.2)).mul(self.conjugate());
        V3(p.1, p.2, p.3)
    }
}
