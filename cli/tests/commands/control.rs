//! Control gradients: the derivative of a loss on a whole trajectory with respect to every
//! step's action, from one backward sweep, against central differences of the same forward
//! map.
//!
//! A kinematic paddle (a box a few cells thick, `dynamic = false`) is steered by its velocity
//! and angular velocity, a floating ball by an external force and torque; each action is held
//! for 5 steps. The loss asks the ball to pass a waypoint half-way and end near a target, and
//! charges the effort of the actions: every action entry's adjoint must agree with
//! (L(a + ε) − L(a − ε)) / 2ε (measured: worst 7.6e-6 with the surface frozen at ε = 1e-5,
//! on an entry whose derivative is the effort's alone; 6.2e-5 with it moving at 1e-6), and
//! so must the ball's mass gradient (measured 8.3e-10 frozen, 7.3e-9 moving).

use crate::common::{builtin_text, tank_toml, EXE};
use diffluid::geometry::body::Motion;
use diffluid::gradients::{
    value_and_gradient_controlled, FinalTarget, GradientOptions, GradientSettings, Schedule,
    Trajectory, TrajectoryLoss, TrajectoryTerms, Waypoint,
};
use diffluid::math::Vec3;
use diffluid::{Scene, Simulation};

fn scene(frozen: bool) -> Simulation {
    let text = tank_toml("control", [0.8, 0.6, 0.8], 0.05, 0.3, 20)
        + &format!(
            r#"
[[body]]
name = "paddle"
shape = {{ kind = "cuboid", half_extents = [0.06, 0.12, 0.16] }}
density = 1000.0
dynamic = false
position = [0.23, 0.27, 0.41]
axis_angle = {{ axis = [0.2, 1.0, 0.1], degrees = 10 }}
[[body]]
name = "ball"
shape = {{ kind = "ball", radius = 0.08 }}
density = 600.0
position = [0.47, 0.31, 0.38]
[solver]
tolerance = 1e-12
freeze_surface = {frozen}
"#
        );
    let mut sim = Scene::from_toml(&text, "<control>").unwrap().build().unwrap();
    // A paddle at rest is a kinematic body the actions set in motion.
    sim.set_motion(sim.handles()[0], Motion::Kinematic).unwrap();
    sim
}

fn schedule(sim: &Simulation) -> Schedule {
    let actions = (0..4)
        .map(|k| {
            let k = k as f64;
            vec![
                [0.6 + 0.1 * k, 0.05, -0.1 * k, 0.0, 0.3 - 0.1 * k, 0.1],
                [1.5 - k, 0.5 * k, 0.8, 0.01 * k, -0.02, 0.015],
            ]
        })
        .collect();
    let h = sim.handles().to_vec();
    Schedule::new(sim, &h, 5, actions).unwrap()
}

fn loss() -> TrajectoryTerms {
    TrajectoryTerms {
        waypoints: vec![Waypoint {
            body: 1,
            step: 10,
            position: Vec3::new(0.5, 0.3, 0.4),
            weight: 2.0,
        }],
        target: Some(FinalTarget {
            body: 1,
            position: Some((Vec3::new(0.55, 0.3, 0.42), 1.0)),
            orientation: None,
            velocity: Some((Vec3::ZERO, 0.3)),
        }),
        effort: 1e-4,
        speed: Some((0, 0.05)),
        liquid_in_box: None,
    }
}

/// L of the run under `schedule`, forward only.
fn run(sim: &Simulation, schedule: &Schedule, loss: &dyn TrajectoryLoss) -> f64 {
    let mut s = sim.clone();
    let mut states = Vec::new();
    for t in 0..schedule.steps() {
        states.push(s.bodies().iter().map(|b| b.state()).collect());
        schedule.apply(&mut s, t);
        s.step().unwrap();
    }
    states.push(s.bodies().iter().map(|b| b.state()).collect());
    loss.value(&Trajectory { states: &states, final_state: &s, schedule })
}

