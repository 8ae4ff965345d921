//! A step that fails leaves the simulation as it was before the step (issue 39, item 12).
//!
//! By the time a step can fail it has moved things: stage 0 advects the marker particles and
//! updates the narrow band, the pressure solve (stage 4) sets the bodies' velocities and
//! fluid forces, stage 6 moves the bodies, and a state found not finite comes after the step
//! count and the time have moved on. A failure there (a body that leaves the tank, a solve
//! that does not converge) must put all of it back: the same
//! state as before the step, bit for bit, so that trying again fails the same way without
//! moving anything again, and a change that lets the step succeed (here: a sane velocity for
//! the body that left) gives exactly the step a simulation that never failed takes.

use diffluid::geometry::body::BodyState;
use diffluid::math::Vec3;
use diffluid::{Error, Scene, Simulation, Solve};

/// A tank with a narrow band (deep cells, no particles in them) and a floating ball.
const TANK: &str = r#"
name = "failed_step"
[domain]
size = [0.48, 0.48, 0.48]
dx = 0.04
[time]
dt = 0.01
steps = 10
[fluid]
density = 1000.0
gravity = [0.0, -9.81, 0.0]
[[liquid]]
shape = { kind = "box", min = [0.0, 0.0, 0.0], max = [0.48, 0.36, 0.48] }
[[liquid]]
shape = { kind = "box", min = [0.0, 0.36, 0.0], max = [0.16, 0.44, 0.48] }
[[body]]
name = "ball"
shape = { kind = "ball", radius = 0.06 }
density = 500.0
position = [0.3, 0.38, 0.24]
velocity = [0.2, 0.0, -0.1]
[solver]
tolerance = 1e-10
narrow_band = 3
"#;

/// Asserts that `a` and `b` hold the same state, bit for bit: everything a step reads or a
/// caller sees.
fn assert_same(a: &Simulation, b: &Simulation) {
    assert_eq!(a.steps_taken(), b.steps_taken(), "step count");
    assert_eq!(a.time().to_bits(), b.time().to_bits(), "time");
    assert!(a.particles() == b.particles(), "marker particles");
    assert!(a.band() == b.band(), "narrow band");
    assert!(a.liquid_phi() == b.liquid_phi(), "φ_L");
    assert!(a.pressure() == b.pressure(), "pressure");
    assert!(a.velocity_field() == b.velocity_field(), "fluid velocity");
    for (x, y) in a.bodies().iter().zip(b.bodies()) {
        assert_eq!(x.state(), y.state(), "body {}", x.name);
    }
    for (&h, &k) in a.handles().iter().zip(b.handles()) {
        assert_eq!(a.fluid_force(h).unwrap(), b.fluid_force(k).unwrap(), "fluid force");
    }
}

/// The tank after `steps` good steps: the liquid moving, the band in use.
fn moving_tank(steps: usize) -> Simulation {
    let mut sim = Scene::from_toml(TANK, "<failed_step>").unwrap().build().unwrap();
    for _ in 0..steps {
        sim.step().unwrap();
    }
    assert!(sim.band().is_some_and(|b| b.deep.iter().any(|&d| d)), "the band has deep cells");
    sim
}

#[test]
fn a_body_leaving_the_tank_is_rolled_back_and_the_step_can_be_retried() {
    let mut sim = moving_tank(4);
    let good = sim.clone();
    // Fast enough to leave the tank in one step, after the particles and the band have moved
    // and the pressure has acted on the ball.
    let h = sim.handles()[0];
    let fast = BodyState { v: Vec3::new(sim[h].v.x, sim[h].v.y, 40.0), ..sim[h].state() };
    sim.set_body_state(h, &fast).unwrap();
    let before = sim.clone();
    for _ in 0..2 {
        match sim.step() {
            Err(Error::BodyLeftTank { step: 5, body, .. }) => assert_eq!(body, "ball"),
            other => panic!("expected the ball to leave the tank at step 5, got {other:?}"),
        }
        assert_same(&sim, &before);
    }
    // The stage-0 work was real: the same step with the ball slowed down moves the particles.
    sim.set_body_state(h, &BodyState { v: good[h].v, ..sim[h].state() }).unwrap();
    let mut never_failed = good.clone();
    sim.step().unwrap();
    never_failed.step().unwrap();
    assert!(sim.particles() != good.particles(), "the step moves the particles");
    assert_same(&sim, &never_failed);
}

/// The density projection (the end of stage 0, after the band's update and the particles'
/// advection) asked for more than it can reach: it fails at step 2, once the liquid moves.
#[test]
fn a_density_projection_that_does_not_converge_is_rolled_back() {
    let text = TANK.replace(
        "tolerance = 1e-10",
        "tolerance = 1e-10\ndensity_tolerance = 1e-15\nmax_iterations = 30",
    );
    let mut sim = Scene::from_toml(&text, "<failed_step>").unwrap().build().unwrap();
    let (step, before) = loop {
        let before = sim.clone();
        match sim.step() {
            Ok(_) => assert!(sim.steps_taken() < 30, "the projection kept converging"),
            Err(Error::NotConverged { solve: Solve::Density, step, .. }) => break (step, before),
            Err(e) => panic!("expected a density projection that does not converge, got {e}"),
        }
    };
    assert!(step > 1, "failed at step {step}: nothing had moved yet");
    assert_same(&sim, &before);
    assert!(matches!(sim.step(), Err(Error::NotConverged { step: s, .. }) if s == step));
    assert_same(&sim, &before);
}

/// Without rollback (`diffluid run`, which stops at the first error, keeps the memory) the
/// failed step puts back the bodies, the step count and the time, but not the marker
/// particles, which stay where its first stage moved them.
#[test]
fn without_rollback_the_failed_step_stays_half_done() {
    let mut sim = moving_tank(2);
    assert!(sim.rollback());
    sim.set_rollback(false);
    let h = sim.handles()[0];
    let fast = BodyState { v: Vec3::new(sim[h].v.x, sim[h].v.y, 40.0), ..sim[h].state() };
    sim.set_body_state(h, &fast).unwrap();
    let before = sim.clone();
    assert!(matches!(sim.step(), Err(Error::BodyLeftTank { .. })));
    assert_eq!((sim.steps_taken(), sim.time()), (before.steps_taken(), before.time()));
    assert_eq!(sim.bodies()[0].state(), before.bodies()[0].state());
    assert!(sim.particles() != before.particles(), "the particles stay moved");
}

#[test]
fn advance_while_stops_where_it_is_asked_to() {
    let mut sim = moving_tank(1);
    let mut whole = sim.clone();
    let all = whole.advance(0.05).unwrap();
    assert!(all.len() >= 5, "{} steps", all.len());
    let mut seen = 0;
    let part = sim
        .advance_while(0.05, |_| {
            seen += 1;
            if seen == 2 {
                std::ops::ControlFlow::Break(())
            } else {
                std::ops::ControlFlow::Continue(())
            }
        })
        .unwrap();
    assert_eq!(part.len(), 2);
    assert_eq!(sim.steps_taken(), 3);
    assert_eq!(sim.time().to_bits(), part[1].time.to_bits());
    assert_eq!(part[1].time.to_bits(), all[1].time.to_bits(), "the frame's first two steps");
}
