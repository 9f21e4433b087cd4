//! Bounded physical quantities for scene and script files.
//!
//! Each type carries its unit and its allowed range, checks them while the JSON is
//! read (so the error names the JSON path, the unit and the range), and describes
//! itself in the generated JSON Schema with the same bounds. One definition serves
//! validation, error messages and schema, so they cannot drift.

use std::borrow::Cow;

use schemars::{JsonSchema, Schema, SchemaGenerator, json_schema};
use serde::{Deserialize, Deserializer, Serialize, de::Error as _};

macro_rules! bounded {
    ($(#[$doc:meta])* $name:ident: $ty:ty, $json:literal, what = $what:literal, unit = $unit:literal, range = [$min:expr, $max:expr]) => {
        $(#[$doc])*
        #[derive(Debug, Clone, Copy, PartialEq, PartialOrd, Serialize)]
        #[serde(transparent)]
        pub struct $name(pub $ty);

        impl $name {
            pub const MIN: $ty = $min;
            pub const MAX: $ty = $max;
            pub const UNIT: &'static str = $unit;
            pub const WHAT: &'static str = $what;

            /// Checks the range; the error says what, the unit and what is allowed.
            pub fn new(value: $ty) -> Result<Self, String> {
                #[allow(clippy::manual_range_contains)]
                if value >= Self::MIN && value <= Self::MAX {
                    Ok(Self(value))
                } else {
                    Err(format!(
                        "{} must be within [{}, {}]{}, got {}",
                        $what, Self::MIN, Self::MAX, unit_suffix($unit), value
                    ))
                }
            }

            pub fn get(self) -> $ty {
                self.0
            }
        }

        impl<'de> Deserialize<'de> for $name {
            fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
                let value = <$ty>::deserialize(deserializer)?;
                Self::new(value).map_err(D::Error::custom)
            }
        }

        impl JsonSchema for $name {
            fn schema_name() -> Cow<'static, str> {
                stringify!($name).into()
            }
            fn inline_schema() -> bool {
                true
            }
            fn json_schema(_: &mut SchemaGenerator) -> Schema {
                json_schema!({
                    "type": $json,
                    "minimum": $min,
                    "maximum": $max,
                    "description": format!("{}{}", $what, unit_suffix($unit)),
                })
            }
        }
    };
}

fn unit_suffix(unit: &str) -> String {
    if unit.is_empty() { String::new() } else { format!(" {unit}") }
}

bounded!(/// Young's modulus E.
    YoungPa: f64, "number", what = "Young's modulus", unit = "Pa", range = [1.0, 1e10]);
bounded!(/// Poisson ratio ν (dimensionless; 0.5 would be incompressible and is refused).
    Poisson: f64, "number", what = "Poisson ratio", unit = "", range = [0.0, 0.4999]);
bounded!(/// Mass density ρ.
    DensityKgPerM3: f64, "number", what = "density", unit = "kg/m³", range = [1.0, 1e5]);
bounded!(/// Membrane thickness t.
    ThicknessM: f64, "number", what = "thickness", unit = "m", range = [1e-6, 0.1]);
bounded!(/// Residual (pre-)strain εr of living tissue; 0 disables the shrinking effect.
    ResidualStrain: f64, "number", what = "residual strain", unit = "", range = [0.0, 0.5]);
bounded!(/// Mass-proportional damping coefficient α (force −α·m·v).
    DampingPerS: f64, "number", what = "damping", unit = "1/s", range = [0.0, 1e4]);
bounded!(/// Stiffness-proportional spring damping β (force β·k·relative speed).
    SpringDampingS: f64, "number", what = "spring damping", unit = "s", range = [0.0, 1.0]);
bounded!(/// Stiffness of an elastic foundation per unit area (Winkler modulus: pressure per
    /// unit deflection), e.g. Young's modulus of the layer under the skin over its thickness.
    FoundationStiffnessPaPerM: f64, "number", what = "foundation stiffness", unit = "Pa/m", range = [0.0, 1e10]);
bounded!(/// Viscous drag of a foundation per unit area (pressure per unit speed).
    FoundationDampingPaSPerM: f64, "number", what = "foundation damping", unit = "Pa·s/m", range = [0.0, 1e9]);
bounded!(/// Fracture toughness: the work a cut needs per unit area of new crack.
    FractureToughnessJPerM2: f64, "number", what = "fracture toughness", unit = "J/m²", range = [0.0, 1e6]);
bounded!(/// A Coulomb friction coefficient (tangential over normal force).
    FrictionCoefficient: f64, "number", what = "friction coefficient", unit = "", range = [0.0, 10.0]);
impl Default for FoundationStiffnessPaPerM {
    fn default() -> Self {
        Self(0.0)
    }
}
impl Default for FoundationDampingPaSPerM {
    fn default() -> Self {
        Self(0.0)
    }
}

impl Default for FractureToughnessJPerM2 {
    fn default() -> Self {
        Self(0.0)
    }
}