fn check(frozen: bool, rtol: f64) {
    let sim = scene(frozen);
    let schedule = schedule(&sim);
    let loss = loss();
    let options = GradientOptions {
        surface: diffluid::gradients::backward::SurfaceGradient::Live,
        ..Default::default()
    };
    let settings = GradientSettings { options, ..Default::default() };
    let out = value_and_gradient_controlled(&sim, &schedule, &loss, &settings).unwrap();
    assert!((out.loss - run(&sim, &schedule, &loss)).abs() < 1e-12 * out.loss.abs());
    // With the surface frozen the map is smooth at 1e-5, and an entry whose derivative is
    // the effort's 2e-6 alone reads the loss's rounding at 1e-6 (2.00006e-6; 2.000005e-6 at
    // 1e-5, 2.0003e-6 at 1e-7: the error goes as 1/ε).
    let eps = if frozen { 1e-5 } else { 1e-6 };
    let mut worst = 0.0f64;
    for k in 0..schedule.actions.len() {
        for j in 0..2 {
            for d in 0..6 {
                let mut plus = schedule.clone();
                plus.actions[k][j][d] += eps;
                let mut minus = schedule.clone();
                minus.actions[k][j][d] -= eps;
                let fd = (run(&sim, &plus, &loss) - run(&sim, &minus, &loss)) / (2.0 * eps);
                let adj = out.actions[k][j][d];
                let err = (adj - fd).abs() / fd.abs().max(1e-6);
                eprintln!("frozen {frozen} action {k} body {j} [{d}]: adjoint {adj:+.8e} fd {fd:+.8e} rel {err:.1e}");
                worst = worst.max(err);
            }
        }
    }
    // The ball's mass (its inertia scaling with it): through the forces' F/m and I⁻¹τ and
    // through the coupled solve's M⁻¹. The paddle's is not a parameter of the map.
    let m = sim.bodies()[1].mass;
    let h = 1e-6 * m;
    let with_mass = |mass: f64| {
        let mut s = sim.clone();
        s.set_mass(s.handles()[1], mass).unwrap();
        run(&s, &schedule, &loss)
    };
    let fd = (with_mass(m + h) - with_mass(m - h)) / (2.0 * h);
    let adj = out.initial.bodies[1].mass;
    let err = (adj - fd).abs() / fd.abs().max(1e-6);
    eprintln!("frozen {frozen} mass of the ball: adjoint {adj:+.8e} fd {fd:+.8e} rel {err:.1e}");
    worst = worst.max(err);
    assert_eq!(out.initial.bodies[0].mass, 0.0, "a kinematic body's mass is no parameter");
    eprintln!("frozen {frozen}: worst {worst:.2e}");
    assert!(worst < rtol, "worst relative error {worst:e}");
}

#[test]
fn action_gradients_match_central_differences_frozen_surface() {
    check(true, 2e-5);
}

#[test]
fn action_gradients_match_central_differences_moving_surface() {
    check(false, 3e-4);
}

/// A schedule a caller cannot get wrong silently: each mistake is an error naming it.
#[test]
fn bad_schedules_are_refused() {
    let sim = scene(true);
    let h = sim.handles().to_vec();
    let err = |r: diffluid::Result<Schedule>| r.unwrap_err().to_string();
    assert!(err(Schedule::new(&sim, &h, 0, vec![vec![[0.0; 6]; 2]])).contains("steps_per_action"));
    assert!(err(Schedule::new(&sim, &h, 1, vec![])).contains("no actions"));
    assert!(err(Schedule::new(&sim, &h, 1, vec![vec![[0.0; 6]; 1]])).contains("1 entries for 2"));
    let nan = vec![vec![[0.0, f64::NAN, 0.0, 0.0, 0.0, 0.0], [0.0; 6]]];
    assert!(err(Schedule::new(&sim, &h, 1, nan)).contains("not finite"));
    let mut fixed = sim.clone();
    fixed.set_motion(fixed.handles()[0], Motion::Fixed).unwrap();
    assert!(err(Schedule::new(&fixed, &h, 1, vec![vec![[0.0; 6]; 2]])).contains("fixed"));
    let mut other = scene(true);
    let gone = other.remove_body(other.handles()[1]).map(|_| h[1]).unwrap();
    assert!(err(Schedule::new(&other, &[gone], 1, vec![vec![[0.0; 6]]])).contains("no body"));
}

/// Closed loop: a run stepped one action at a time ([`Stepper`], what a policy trained
/// through the simulator drives) and taken back one action at a time, the liquid's adjoint
/// carried inside, gives the gradients of the whole-schedule sweep (to round-off in the
/// order the loss's own effort term is added).
#[test]
fn one_action_at_a_time_matches_the_whole_schedule() {
    use diffluid::gradients::{BodyAdjoint, Stepper, TrajectorySeed};
    let sim = scene(false);
    let schedule = schedule(&sim);
    // Waypoints on action boundaries only (a closed loop sees the states there).
    let mut loss = loss();
    loss.waypoints[0].step = 10;
    loss.speed = None;
    let options = GradientOptions {
        surface: diffluid::gradients::backward::SurfaceGradient::Live,
        ..Default::default()
    };
    let settings = GradientSettings { options, ..Default::default() };
    let whole = value_and_gradient_controlled(&sim, &schedule, &loss, &settings).unwrap();
    let h = sim.handles().to_vec();
    let mut stepper = Stepper::new(&sim, &h, 5, options).unwrap();
    for a in &schedule.actions {
        stepper.step(a).unwrap();
    }
    assert_eq!(stepper.states(), whole.states[schedule.steps()]);
    let seed: TrajectorySeed = loss.gradient(&Trajectory {
        states: &whole.states,
        final_state: &whole.final_state,
        schedule: &schedule,
    });
    let mut after: Vec<BodyAdjoint> = seed.states[schedule.steps()].clone();
    for k in (0..schedule.actions.len()).rev() {
        let (g, before) = stepper.backward(&after).unwrap();
        for (j, gj) in g.iter().enumerate() {
            #[allow(clippy::needless_range_loop)]
            for d in 0..6 {
                // The sweep started from the loss's own (effort) term; the stepper adds it last.
                let (got, want) = (gj[d] + seed.actions[k][j][d], whole.actions[k][j][d]);
                assert!(
                    (got - want).abs() <= 1e-12 * want.abs(),
                    "action {k} body {j} [{d}]: {got} vs {want}"
                );
            }
        }
        after = before;
        for (a, s) in after.iter_mut().zip(&seed.states[k * 5]) {
            a.x += s.x;
            a.v += s.v;
            a.w += s.w;
        }
    }
    assert!(stepper.backward(&after).is_err(), "more actions taken back than taken");
    // The whole run's mass gradient, summed action by action.
    let (got, want) = (stepper.mass_gradient()[1], whole.initial.bodies[1].mass);
    assert!((got - want).abs() <= 1e-12 * want.abs(), "mass: {got} vs {want}");
    // A run being taken back takes no more actions; reset() starts a new one, the same run.
    let err = stepper.step(&schedule.actions[0]).unwrap_err().to_string();
    assert!(err.contains("reset()"), "{err}");
    stepper.reset();
    assert_eq!(stepper.actions_taken(), 0);
    assert_eq!(stepper.mass_gradient(), vec![0.0, 0.0]);
    let first = stepper.step(&schedule.actions[0]).unwrap();
    assert_eq!(first, whole.states[5]);
    // A refused backward (wrong number of adjoints) takes nothing back.
    assert!(stepper.backward(&after[..1]).is_err());
    assert_eq!(stepper.actions_taken(), 1);
}

