//! A gradient for long horizons where the forward map jumps: the gradient of the loss
//! smoothed over a small Gaussian perturbation of the initial state,
//!
//! L_σ(s) = E_ξ[L(s ⊕ σ·ξ)],  ∇L_σ(s) = E_ξ[∇L(s ⊕ σ·ξ)],  ξ ~ N(0, 1),
//!
//! estimated as the mean of exact gradients ([`value_and_gradient`]) over K perturbed runs in
//! antithetic pairs (ξ and −ξ), with its standard error; or, with
//! [`SmoothingEstimator::Values`], from the runs' losses alone (see there). `s ⊕ σξ` moves
//! every moving body's velocity, angular velocity and position by σ·ξ and turns its
//! orientation by exp(σ_q·ξ_q) on the left; each run's orientation gradient is taken back to
//! the unperturbed frame, so the mean is the exact gradient of L_σ's estimate (not an
//! approximation of it).
//!
//! Where the map is smooth at the scale σ, L_σ's gradient is L's to O(σ²); where L jumps (a
//! cell changing kind, a particle crossing a face) between s and s ± σ, the mean of the slopes
//! around s sees what a central difference at that scale sees, and a step along it is not
//! thrown off by one sample's kink. The cost is K forward and backward passes, taken one after
//! the other, each with every thread (the step is parallel inside); from Python they can go
//! to Ray workers.

use super::loss::{BodyGradient, Gradient, Loss};
use super::run::{value, value_and_gradient, GradientSettings};
use crate::error::{Error, Result};
use crate::geometry::body::{BodyState, Param};
use crate::geometry::grid::Mac;
use crate::math::pool::{runs, side_by_side};
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

impl SmoothingScale {
    /// σ of the kind of parameter `p`.
    pub fn of(&self, p: Param) -> f64 {
        match p {
            Param::V => self.v,
            Param::W => self.w,
            Param::X => self.x,
            Param::Q => self.q,
        }
    }
}

/// What [`value_and_smoothed_gradient`] estimates ∇L_σ from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SmoothingEstimator {
    /// The mean of the perturbed runs' exact gradients (a forward and a backward pass each):
    /// ∇L_σ = E[∇L(s ⊕ σξ)]. Unbiased where L is continuous; where L jumps between the
    /// samples, the slopes on either side of a jump do not see the jump itself.
    #[default]
    Gradients,
    /// The perturbed runs' losses alone (a forward pass each, the runs in parallel): Gaussian
    /// smoothing's identity ∇L_σ = E[L(s ⊕ σξ)·ξ]/σ, per antithetic pair
    /// (L(s ⊕ σξ) − L(s ⊖ σξ))·ξ/(2σ), per coordinate with its own σ. It holds where L jumps
    /// too, and it needs no adjoint, at a variance that grows with the number of perturbed
    /// coordinates (every coordinate of every moving body whose kind has σ > 0; a kind with
    /// σ = 0, and the mass, get no gradient).
    Values,
}

impl SmoothingEstimator {
    /// Both, in the order of their names' list.
    pub const ALL: [SmoothingEstimator; 2] =
        [SmoothingEstimator::Gradients, SmoothingEstimator::Values];

    /// Its name in a scene file (`gradients`, `values`).
    pub fn name(self) -> &'static str {
        match self {
            SmoothingEstimator::Gradients => "gradients",
            SmoothingEstimator::Values => "values",
        }
    }
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
    /// What the gradient is estimated from (default `gradients`).
    #[serde(default, skip_serializing_if = "is_gradients")]
    pub estimator: SmoothingEstimator,
    /// σ's factor per epoch of `diffluid optimize` (gradient descent and Adam): epoch k
    /// perturbs by σ·sigma_decay^k, so the run narrows onto a minimum of L itself as it
    /// settles. In (0, 1], default 1 (the same σ every epoch).
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub sigma_decay: f64,
}

fn is_gradients(e: &SmoothingEstimator) -> bool {
    *e == SmoothingEstimator::Gradients
}

fn one() -> f64 {
    1.0
}

fn is_one(x: &f64) -> bool {
    *x == 1.0
}

impl Smoothing {
    /// `samples` runs in antithetic pairs of perturbations with standard deviations `sigma`,
    /// drawn from `seed`, the mean of their exact gradients, the same σ every epoch.
    pub fn new(samples: usize, sigma: SmoothingScale, seed: u64) -> Smoothing {
        Smoothing {
            samples,
            sigma,
            seed,
            estimator: SmoothingEstimator::Gradients,
            sigma_decay: 1.0,
        }
    }

    /// The smoothing of epoch `epoch` of an optimisation: σ scaled by sigma_decay^epoch.
    pub fn at_epoch(&self, epoch: usize) -> Smoothing {
        let f = self.sigma_decay.powi(epoch.min(i32::MAX as usize) as i32);
        let s = self.sigma;
        let sigma = SmoothingScale { v: s.v * f, w: s.w * f, x: s.x * f, q: s.q * f };
        Smoothing { sigma, ..*self }
    }

