//! A gradient for long horizons where the forward map jumps: the gradient of the loss
//! smoothed over a small Gaussian perturbation of the initial state,
//!
//! L_σ(s) = E_ξ[L(s ⊕ σ·ξ)],  ∇L_σ(s) = E_ξ[∇L(s ⊕ σ·ξ)],  ξ ~ N(0, 1),
//!
//! estimated as the mean of exact gradients ([`value_and_gradient`]) over K perturbed runs in
//! antithetic pairs (ξ and −ξ), with its standard error. `s ⊕ σξ` moves every moving body's
//! velocity, angular velocity and position by σ·ξ and turns its orientation by exp(σ_q·ξ_q)
//! on the left; each run's orientation gradient is taken back to the unperturbed frame, so the
//! mean is the exact gradient of L_σ's estimate (not an approximation of it).
//!
//! Where the map is smooth at the scale σ, L_σ's gradient is L's to O(σ²); where L jumps (a
//! cell changing kind, a particle crossing a face) between s and s ± σ, the mean of the slopes
//! around s sees what a central difference at that scale sees, and a step along it is not
//! thrown off by one sample's kink. The cost is K forward and backward passes, taken one after
//! the other, each with every thread (the step is parallel inside); from Python they can go
//! to Ray workers.

use super::loss::{BodyGradient, Gradient, Loss};
use super::run::{value_and_gradient, GradientSettings};
use crate::error::{Error, Result};
use crate::geometry::body::BodyState;
use crate::geometry::grid::Mac;
use crate::math::{Rotation, Vec3};
use crate::world::Simulation;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};

/// The perturbation's standard deviations, per kind of initial state parameter.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SmoothingScale {
    /// Velocity, m/s.
    #[serde(default)]
    pub v: f64,
    /// Angular velocity, rad/s.
    #[serde(default)]
    pub w: f64,
    /// Position, m.
    #[serde(default)]
    pub x: f64,
    /// Orientation, rad.
    #[serde(default)]
    pub q: f64,
}

/// How [`value_and_smoothed_gradient`] smooths.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Smoothing {
    /// Runs per gradient (K ≥ 2, even: antithetic pairs).
    pub samples: usize,
    /// σ per kind of parameter.
    pub sigma: SmoothingScale,
    /// The random perturbations' seed: the same seed, the same runs.
    #[serde(default)]
    pub seed: u64,
}

impl Smoothing {
    /// Refuses what cannot be estimated: fewer than 2 or an odd number of samples, a σ that
    /// is negative or not finite, or all σ zero (that is [`value_and_gradient`]).
    pub fn validate(&self) -> Result<()> {
        let bad = |message: String| {
            Err(Error::InvalidSettings { key: "optimize.smoothing".into(), message })
        };
        if self.samples < 2 || self.samples % 2 != 0 {
            return bad(format!(
                "samples must be even and at least 2 (antithetic pairs), got {}",
                self.samples
            ));
        }
        let s = self.sigma;
        for (name, x) in [("v", s.v), ("w", s.w), ("x", s.x), ("q", s.q)] {
            if !(x.is_finite() && x >= 0.0) {
                return bad(format!("sigma.{name} must be finite and ≥ 0, got {x}"));
            }
        }
        if [s.v, s.w, s.x, s.q].iter().all(|&x| x == 0.0) {
            return bad("every sigma is 0: that is the plain gradient".into());
        }
        Ok(())
    }
}

/// The smoothed loss and gradient, with what the estimate is worth.
#[derive(Clone, Debug)]
pub struct SmoothedRun {
    /// The mean of L over the runs (L_σ's estimate).
    pub loss: f64,
    /// The mean of the runs' gradients (∇L_σ's estimate); ∂L/∂u₀ and the particles' are
    /// left out (zero and empty): the smoothing is over the bodies.
    pub gradient: Gradient,
    /// Per body, the standard error of each gradient coordinate's mean (over the antithetic
    /// pairs' means: the pairs are independent, their two runs are not).
    pub standard_error: Vec<BodyGradient>,
    /// Each run's loss, in the order run.
    pub losses: Vec<f64>,
    /// Wall time of all the runs, s.
    pub seconds: f64,
}

/// One perturbation: per body, ξ for v, ω, x and θ.
type Draw = Vec<[Vec3; 4]>;