/// A scene's `[control]` section and the trajectory terms of its `[loss]`: each mistake is
/// an error naming its key, nothing run.
#[test]
fn bad_control_sections_are_refused() {
    let base = builtin_text("paddle_push");
    let cases = [
        (r#"bodies = ["paddle"]"#, r#"bodies = ["oar"]"#, "control.bodies"),
        ("steps_per_action = 10", "steps_per_action = 0", "control.steps_per_action"),
        ("steps_per_action = 10", "steps_per_action = 7", "multiple"),
        ("bound = 0.4", "bound = -1.0", "control.bound"),
        ("epochs = 100", "epochs = 0", "control.epochs"),
        (
            r#"optimizer = { kind = "adam", learning_rate = 0.03 }"#,
            r#"optimizer = { kind = "lbfgs" }"#,
            "control.optimizer",
        ),
        (
            "initial = [[0.1, 0.0, 0.0, 0.0, 0.0, 0.0]]",
            "initial = [[0.1, 0.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]]",
            "control.initial",
        ),
        ("effort = 1e-4", "effort = -1.0", "loss.effort"),
        (r#"free = ["vx", "vz", "wy"]"#, r#"free = ["vx", "spin"]"#, "control.free"),
        (
            "effort = 1e-4",
            "effort = 1e-4\nwaypoint = [{ step = 151, position = [0.5, 0.24, 0.4] }]",
            "loss.waypoint[0].step",
        ),
    ];
    for (from, to, key) in cases {
        assert!(base.contains(from), "{from}");
        let text = base.replacen(from, to, 1);
        let err = Scene::from_toml(&text, "<bad>").unwrap_err().to_string();
        assert!(err.contains(key), "{to}: {err}");
    }
    // Trajectory terms need actions to act on.
    let text = base.replacen("[control]", "[unused]", 1);
    let cut = text.find("[unused]").unwrap();
    let end = text.find("[loss]").unwrap();
    let without = format!("{}{}", &text[..cut], &text[end..]);
    let err = Scene::from_toml(&without, "<bad>").unwrap_err().to_string();
    assert!(err.contains("need a [control] section"), "{err}");
}

/// `diffluid control` on a small version of `paddle_push` (frozen surface, 2 epochs): the
/// table, the actions, the result and both pictures are written, and the particle swarm
/// runs for the same calls.
#[test]
fn the_control_command_writes_its_files() {
    let base = builtin_text("paddle_push");
    let text = base.replacen("steps = 150", "steps = 20", 1).replacen(
        "[output]",
        "[solver]\nfreeze_surface = true\n\n[output]",
        1,
    );
    let dir = std::env::temp_dir().join(format!("diffluid-control-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let scene = dir.join("small.toml");
    std::fs::write(&scene, text).unwrap();
    let out = dir.join("out");
    let status = std::process::Command::new(EXE)
        .args(["control", scene.to_str().unwrap(), "--epochs", "2", "--swarm", "--quiet", "--out"])
        .arg(&out)
        .status()
        .unwrap();
    assert!(status.success());
    for f in ["control.csv", "actions.csv", "result.json", "control.png", "trajectory.png"] {
        let p = out.join(f);
        assert!(std::fs::metadata(&p).map(|m| m.len() > 50).unwrap_or(false), "{p:?}");
    }
    let result: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("result.json")).unwrap()).unwrap();
    assert_eq!(result["calls"], 6, "three gradients, two calls each");
    assert!(result["best_loss"].as_f64().unwrap() <= result["initial_loss"].as_f64().unwrap());
    assert!(result["particle_swarm_loss"].as_f64().unwrap().is_finite());
    let _ = std::fs::remove_dir_all(&dir);
}
