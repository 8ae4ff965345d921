//! Losses on whole trajectories ([`TrajectoryTerms`]): waypoints a body passes at given
//! steps, a target for a body's final state, the effort of the actions, a body's speed all
//! along, and the liquid volume inside a box at the end ("fill the cup", or with a target
//! of zero, "don't spill").

use super::control::{Trajectory, TrajectoryLoss, TrajectorySeed};
use super::loss::AdjointState;
use crate::geometry::grid::Mac;
use crate::math::{Rotation, Vec3};

/// Body `body` at boundary `step` (after that many steps) near `position`: weight·|x − p|².
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Waypoint {
    /// The body (index into the simulation's bodies).
    pub body: usize,
    /// The boundary (steps taken), 0 ..= the schedule's steps.
    pub step: usize,
    /// Where it should be.
    pub position: Vec3,
    /// The weight.
    pub weight: f64,
}

/// The liquid's volume inside an axis-aligned box at the end, against a target:
/// weight·(V − V*)². A marker particle counts with its share of a cell's volume times a
/// smooth indicator of the box (a product of logistic steps half a cell wide at its faces),
/// so the volume is differentiable in the particles' positions; with the surface frozen they
/// do not move and its gradient is zero.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LiquidInBox {
    /// The box's lower corner.
    pub min: Vec3,
    /// Its upper corner.
    pub max: Vec3,
    /// The volume wanted inside, m³ (0: keep the liquid out).
    pub target: f64,
    /// The weight, per m⁶.
    pub weight: f64,
}

impl LiquidInBox {
    /// The smooth indicator of the box at `x` and its gradient, for steps of width `h`.
    fn indicator(&self, x: Vec3, h: f64) -> (f64, Vec3) {
        let s = |t: f64| 1.0 / (1.0 + (-t).exp());
        let (lo, hi, p) = (self.min.to_array(), self.max.to_array(), x.to_array());
        let mut f = [0.0; 3];
        let mut df = [0.0; 3];
        for d in 0..3 {
            let (a, b) = (s((p[d] - lo[d]) / h), s((hi[d] - p[d]) / h));
            f[d] = a * b;
            df[d] = (a * (1.0 - a) * b - a * b * (1.0 - b)) / h;
        }
        let v = f[0] * f[1] * f[2];
        (v, Vec3::new(df[0] * f[1] * f[2], f[0] * df[1] * f[2], f[0] * f[1] * df[2]))
    }

    /// V and ∂V/∂x_p.
    fn volume(&self, t: &Trajectory<'_>) -> (f64, Vec<Vec3>) {
        let sim = t.final_state;
        let grid = sim.grid();
        let per = grid.dx.powi(3) / sim.settings().solver.particles_per_cell as f64;
        let h = 0.5 * grid.dx;
        let mut v = 0.0;
        let grads = sim
            .particles
            .iter()
            .map(|x| {
                let (f, g) = self.indicator(*x, h);
                v += per * f;
                g * per
            })
            .collect();
        (v, grads)
    }
}

/// A loss on a trajectory, the sum of the terms it has.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TrajectoryTerms {
    /// Positions to pass at given steps.
    pub waypoints: Vec<Waypoint>,
    /// A target for one body's final position, orientation and velocity, as
    /// [`super::BodyTargetLoss`] weighs them: (body, position and weight, orientation and
    /// weight, velocity and weight).
    pub target: Option<FinalTarget>,
    /// weight·Σ_k Σ_j |a_kj|² over every action.
    pub effort: f64,
    /// weight·Σ_b |v|² of one body over the boundaries after each step, times Δt: (body,
    /// weight).
    pub speed: Option<(usize, f64)>,
    /// The liquid inside a box at the end.
    pub liquid_in_box: Option<LiquidInBox>,
}

/// A target for one body's final state (see [`TrajectoryTerms::target`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FinalTarget {
    /// The body.
    pub body: usize,
    /// Target position and weight.
    pub position: Option<(Vec3, f64)>,
    /// Target orientation and weight: weight·(1 − (q·q*)²).
    pub orientation: Option<(Rotation, f64)>,
    /// Target velocity and weight.
    pub velocity: Option<(Vec3, f64)>,
}

impl TrajectoryLoss for TrajectoryTerms {
    fn value(&self, t: &Trajectory<'_>) -> f64 {
        let mut l = 0.0;
        for w in &self.waypoints {
            l += w.weight * (t.states[w.step][w.body].x - w.position).length_squared();
        }
        if let Some(f) = &self.target {
            let s = &t.states[t.states.len() - 1][f.body];
            if let Some((p, w)) = f.position {
                l += w * (s.x - p).length_squared();
            }
            if let Some((q, w)) = f.orientation {
                l += w * (1.0 - s.q.dot(q).powi(2));
            }
            if let Some((v, w)) = f.velocity {
                l += w * (s.v - v).length_squared();
            }
        }
        l +=
            self.effort * t.schedule.actions.iter().flatten().flatten().map(|a| a * a).sum::<f64>();
        if let Some((body, w)) = self.speed {
            let dt = t.final_state.dt();
            l += w * dt * t.states[1..].iter().map(|s| s[body].v.length_squared()).sum::<f64>();
        }
        if let Some(b) = &self.liquid_in_box {
            l += b.weight * (b.volume(t).0 - b.target).powi(2);
        }
        l
    }

    fn gradient(&self, t: &Trajectory<'_>) -> TrajectorySeed {
        let mut seed = TrajectorySeed::zero(t);
        for w in &self.waypoints {
            seed.states[w.step][w.body].x +=
                2.0 * w.weight * (t.states[w.step][w.body].x - w.position);
        }
        if let Some(f) = &self.target {
            let last = t.states.len() - 1;
            let s = &t.states[last][f.body];
            let g = &mut seed.states[last][f.body];
            if let Some((p, w)) = f.position {
                g.x += 2.0 * w * (s.x - p);
            }
            if let Some((q, w)) = f.orientation {
                let d = q * (-2.0 * w * s.q.dot(q));
                g.q = Rotation::from_xyzw(g.q.x + d.x, g.q.y + d.y, g.q.z + d.z, g.q.w + d.w);
            }
            if let Some((v, w)) = f.velocity {
                g.v += 2.0 * w * (s.v - v);
            }
        }
        if self.effort != 0.0 {
            for (g, a) in seed.actions.iter_mut().flatten().zip(t.schedule.actions.iter().flatten())
            {
                for d in 0..6 {
                    g[d] += 2.0 * self.effort * a[d];
                }
            }
        }
        if let Some((body, w)) = self.speed {
            let dt = t.final_state.dt();
            for (g, s) in seed.states[1..].iter_mut().zip(&t.states[1..]) {
                g[body].v += 2.0 * w * dt * s[body].v;
            }
        }
        if let Some(b) = &self.liquid_in_box {
            let (v, grads) = b.volume(t);
            let c = 2.0 * b.weight * (v - b.target);
            seed.liquid = Some(AdjointState {
                u: Mac::zeros(t.final_state.grid()),
                bodies: Vec::new(),
                particles: grads.into_iter().map(|g| g * c).collect(),
                mass: Vec::new(),
            });
        }
        seed
    }
}