/// `s` moved by `sign`·σ·ξ (see the module's text).
fn perturbed(s: &BodyState, sigma: &SmoothingScale, xi: &[Vec3; 4], sign: f64) -> BodyState {
    BodyState {
        v: s.v + sign * sigma.v * xi[0],
        w: s.w + sign * sigma.w * xi[1],
        x: s.x + sign * sigma.x * xi[2],
        q: (Rotation::from_scaled_axis(sign * sigma.q * xi[3]) * s.q).normalize(),
    }
}

/// L_σ and ∇L_σ at `initial`'s state, by `smoothing.samples` runs of `steps` steps (see the
/// module's text). Every run's failure is an error naming its sample.
pub fn value_and_smoothed_gradient(
    initial: &Simulation,
    steps: usize,
    loss: &dyn Loss,
    settings: &GradientSettings,
    smoothing: &Smoothing,
) -> Result<SmoothedRun> {
    smoothing.validate()?;
    let clock = std::time::Instant::now();
    let mut rng = rand::rngs::StdRng::seed_from_u64(smoothing.seed);
    let mut normal = || -> Vec3 {
        Vec3::new(
            StandardNormal.sample(&mut rng),
            StandardNormal.sample(&mut rng),
            StandardNormal.sample(&mut rng),
        )
    };
    let n = initial.bodies().len();
    let pairs = smoothing.samples / 2;
    let draws: Vec<Draw> = (0..pairs)
        .map(|_| (0..n).map(|_| [normal(), normal(), normal(), normal()]).collect())
        .collect();
    let zero =
        BodyGradient { v: Vec3::ZERO, w: Vec3::ZERO, x: Vec3::ZERO, q: Vec3::ZERO, mass: 0.0 };
    let mut losses = Vec::with_capacity(smoothing.samples);
    let mut pair_means: Vec<Vec<BodyGradient>> = Vec::with_capacity(pairs);
    for draw in &draws {
        let mut mean = vec![zero; n];
        for sign in [1.0, -1.0] {
            let mut sim = initial.clone();
            for (b, xi) in sim.bodies_mut().iter_mut().zip(draw) {
                if b.moves() {
                    let s = perturbed(&b.state(), &smoothing.sigma, xi, sign);
                    b.set_state(&s);
                }
            }
            let run = value_and_gradient(&sim, steps, loss, settings)?;
            losses.push(run.loss);
            for ((m, g), xi) in mean.iter_mut().zip(&run.gradient.bodies).zip(draw) {
                // Back to the unperturbed frame: L(exp(σξ)·exp(θ)·q) = L(exp(Rθ)·exp(σξ)·q),
                // R the perturbation's rotation, so ∂/∂θ = Rᵀ·g.
                let r = Rotation::from_scaled_axis(sign * smoothing.sigma.q * xi[3]);
                m.v += 0.5 * g.v;
                m.w += 0.5 * g.w;
                m.x += 0.5 * g.x;
                m.q += 0.5 * (r.inverse() * g.q);
                m.mass += 0.5 * g.mass;
            }
        }
        pair_means.push(mean);
    }
    let k = pairs as f64;
    let combine = |f: &dyn Fn(&BodyGradient) -> Vec3, b: usize| -> (Vec3, Vec3) {
        let mean = pair_means.iter().map(|m| f(&m[b])).fold(Vec3::ZERO, |a, x| a + x) / k;
        let var = pair_means
            .iter()
            .map(|m| {
                let d = f(&m[b]) - mean;
                d * d
            })
            .fold(Vec3::ZERO, |a, x| a + x)
            / (k - 1.0).max(1.0);
        (mean, if pairs > 1 { (var / k).sqrt() } else { Vec3::splat(f64::NAN) })
    };
    let mut bodies = vec![zero; n];
    let mut standard_error = vec![zero; n];
    for b in 0..n {
        (bodies[b].v, standard_error[b].v) = combine(&|g| g.v, b);
        (bodies[b].w, standard_error[b].w) = combine(&|g| g.w, b);
        (bodies[b].x, standard_error[b].x) = combine(&|g| g.x, b);
        (bodies[b].q, standard_error[b].q) = combine(&|g| g.q, b);
        let (m, e) = combine(&|g| Vec3::new(g.mass, 0.0, 0.0), b);
        (bodies[b].mass, standard_error[b].mass) = (m.x, e.x);
    }
    Ok(SmoothedRun {
        loss: losses.iter().sum::<f64>() / losses.len() as f64,
        gradient: Gradient { u: Mac::zeros(initial.grid()), bodies, particles: Vec::new() },
        standard_error,
        losses,
        seconds: clock.elapsed().as_secs_f64(),
    })
}
