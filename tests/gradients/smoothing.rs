//! The smoothed gradient (`gradients::smooth`): the mean of exact gradients over antithetic
//! Gaussian perturbations of the initial state.
//!
//! 1. It is the exact gradient of its own estimate: with the perturbations held (the same
//!    seed), central differences of the smoothed loss in every coordinate agree with it,
//!    orientation included (each run's orientation gradient is taken back to the unperturbed
//!    frame; without that the q rows are off by the rotation).
//! 2. As σ → 0 it tends to the plain gradient, the gap shrinking as σ² (antithetic pairs
//!    cancel the odd terms).
//! 3. Bad settings are refused with the key named.
//! 4. From the losses alone (`estimator = "values"`), it is Gaussian smoothing's
//!    (L₊ − L₋)·ξ/(2σ) per antithetic pair: on a smooth map its mean is the gradient within
//!    its standard errors, and its σ shrinks by `sigma_decay` per epoch of an optimisation.

use crate::common::{builtin_text, tank_toml};
use diffluid::gradients::{
    value_and_gradient, value_and_smoothed_gradient, BodyTargetLoss, Coordinate, GradientSettings,
    Smoothing, SmoothingEstimator, SmoothingScale,
};
use diffluid::math::Vec3;
use diffluid::{Scene, Simulation};

/// A ball of density 600 thrown into a tank, 8 steps, the surface held fixed: a map smooth
/// at the scales below (a box's is not: its fractions' slopes jump where its faces tie at a
/// sample point, and the mean of slopes around such a point is not the slope on either side).
fn scene() -> (Simulation, BodyTargetLoss, usize) {
    let text = tank_toml("smooth", [0.8, 0.6, 0.8], 0.05, 0.3, 8)
        + r#"
[[body]]
name = "ball"
shape = { kind = "ball", radius = 0.1 }
density = 600.0
position = [0.41, 0.33, 0.38]
velocity = [0.2, -0.3, 0.1]
angular_velocity = [0.5, -0.3, 0.8]
[solver]
tolerance = 1e-12
freeze_surface = true
"#;
    let sim = Scene::from_toml(&text, "<smooth>").unwrap().build().unwrap();
    let loss = BodyTargetLoss {
        body: 0,
        position: Some((Vec3::new(0.35, 0.2, 0.45), 1.0)),
        orientation: Some((sim.bodies()[0].q, 0.5)),
        velocity: Some((Vec3::new(0.1, -0.2, 0.0), 0.2)),
    };
    (sim, loss, 8)
}

fn smoothing(sigma: f64) -> Smoothing {
    Smoothing::new(4, SmoothingScale { v: sigma, w: 4.0 * sigma, x: 0.1 * sigma, q: sigma }, 7)
}

#[test]
fn the_smoothed_gradient_is_the_gradient_of_its_estimate() {
    let (sim, loss, steps) = scene();
    let s = smoothing(0.05);
    let settings = GradientSettings::default();
    let run = value_and_smoothed_gradient(&sim, steps, &loss, &settings, &s).unwrap();
    assert_eq!(run.losses.len(), 4);
    let at = |c: Coordinate, h: f64| {
        let mut moved = sim.clone();
        let h0 = moved.handles()[0];
        let state = c.param.perturbed(&moved[h0].state(), c.axis, h);
        moved.set_body_state(h0, &state).unwrap();
        value_and_smoothed_gradient(&moved, steps, &loss, &settings, &s).unwrap().loss
    };
    let eps = 1e-6;
    let mut worst = 0.0f64;
    for c in Coordinate::all() {
        let fd = (at(c, eps) - at(c, -eps)) / (2.0 * eps);
        let adj = c.of(&run.gradient.bodies[0]);
        let rel = (adj - fd).abs() / fd.abs().max(1e-8);
        eprintln!("{}: smoothed {adj:+.8e} fd {fd:+.8e} rel {rel:.1e}", c.name());
        worst = worst.max(rel);
    }
    eprintln!("worst {worst:.2e}");
    assert!(worst < 1e-5, "worst relative error {worst:e}");
    // The mass too: the same sweep's parameter, averaged.
    let m = sim.bodies()[0].mass;
    let with_mass = |mass: f64| {
        let mut s2 = sim.clone();
        s2.set_mass(s2.handles()[0], mass).unwrap();
        value_and_smoothed_gradient(&s2, steps, &loss, &settings, &s).unwrap().loss
    };
    let h = 1e-6 * m;
    let fd = (with_mass(m + h) - with_mass(m - h)) / (2.0 * h);
    let adj = run.gradient.bodies[0].mass;
    assert!((adj - fd).abs() <= 1e-6 * fd.abs(), "mass: {adj} vs {fd}");
}

