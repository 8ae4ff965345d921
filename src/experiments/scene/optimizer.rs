//! The `[control]` and `[optimize]` tables and the optimiser each names, every default with
//! its reason.

use crate::geometry::body::Param;
use crate::math::Arr3;
use serde::{Deserialize, Serialize};

/// Actions at every step (`diffluid control`): a dynamic body takes an external force and
/// torque `[fx, fy, fz, τx, τy, τz]` (world frame, N and N·m), a body with `dynamic = false`
/// a velocity and angular velocity `[vx, vy, vz, ωx, ωy, ωz]` (it moves along them, from
/// rest if it has no `velocity`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControlSpec {
    /// The steered bodies, by name.
    pub bodies: Vec<String>,
    /// Steps each action is held; time.steps must be a multiple of it. Default 1.
    #[serde(default = "one_usize")]
    pub steps_per_action: usize,
    /// Every action's starting value, one per body (default zeros).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub initial: Vec<[f64; 6]>,
    /// The largest magnitude of an action's entry: the optimiser clips to it. Optional.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bound: Option<f64>,
    /// The entries the optimiser changes, by name: `vx vy vz wx wy wz` for a body with
    /// `dynamic = false`, `fx fy fz tx ty tz` for a dynamic one (the others keep their
    /// `initial` values). Default: all six.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub free: Vec<String>,
    /// The optimiser (`gd` or `adam`).
    pub optimizer: OptimizerSpec,
    /// Epochs (forward + backward + update each).
    pub epochs: usize,
}

fn one_usize() -> usize {
    1
}

/// The index in an action of an entry named in `control.free`.
pub fn action_entry(name: &str) -> Option<usize> {
    ["vx", "vy", "vz", "wx", "wy", "wz"]
        .iter()
        .position(|n| *n == name)
        .or_else(|| ["fx", "fy", "fz", "tx", "ty", "tz"].iter().position(|n| *n == name))
}

/// The optimiser.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum OptimizerSpec {
    /// Plain gradient descent, p ← p − lr·g (the paper's).
    Gd {
        /// Learning rate.
        learning_rate: f64,
        /// The learning rate's factor per epoch: epoch k steps with learning_rate·decay^k
        /// (an exponential schedule, PyTorch's `ExponentialLR`). Default 1 (constant).
        #[serde(default = "no_decay", skip_serializing_if = "is_no_decay")]
        decay: f64,
    },
    /// Adam (Kingma & Ba 2015).
    Adam {
        /// Learning rate.
        learning_rate: f64,
        /// The learning rate's factor per epoch, as for `gd`. Default 1 (constant).
        #[serde(default = "no_decay", skip_serializing_if = "is_no_decay")]
        decay: f64,
        /// First-moment decay. Default 0.9.
        #[serde(default = "beta1")]
        beta1: f64,
        /// Second-moment decay. Default 0.999.
        #[serde(default = "beta2")]
        beta2: f64,
    },
    /// L-BFGS (Liu & Nocedal 1989) from argmin, with argmin's Moré–Thuente line search
    /// (strong Wolfe conditions, c1 = 1e-4, c2 = 0.9, the classic companion of L-BFGS):
    /// one epoch is one iteration, which may evaluate the loss and gradient several times. It
    /// has no learning rate: the first step is the steepest-descent direction scaled by the
    /// line search. (argmin's Hager–Zhang search is not offered: it evaluates both ends of
    /// its initial bracket [ε, 1e5] before anything else, and a step of 1e5 gradients throws
    /// a body out of the tank.)
    Lbfgs {
        /// Correction pairs kept. Default 5: the problems here have at most 12 parameters,
        /// and 3 to 7 pairs is the usual range (Nocedal & Wright, section 7.2).
        #[serde(default = "memory")]
        memory: usize,
        /// The run ends (converged) once the gradient norm falls below this. Default √ε ≈
        /// 1.5e-8, argmin's: a gradient that small is round-off of the adjoint.
        #[serde(default = "tolerance_grad")]
        tolerance_grad: f64,
        /// The run ends (converged) once an iteration changes the loss by less than this.
        /// Default ε ≈ 2.2e-16, argmin's: a change at f64 round-off.
        #[serde(default = "tolerance_cost")]
        tolerance_cost: f64,
    },
}

