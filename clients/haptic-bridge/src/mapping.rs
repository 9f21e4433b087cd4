//! From the device's workspace to the scene: scene = R·(scale·device) + offset. Forces go
//! back through the rotation only (scaling positions already changes how stiff the
//! tissue feels, by the same factor).

use crate::vec::{Quat, V3};

#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct Workspace {
    /// Scene position of the device's origin, m.
    pub offset_m: [f64; 3],
    /// Scene metres per device metre.
    pub scale: f64,
    /// Rotation from device axes to scene axes, unit quaternion (w, x, y, z).
    pub rotation_wxyz: [f64; 4],
}

impl Default for Workspace {
    fn default() -> Self {
        Self { offset_m: [0.0; 3], scale: 1.0, rotation_wxyz: [1.0, 0.0, 0.0, 0.0] }
    }
}

impl Workspace {
    fn rotation(&self) -> Quat {
        let [w, x, y, z] = self.rotation_wxyz;
        Quat(w, x, y, z).normalized()
    }

    pub fn position(&self, device: V3) -> V3 {
        self.rotation().rotate(device * self.scale) + V3(self.offset_m[0], self.offset_m[1], self.offset_m[2])
    }

    pub fn orientation(&self, device: Quat) -> Quat {
        self.rotation().mul(device).normalized()
    }

    /// A scene force (N) in device axes.
    pub fn force_to_device(&self, scene: V3) -> V3 {
        self.rotation().conjugate().rotate(scene)
    }

    /// Checks the values; the error says which and what is allowed.
    pub fn check(&self) -> Result<(), String> {
        if !(self.scale.is_finite() && self.scale > 0.0 && self.scale <= 1000.0) {
            return Err(format!("scale must be within (0, 1000], got {}", self.scale));
        }
        if !self.offset_m.iter().all(|c| c.is_finite()) {
            return Err("offset_m must be finite".into());
        }
        let n = self.rotation_wxyz.iter().map(|c| c * c).sum::<f64>().sqrt();
        if !n.is_finite() || (n - 1.0).abs() > 1e-3 {
            return Err(format!("rotation_wxyz must be a unit quaternion, its norm is {n}"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn maps_and_brings_forces_back() {
        // A quarter turn about z: device x is scene y.
        let s = std::f64::consts::FRAC_1_SQRT_2;
        let w = Workspace { offset_m: [0.1, 0.0, 0.0], scale: 2.0, rotation_wxyz: [s, 0.0, 0.0, s] };
        let p = w.position(V3(0.01, 0.0, 0.0));
        assert!((p - V3(0.1, 0.02, 0.0)).norm() < 1e-12);
        let f = w.force_to_device(V3(0.0, 1.0, 0.0));
        assert!((f - V3(1.0, 0.0, 0.0)).norm() < 1e-12);
    }
}
