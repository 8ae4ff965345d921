//! The `[loss]` table: weighted targets on the final state, and the terms on a trajectory
//! (waypoints, effort, speed, the liquid in a box).

use crate::math::Arr3;
use serde::{Deserialize, Serialize};

/// A weighted target for a 3-vector.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Target3 {
    /// Target value.
    pub target: Arr3,
    /// Weight (≥ 0).
    #[serde(default = "one_f")]
    pub weight: f64,
}

/// A weighted target orientation, as a quaternion `[w, x, y, z]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TargetQ {
    /// Target quaternion `[w, x, y, z]` (normalised on use).
    pub target: [f64; 4],
    /// Weight (≥ 0).
    #[serde(default = "one_f")]
    pub weight: f64,
}

fn one_f() -> f64 {
    1.0
}

/// The loss on the final state: weighted squared distances of one body's position,
/// orientation (1 − (q·q*)²) and velocity to targets.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LossSpec {
    /// The body's name.
    pub body: String,
    /// Final position target.
    #[serde(default)]
    pub position: Option<Target3>,
    /// Final orientation target.
    #[serde(default)]
    pub orientation: Option<TargetQ>,
    /// Final velocity target.
    #[serde(default)]
    pub velocity: Option<Target3>,
    /// Positions the body passes after given steps (with `[control]`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub waypoint: Vec<WaypointSpec>,
    /// weight·Σ|a|² over every action of `[control]`. Default 0.
    #[serde(default)]
    pub effort: f64,
    /// weight·Δt·Σ|v|² of the body after every step (a running cost). Default 0.
    #[serde(default)]
    pub speed: f64,
    /// The liquid's volume inside a box at the end, against a target (with `[control]`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub liquid_in_box: Option<BoxTarget>,
}

/// A position the loss body passes after `step` steps: weight·|x − position|².
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WaypointSpec {
    /// Steps taken (1 ..= time.steps).
    pub step: usize,
    /// Where the body should be, m.
    pub position: Arr3,
    /// Weight (≥ 0). Default 1.
    #[serde(default = "one_f")]
    pub weight: f64,
}

/// The liquid's volume inside an axis-aligned box at the end: weight·(V − target)².
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoxTarget {
    /// Lower corner, m.
    pub min: Arr3,
    /// Upper corner, m.
    pub max: Arr3,
    /// The volume wanted inside, m³ (0: keep the liquid out).
    pub target: f64,
    /// Weight (≥ 0), per m⁶. Default 1.
    #[serde(default = "one_f")]
    pub weight: f64,
}
