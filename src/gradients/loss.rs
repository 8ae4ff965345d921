//! Losses on the final state, and the adjoint state they start the backward pass from.

use crate::error::{Error, Result};
use crate::geometry::body::Param;
use crate::geometry::grid::Mac;
use crate::math::{Rotation, Vec3};
pub use crate::stages::rigid::BodyAdjoint;
use crate::world::{BodyHandle, Simulation};

/// ∂L/∂(state): fluid velocity and bodies.
#[derive(Clone, Debug)]
pub struct AdjointState {
    /// ∂L/∂u.
    pub u: Mac,
    /// Per body.
    pub bodies: Vec<BodyAdjoint>,
    /// ∂L/∂(marker particle positions); empty means zero.
    pub particles: Vec<Vec3>,
    /// ∂L/∂m per body: its mass, with its inertia scaling with it (its density changes, not
    /// its shape). A parameter, not a state: the backward pass adds each step's part as it
    /// crosses the step, so a loss hands in zero (empty means zero).
    pub mass: Vec<f64>,
}

impl AdjointState {
    /// Zero on `grid`: no body, particle or mass adjoint (empty means zero).
    pub fn zero(grid: &crate::geometry::grid::Grid) -> AdjointState {
        AdjointState {
            u: Mac::zeros(grid),
            bodies: Vec::new(),
            particles: Vec::new(),
            mass: Vec::new(),
        }
    }
}

/// A loss on the final state.
pub trait Loss: Sync {
    /// L(final state).
    fn value(&self, sim: &Simulation) -> f64;
    /// ∂L/∂(final state).
    fn gradient(&self, sim: &Simulation) -> AdjointState;
}

/// Weighted squared distances of one body's final position, orientation and velocity to
/// targets: `wₓ·|x − x*|² + w_q·(1 − (q·q*)²) + w_v·|v − v*|²` (the orientation term is
/// zero at q = ±q*).
#[derive(Clone, Debug, PartialEq)]
pub struct BodyTargetLoss {
    /// Which body (index in [`Simulation::bodies`]).
    pub body: usize,
    /// Target position and weight.
    pub position: Option<(Vec3, f64)>,
    /// Target orientation and weight.
    pub orientation: Option<(Rotation, f64)>,
    /// Target velocity and weight.
    pub velocity: Option<(Vec3, f64)>,
}

impl BodyTargetLoss {
    /// A loss on body `h` of `sim` with no target yet (set `position`, `orientation` or
    /// `velocity`): the Rust API names a body by its handle (a scene file by its name).
    /// Errors: [`Error::UnknownBody`].
    pub fn on(sim: &Simulation, h: BodyHandle) -> Result<BodyTargetLoss> {
        let body = sim.index_of(h).ok_or(Error::UnknownBody { handle: h.id() })?;
        Ok(BodyTargetLoss { body, position: None, orientation: None, velocity: None })
    }
}

impl Loss for BodyTargetLoss {
    fn value(&self, sim: &Simulation) -> f64 {
        let b = &sim.bodies()[self.body];
        let mut l = 0.0;
        if let Some((t, w)) = self.position {
            l += w * (b.x - t).length_squared();
        }
        if let Some((t, w)) = self.orientation {
            l += w * (1.0 - b.q.dot(t).powi(2));
        }
        if let Some((t, w)) = self.velocity {
            l += w * (b.v - t).length_squared();
        }
        l
    }

    fn gradient(&self, sim: &Simulation) -> AdjointState {
        let mut bodies = vec![BodyAdjoint::zero(); sim.bodies().len()];
        let b = &sim.bodies()[self.body];
        let g = &mut bodies[self.body];
        if let Some((t, w)) = self.position {
            g.x = 2.0 * w * (b.x - t);
        }
        if let Some((t, w)) = self.orientation {
            g.q = t * (-2.0 * w * b.q.dot(t));
        }
        if let Some((t, w)) = self.velocity {
            g.v = 2.0 * w * (b.v - t);
        }
        AdjointState { bodies, ..AdjointState::zero(sim.grid()) }
    }
}

/// One body's initial-state gradient: ∂L/∂v₀, ∂L/∂ω₀, ∂L/∂x₀ and ∂L/∂θ₀ (the orientation in
/// the world-frame tangent space q → exp(θ)·q), a 3-vector per [`Param`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BodyGradient {
    /// ∂L/∂v₀.
    pub v: Vec3,
    /// ∂L/∂ω₀.
    pub w: Vec3,
    /// ∂L/∂x₀.
    pub x: Vec3,
    /// ∂L/∂θ₀.
    pub q: Vec3,
    /// ∂L/∂m: the body's mass, its inertia scaling with it (its density changes, not its
    /// shape). Zero for a body the pressure and the forces do not move.
    pub mass: f64,
}

impl BodyGradient {
    /// The part for `p`.
    pub fn get(&self, p: Param) -> Vec3 {
        match p {
            Param::V => self.v,
            Param::W => self.w,
            Param::X => self.x,
            Param::Q => self.q,
        }
    }
}

/// The gradient of a loss with respect to the initial state.
#[derive(Clone, Debug)]
pub struct Gradient {
    /// ∂L/∂u₀ on every face.
    pub u: Mac,
    /// Per body.
    pub bodies: Vec<BodyGradient>,
    /// ∂L/∂(initial marker particle positions) (empty with a frozen surface).
    pub particles: Vec<Vec3>,
}

impl Gradient {
    /// The part for body `h` of `sim`, the initial state the gradient was taken at.
    /// Errors: [`Error::UnknownBody`].
    pub fn body(&self, sim: &Simulation, h: BodyHandle) -> Result<&BodyGradient> {
        sim.index_of(h)
            .and_then(|i| self.bodies.get(i))
            .ok_or(Error::UnknownBody { handle: h.id() })
    }
}