fn memory() -> usize {
    5
}
fn tolerance_grad() -> f64 {
    f64::EPSILON.sqrt()
}
fn tolerance_cost() -> f64 {
    f64::EPSILON
}

fn no_decay() -> f64 {
    1.0
}

fn is_no_decay(d: &f64) -> bool {
    *d == 1.0
}

impl OptimizerSpec {
    /// The learning rate of epoch `epoch` (from 0) of a first-order optimiser (None for
    /// L-BFGS, which has none).
    pub fn rate(&self, epoch: usize) -> Option<f64> {
        match self {
            OptimizerSpec::Gd { learning_rate, decay }
            | OptimizerSpec::Adam { learning_rate, decay, .. } => {
                Some(learning_rate * decay.powi(epoch.min(i32::MAX as usize) as i32))
            }
            OptimizerSpec::Lbfgs { .. } => None,
        }
    }
}

fn through_contact() -> bool {
    true
}

fn beta1() -> f64 {
    0.9
}
fn beta2() -> f64 {
    0.999
}

/// What `diffluid optimize` does.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OptimizeSpec {
    /// Initial parameters of the loss body to optimise: any of "v", "w", "x", "q".
    pub params: Vec<Param>,
    /// The optimiser.
    pub optimizer: OptimizerSpec,
    /// Epochs (forward + backward + update each).
    pub epochs: usize,
    /// A gradient whose norm exceeds this stops the run (exploding). Default 1e6.
    #[serde(default = "max_grad")]
    pub max_gradient_norm: f64,
    /// Recovery: the loss's position and velocity targets are the final state of a forward
    /// run from this initial velocity of the loss body.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recover_velocity: Option<Arr3>,
    /// With rapier contact on, the backward pass goes through rapier's contact step
    /// (differenced, see `gradients::GradientOptions::through_contact`) at some extra cost.
    /// Default true; false makes an epoch in which contact acted an error.
    #[serde(default = "through_contact")]
    pub through_contact: bool,
    /// The backward pass's surface: `"live"` (default: the surface's motion differentiated,
    /// the exact gradient of the map) or `"frozen"` (the paper's approximation: the surface
    /// taken as fixed in the backward pass while the forward pass moves it).
    #[serde(default)]
    pub surface_gradient: SurfaceGradientSpec,
    /// Hold the liquid surface fixed during the optimisation's epochs (as the paper did for
    /// its timings: no marker particles in the loop). The gradient is then exact, and an epoch
    /// costs no particle work. `run` keeps the scene's own setting. Default false.
    #[serde(default)]
    pub freeze_surface: bool,
    /// Optimise the loss smoothed over a Gaussian perturbation of the initial state (see
    /// [`crate::gradients::smooth`]): `{ samples = K, sigma = { v, w, x, q }, seed }`, K runs
    /// an epoch. For horizons where the map jumps. Default: the plain gradient.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub smoothing: Option<crate::gradients::Smoothing>,
}

/// The backward pass's surface, as a scene names it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SurfaceGradientSpec {
    /// Differentiate the surface's motion.
    #[default]
    Live,
    /// Hold it fixed in the backward pass.
    Frozen,
}

fn max_grad() -> f64 {
    1e6
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Epoch k steps with lr·decay^k; without `decay` the rate is constant, and a scene
    /// written without it reads back the same.
    #[test]
    fn the_learning_rate_decays_per_epoch() {
        let adam: OptimizerSpec =
            toml::from_str("kind = \"adam\"\nlearning_rate = 0.3\ndecay = 0.5").unwrap();
        let rates: Vec<f64> = (0..3).map(|k| adam.rate(k).unwrap()).collect();
        assert_eq!(rates, [0.3, 0.15, 0.075]);
        let gd: OptimizerSpec = toml::from_str("kind = \"gd\"\nlearning_rate = 2.0").unwrap();
        assert_eq!(gd.rate(7), Some(2.0));
        assert!(!toml::to_string(&gd).unwrap().contains("decay"));
        let lbfgs: OptimizerSpec = toml::from_str("kind = \"lbfgs\"").unwrap();
        assert_eq!(lbfgs.rate(0), None);
    }
}