bounded!(/// Physics time step.
    TimeStepS: f64, "number", what = "time step", unit = "s", range = [1e-6, 0.1]);
bounded!(/// Explicit substeps per physics step.
    Substeps: u32, "integer", what = "substeps", unit = "", range = [1, 1000]);
bounded!(/// Haptic steps per deformation step of a multirate schedule.
    DeformationEvery: u32, "integer", what = "haptic steps per deformation step", unit = "", range = [2, 100]);
bounded!(/// Conjugate-gradient iteration cap.
    CgIterations: u32, "integer", what = "conjugate-gradient iteration cap", unit = "", range = [1, 10000]);
bounded!(/// Conjugate-gradient relative residual tolerance.
    CgTolerance: f64, "number", what = "conjugate-gradient tolerance", unit = "", range = [1e-14, 0.1]);
bounded!(/// A length such as a patch side.
    LengthM: f64, "number", what = "length", unit = "m", range = [1e-5, 10.0]);
bounded!(/// A coordinate in space.
    CoordinateM: f64, "number", what = "coordinate", unit = "m", range = [-100.0, 100.0]);
bounded!(/// Number of mesh cells along one side.
    Resolution: u32, "integer", what = "resolution", unit = "cells", range = [1, 2000]);
bounded!(/// Random jitter of interior nodes, as a fraction of the edge length.
    Jitter: f64, "number", what = "jitter", unit = "of the edge length", range = [0.0, 0.3]);
bounded!(/// Scale from a mesh file's units to metres (0.001 for a file in mm).
    ScaleMPerUnit: f64, "number", what = "scale", unit = "m per file unit", range = [1e-9, 1e3]);
bounded!(/// A tool radius.
    RadiusM: f64, "number", what = "radius", unit = "m", range = [1e-5, 0.1]);
bounded!(/// The width of a scalpel blade's plate, across its axis along its edge's direction.
    BladeWidthM: f64, "number", what = "blade width", unit = "m", range = [1e-4, 0.05]);
bounded!(/// The thickness of a scalpel blade's plate, across its flat.
    BladeThicknessM: f64, "number", what = "blade thickness", unit = "m", range = [1e-5, 0.005]);
bounded!(/// The gap between a forceps' open jaws, across their flats.
    JawOpeningM: f64, "number", what = "jaw opening", unit = "m", range = [1e-4, 0.03]);
bounded!(/// A tool length.
    ToolLengthM: f64, "number", what = "tool length", unit = "m", range = [1e-4, 1.0]);
bounded!(/// Penalty contact stiffness between a tool and the tissue nodes.
    StiffnessNPerM: f64, "number", what = "contact stiffness", unit = "N/m", range = [0.0, 1e7]);
bounded!(/// One component of an acceleration (gravity).
    AccelerationMPerS2: f64, "number", what = "acceleration", unit = "m/s²", range = [-1000.0, 1000.0]);
bounded!(/// A force magnitude.
    ForceN: f64, "number", what = "force", unit = "N", range = [0.0, 1e6]);

bounded!(/// The edge of a voxel.
    VoxelSizeM: f64, "number", what = "voxel size", unit = "m", range = [1e-5, 0.1]);
bounded!(
    /// The p99 step time a `"fidelity": "auto"` grid must fit, ms.
    StepBudgetMs: f64, "number", what = "step time budget", unit = "ms", range = [0.01, 1000.0]);

bounded!(/// Coarsening level L of the branched grid: a coarse cell is 2^L voxels a side.
    GridLevel: u32, "integer", what = "level", unit = "", range = [0, 5]);
bounded!(/// A label value of a label image (0 is empty and cannot be given a material).
    LabelValue: u16, "integer", what = "label", unit = "", range = [1, 65535]);
bounded!(/// A voxel count along one side of a procedural shape.
    VoxelsAlong: u32, "integer", what = "voxel count", unit = "voxels", range = [1, 1000]);
bounded!(/// A voxel index along one axis of a label image.
    VoxelIndex: u32, "integer", what = "voxel index", unit = "", range = [0, 100000]);
bounded!(/// Taubin smoothing passes applied to the surface in rest space.
    SmoothingIterations: u32, "integer", what = "smoothing iterations", unit = "", range = [0, 20]);
bounded!(/// Voxels one cutting step may remove.
    VoxelsPerStep: u32, "integer", what = "voxels per step", unit = "", range = [1, 1000000]);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn out_of_range_message_names_unit_and_range() {
        let err = YoungPa::new(-5.0).unwrap_err();
        assert_eq!(err, "Young's modulus must be within [1, 10000000000] Pa, got -5");
        let err = serde_json::from_str::<Poisson>("0.5").unwrap_err().to_string();
        assert!(err.contains("Poisson ratio must be within [0, 0.4999], got 0.5"), "{err}");
    }

    #[test]
    fn nan_is_refused() {
        assert!(YoungPa::new(f64::NAN).is_err());
    }
}