#[test]
fn the_smoothed_gradient_tends_to_the_gradient_as_sigma_squared() {
    let (sim, loss, steps) = scene();
    let settings = GradientSettings::default();
    let exact = value_and_gradient(&sim, steps, &loss, &settings).unwrap().gradient.bodies[0];
    let gap = |sigma: f64| {
        let run =
            value_and_smoothed_gradient(&sim, steps, &loss, &settings, &smoothing(sigma)).unwrap();
        let g = run.gradient.bodies[0];
        let norm = |b: &diffluid::gradients::BodyGradient| {
            (b.v.length_squared()
                + b.w.length_squared()
                + b.x.length_squared()
                + b.q.length_squared())
            .sqrt()
        };
        let d = diffluid::gradients::BodyGradient {
            v: g.v - exact.v,
            w: g.w - exact.w,
            x: g.x - exact.x,
            q: g.q - exact.q,
            mass: 0.0,
        };
        norm(&d) / norm(&exact)
    };
    let (coarse, fine) = (gap(0.02), gap(0.005));
    eprintln!("relative gap: σ 0.02 {coarse:.3e}, σ 0.005 {fine:.3e}, ratio {:.1}", coarse / fine);
    // σ² would give 16 for a factor 4 in σ; anything between 8 and 32 is second order.
    assert!(coarse > 0.0 && (8.0..32.0).contains(&(coarse / fine)), "{coarse} vs {fine}");
    assert!(fine < 1e-2, "the smoothed gradient at σ = 0.005 is {fine} away");
}

#[test]
fn bad_smoothing_is_refused() {
    let (sim, loss, steps) = scene();
    let settings = GradientSettings::default();
    let mut cases = Vec::new();
    let mut odd = smoothing(0.01);
    odd.samples = 3;
    cases.push((odd, "even"));
    let mut one = smoothing(0.01);
    one.samples = 0;
    cases.push((one, "even"));
    let mut nan = smoothing(0.01);
    nan.sigma.x = f64::NAN;
    cases.push((nan, "sigma.x"));
    let mut negative = smoothing(0.01);
    negative.sigma.q = -1.0;
    cases.push((negative, "sigma.q"));
    cases.push((
        Smoothing::new(2, SmoothingScale { v: 0.0, w: 0.0, x: 0.0, q: 0.0 }, 0),
        "plain gradient",
    ));
    for decay in [0.0, -0.5, 1.5, f64::NAN] {
        cases.push((Smoothing { sigma_decay: decay, ..smoothing(0.01) }, "sigma_decay"));
    }
    for (s, says) in cases {
        let err =
            value_and_smoothed_gradient(&sim, steps, &loss, &settings, &s).unwrap_err().to_string();
        assert!(err.contains("smoothing") && err.contains(says), "{err}");
    }
}

/// The recovery scene (`recover_box`: find the initial velocity v* whose run ends at a known
/// state) optimised on the smoothed loss: with σ_v = 0.01 m/s on a smooth map the minimum
/// moves by O(σ²), and gradient descent still finds v* within 1%.
#[test]
fn optimize_on_the_smoothed_loss_recovers_the_initial_velocity() {
    use diffluid::experiments::optimize::Optimization;
    let base = builtin_text("recover_box");
    let text = base.replacen(
        "[optimize]",
        "[optimize]\nsmoothing = { samples = 2, sigma = { v = 0.01 }, seed = 3 }",
        1,
    );
    let scene = Scene::from_toml(&text, "<recover_smooth>").unwrap();
    let vstar = scene.optimize.as_ref().unwrap().recover_velocity.unwrap();
    let problem = Optimization::new(scene).unwrap();
    let out = problem.run(None, None, |_| {}).unwrap();
    // Each epoch records L itself beside L_σ: a forward run at its parameters, not the
    // smoothed estimate (which differs from it by O(σ²) here).
    for r in [&out.history[0], &out.history[out.history.len() / 2]] {
        let plain = problem.loss_at(&r.params).unwrap();
        assert_eq!(r.unsmoothed_loss, Some(plain), "epoch {}", r.epoch);
        assert_ne!(r.loss, plain, "epoch {}: L_σ is not L", r.epoch);
    }
    let v = out.params.v;
    let err = ((0..3).map(|d| (v[d] - vstar[d]).powi(2)).sum::<f64>()
        / vstar.iter().map(|x| x * x).sum::<f64>())
    .sqrt();
    eprintln!("smoothed recovery: v0 = {v:?} (v* = {vstar:?}), relative error {err:.2e}");
    assert!(err < 0.01, "relative error {err}");
    // A bad smoothing section is refused when the scene is read, naming the key.
    for (bad, says) in [
        ("smoothing = { samples = 3, sigma = { v = 0.01 } }", "even"),
        ("smoothing = { samples = 2, sigma = { v = -1.0 } }", "sigma.v"),
        ("smoothing = { samples = 2, sigma = { u = 0.1 } }", "unknown field"),
    ] {
        let text = base.replacen("[optimize]", &format!("[optimize]\n{bad}"), 1);
        let err = Scene::from_toml(&text, "<bad>").unwrap_err().to_string();
        assert!(err.contains(says), "{err}");
    }
}

