//! A step that blows up is an error, never a converged step, and it is rolled back.
//!
//! A right-hand side whose norm overflows (‖b‖² past f64's range once a component passes
//! about 1e154) made CG's relative residual ∞/∞ = NaN, and its test ‖r‖ ≤ tol·‖b‖ = ∞ passed:
//! `gravity = [0, -1e160, 0]` ran "converged" with `max speed inf` and a `null` residual,
//! and a body at 1e200 m/s stepped "fine" and then showed 4e-12 m/s. Now CG reports such a
//! solve as not converged with a NaN residual, a step refuses a state or a predicted velocity
//! beyond 1e100 (m, m/s, rad/s) before it changes anything, so the caller can fix what failed
//! and step again; a step that fails later puts back what it can at no cost.

use crate::common::{builtin_text, EXE};
use diffluid::math::Vec3;
use diffluid::{Error, Scene, Simulation};

/// The dam break with a ball (contact off, so a body leaving the tank fails the step too),
/// `edit` applied to its text.
fn dam_break_ball(edit: impl Fn(String) -> String) -> Simulation {
    let text = builtin_text("dam_break_ball")
        .replace("[contact]\nenabled = true", "[contact]\nenabled = false");
    Scene::from_toml(&edit(text), "<test>").unwrap().build().unwrap()
}

/// Everything a failed step must leave as it was.
fn state(sim: &Simulation) -> (Vec<Vec3>, Vec<diffluid::geometry::body::BodyState>, usize, f64) {
    let bodies = sim.bodies().iter().map(|b| b.state()).collect();
    (sim.particles().to_vec(), bodies, sim.steps_taken(), sim.time())
}

#[test]
fn cg_does_not_call_an_infinite_right_hand_side_converged() {
    use diffluid::solvers::cg::{pcg, CgSettings};
    let s = CgSettings { tolerance: 1e-8, max_iterations: 100, project_constant: false };
    let identity = |x: &[f64], y: &mut [f64]| y.copy_from_slice(x);
    for b in [vec![1e160, -2e160, 3.0], vec![f64::INFINITY, 1.0, 1.0], vec![f64::NAN, 0.0, 1.0]] {
        let mut x = vec![0.0; 3];
        let stats = pcg(identity, identity, &b, &mut x, &s);
        assert!(!stats.converged, "{b:?}: {stats:?}");
        assert!(stats.relative_residual.is_nan(), "{b:?}: {stats:?}");
    }
    // A large but representable one still solves.
    let mut x = vec![0.0; 3];
    let stats = pcg(identity, identity, &[1e150, -2e150, 3.0], &mut x, &s);
    assert!(stats.converged && x[0] == 1e150, "{stats:?}");
}

#[test]
fn huge_gravity_is_an_error_and_changes_nothing() {
    let mut sim = dam_break_ball(|t| t.replace("[0.0, -9.81, 0.0]", "[0.0, -1e160, 0.0]"));
    let before = state(&sim);
    let err = sim.step().unwrap_err();
    assert!(matches!(err, Error::NonFinite { step: 1, .. }), "{err}");
    assert!(err.to_string().contains("fluid velocity"), "{err}");
    assert!(state(&sim) == before, "the failed step changed the state");
}

#[test]
fn a_body_at_a_huge_speed_is_an_error_and_changes_nothing() {
    let mut sim = dam_break_ball(|t| t);
    for _ in 0..3 {
        sim.step().unwrap();
    }
    let h = sim.handles()[0];
    for v in [1e200, f64::MAX] {
        let mut s = sim.body(h).unwrap().state();
        s.v = Vec3::new(v, 0.0, 0.0);
        sim.set_body_state(h, &s).unwrap();
        let before = state(&sim);
        let err = sim.step().unwrap_err();
        assert!(matches!(err, Error::NonFinite { step: 4, .. }), "{err}");
        assert!(err.to_string().contains("body ball"), "{err}");
        assert!(state(&sim) == before, "the failed step changed the state");
    }
    // A huge force or torque: the velocity it would give in one step.
    let mut s = sim.body(h).unwrap().state();
    s.v = Vec3::ZERO;
    sim.set_body_state(h, &s).unwrap();
    let (huge, zero) = (Vec3::new(0.0, -1e300, 0.0), Vec3::ZERO);
    for (force, torque) in [(huge, zero), (zero, huge)] {
        sim.set_external_force(h, force, torque).unwrap();
        let before = state(&sim);
        assert!(matches!(sim.step(), Err(Error::NonFinite { .. })));
        assert!(state(&sim) == before);
    }
    // Fixed, the simulation steps on from where it was.
    sim.set_external_force(h, Vec3::ZERO, Vec3::ZERO).unwrap();
    let report = sim.step().unwrap();
    assert_eq!(report.step, 4);
    assert!(report.cg_relative_residual < 1e-8 && report.max_speed.is_finite());
}

/// A step that fails after its first stage (here the ball leaves the tank in stage 6)
/// puts back the bodies, the time and the step count; the marker particles stay where that
/// stage moved them (a copy to put them back costs 24 bytes a particle every step).
#[test]
fn a_step_that_fails_late_puts_the_bodies_and_the_clock_back() {
    let mut sim = dam_break_ball(|t| t);
    for _ in 0..5 {
        sim.step().unwrap();
    }
    let h = sim.handles()[0];
    let mut s = sim.body(h).unwrap().state();
    s.v = Vec3::new(0.0, 0.0, 100.0);
    sim.set_body_state(h, &s).unwrap();
    let (_, bodies, steps, time) = state(&sim);
    let err = sim.step().unwrap_err();
    assert!(matches!(err, Error::BodyLeftTank { step: 6, .. }), "{err}");
    let (_, after, steps_after, time_after) = state(&sim);
    assert!((after, steps_after, time_after) == (bodies, steps, time));
    s.v = Vec3::ZERO;
    sim.set_body_state(h, &s).unwrap();
    assert_eq!(sim.step().unwrap().step, 6);
}

/// The command line: `error:` and status 1, and the summary holds no step.
#[test]
fn the_cli_reports_a_blown_up_run() {
    let dir = std::env::temp_dir().join(format!("diffluid-non-finite-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let scene = dir.join("scene.toml");
    let text = builtin_text("dam_break").replace("[0.0, -9.81, 0.0]", "[0.0, -1e160, 0.0]");
    std::fs::write(&scene, text).unwrap();
    let out = dir.join("out");
    let run = std::process::Command::new(EXE)
        .args(["run", scene.to_str().unwrap(), "--quiet", "--steps", "3", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "{stderr}");
    assert!(stderr.starts_with("error: the simulation blew up at step 1"), "{stderr}");
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["steps"].as_array().map(Vec::len), Some(0), "{summary}");
    assert_eq!(summary["status"], "stopped");
    std::fs::remove_dir_all(&dir).ok();
}
