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

use crate::common::{builtin_text, tank_toml};
use diffluid::gradients::{
    value_and_gradient, value_and_smoothed_gradient, BodyTargetLoss, Coordinate, GradientSettings,
    Smoothing, SmoothingScale,
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
    Smoothing {
        samples: 4,
        sigma: SmoothingScale { v: sigma, w: 4.0 * sigma, x: 0.1 * sigma, q: sigma },
        seed: 7,
    }
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
        Smoothing { samples: 2, sigma: SmoothingScale { v: 0.0, w: 0.0, x: 0.0, q: 0.0 }, seed: 0 },
        "plain gradient",
    ));
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
    let out = Optimization::new(scene).unwrap().run(None, None, |_| {}).unwrap();
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