    /// Refuses what cannot be estimated: fewer than 2 or an odd number of samples, a σ that
    /// is negative or not finite, all σ zero (that is [`value_and_gradient`]), or a
    /// `sigma_decay` outside (0, 1].
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
        let d = self.sigma_decay;
        if !(d.is_finite() && d > 0.0 && d <= 1.0) {
            return bad(format!("sigma_decay must be in (0, 1], got {d}"));
        }
        Ok(())
    }
}

/// The smoothed loss and gradient, with what the estimate is worth.
#[derive(Clone, Debug)]
pub struct SmoothedRun {
    /// The mean of L over the runs (L_σ's estimate).
    pub loss: f64,
    /// ∇L_σ's estimate (the mean of the runs' gradients, or with
    /// [`SmoothingEstimator::Values`] of the pairs' loss differences); ∂L/∂u₀ and the
    /// particles' are left out (zero and empty): the smoothing is over the bodies.
    pub gradient: Gradient,
    /// Per body, the standard error of each gradient coordinate's mean (over the antithetic
    /// pairs' estimates: the pairs are independent, their two runs are not).
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
/// module's text). A run that fails ends it with that run's error.
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
    // `initial` with every moving body's state moved by sign·σ·ξ.
    let perturb = |draw: &Draw, sign: f64| {
        let mut sim = initial.clone();
        for (b, xi) in sim.bodies_mut().iter_mut().zip(draw) {
            if b.moves() {
                let s = perturbed(&b.state(), &smoothing.sigma, xi, sign);
                b.set_state(&s);
            }
        }
        sim
    };
    let (losses, pair_means) = match smoothing.estimator {
        SmoothingEstimator::Gradients => {
            // The draws' pairs of runs side by side where a run steps on one thread (a grid
            // under `SERIAL_BELOW` cells); a larger grid's runs keep the threads busy alone,
            // and one at a time hold one tape.
            // Each run's loss and bodies' gradient (not the run, which keeps its tape).
            type Ran = (f64, Vec<BodyGradient>);
            let pair = |draw: &Draw| -> Result<[Ran; 2]> {
                let run = |sign: f64| -> Result<Ran> {
                    let run = value_and_gradient(&perturb(draw, sign), steps, loss, settings)?;
                    Ok((run.loss, run.gradient.bodies))
                };
                Ok([run(1.0)?, run(-1.0)?])
            };
            let ran: Vec<[Ran; 2]> =
                runs(initial.spread(), &draws, pair).into_iter().collect::<Result<_>>()?;
            let mut losses = Vec::with_capacity(smoothing.samples);
            let mut pair_means: Vec<Vec<BodyGradient>> = Vec::with_capacity(pairs);
            for (draw, runs) in draws.iter().zip(&ran) {
                let mut mean = vec![zero; n];
                for (sign, (loss, bodies)) in [1.0, -1.0].into_iter().zip(runs) {
                    losses.push(*loss);
                    for ((m, g), xi) in mean.iter_mut().zip(bodies).zip(draw) {
                        // Back to the unperturbed frame: L(exp(σξ)·exp(θ)·q) =
                        // L(exp(Rθ)·exp(σξ)·q), R the perturbation's rotation, so
                        // ∂/∂θ = Rᵀ·g.
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
            (losses, pair_means)
        }
        SmoothingEstimator::Values => {
            // Forward passes only, a pair to a thread at a time (a small grid's step keeps
            // few threads busy; it steps on its thread's own serial pool), each run's loss
            // in the order of the draws.
            let runs: Vec<[f64; 2]> = side_by_side(&draws, |draw| -> Result<[f64; 2]> {
                let value = |sign: f64| value(perturb(draw, sign), steps, loss);
                Ok([value(1.0)?, value(-1.0)?])
            })
            .into_iter()
            .collect::<Result<_>>()?;
            let sigma = smoothing.sigma;
            // (L₊ − L₋)·ξ/(2σ) per coordinate, 0 where σ is.
            let slope = |diff: f64, xi: Vec3, s: f64| {
                if s > 0.0 {
                    diff / (2.0 * s) * xi
                } else {
                    Vec3::ZERO
                }
            };
            let pair_means = runs
                .iter()
                .zip(&draws)
                .map(|([plus, minus], draw)| {
                    let d = plus - minus;
                    let moving = initial.bodies().iter().map(|b| b.moves());
                    draw.iter()
                        .zip(moving)
                        .map(|(xi, moves)| match moves {
                            false => zero,
                            true => BodyGradient {
                                v: slope(d, xi[0], sigma.v),
                                w: slope(d, xi[1], sigma.w),
                                x: slope(d, xi[2], sigma.x),
                                q: slope(d, xi[3], sigma.q),
                                mass: 0.0,
                            },
                        })
                        .collect()
                })
                .collect();
            (runs.iter().flatten().copied().collect(), pair_means)
        }
    };
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