/// The losses alone: each pair's estimate is (L₊ − L₋)·ξ/(2σ) of its own runs' losses. On
/// the smooth map, perturbing the velocity only and then the orientation only (three
/// coordinates each, 128 runs), its mean is within four of its standard errors of the exact
/// gradient in every coordinate, and those errors are under a third of the gradient (so the
/// check can fail: a mean of the wrong sign is off by several of them). Coordinates whose
/// kind has σ = 0 and the mass get no gradient.
#[test]
fn the_values_estimator_is_the_gradient_within_its_standard_error() {
    let (sim, loss, steps) = scene();
    let settings = GradientSettings::default();
    let exact = value_and_gradient(&sim, steps, &loss, &settings).unwrap().gradient.bodies[0];
    let zero = SmoothingScale { v: 0.0, w: 0.0, x: 0.0, q: 0.0 };
    for (name, sigma) in
        [("v", SmoothingScale { v: 1e-3, ..zero }), ("q", SmoothingScale { q: 1e-3, ..zero })]
    {
        let s =
            Smoothing { estimator: SmoothingEstimator::Values, ..Smoothing::new(128, sigma, 5) };
        let run = value_and_smoothed_gradient(&sim, steps, &loss, &settings, &s).unwrap();
        assert_eq!(run.losses.len(), 128);
        let mean = run.losses.iter().sum::<f64>() / 128.0;
        assert!((run.loss - mean).abs() <= 1e-15 * mean.abs());
        let (g, se) = (run.gradient.bodies[0], run.standard_error[0]);
        let (est, err, want) = match name {
            "v" => (g.v, se.v, exact.v),
            _ => (g.q, se.q, exact.q),
        };
        let others = if name == "v" { [g.w, g.x, g.q] } else { [g.v, g.w, g.x] };
        assert!(others.iter().all(|o| *o == Vec3::ZERO) && g.mass == 0.0, "{g:?}");
        for a in 0..3 {
            let (e, s, w) = (est.to_array()[a], err.to_array()[a], want.to_array()[a]);
            let z = (e - w).abs() / s;
            eprintln!("{name}[{a}]: values {e:+.6e} ± {s:.1e}, exact {w:+.6e}, {z:.2} errors");
            assert!(s > 0.0 && z < 4.0, "{name}[{a}]: {e} ± {s} against {w}");
        }
        let rel = err.length() / want.length();
        eprintln!("{name}: standard error {rel:.2e} of the gradient");
        assert!(rel < 0.33, "{name}: the standard error is {rel} of the gradient");
    }
}

/// `sigma_decay`: epoch k of an optimisation perturbs by σ·sigma_decay^k, every kind alike,
/// and leaves the rest of the smoothing as it was.
#[test]
fn sigma_decays_per_epoch() {
    let s = Smoothing {
        sigma_decay: 0.9,
        estimator: SmoothingEstimator::Values,
        ..Smoothing::new(4, SmoothingScale { v: 0.1, w: 0.2, x: 0.01, q: 0.05 }, 9)
    };
    assert_eq!(s.at_epoch(0), s);
    let e = s.at_epoch(3);
    let f = 0.9f64.powi(3);
    for (got, base) in [(e.sigma.v, 0.1), (e.sigma.w, 0.2), (e.sigma.x, 0.01), (e.sigma.q, 0.05)] {
        assert!((got - base * f).abs() <= 1e-15 * base, "{got} vs {}", base * f);
    }
    assert_eq!((e.samples, e.seed, e.estimator, e.sigma_decay), (4, 9, s.estimator, 0.9));
}
