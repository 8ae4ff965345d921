//! A body floating at rest leaves still water still (issue 33).
//!
//! A body placed at its Archimedes height in still water is a rest state of the continuous
//! problem: the hydrostatic pressure p = ρ·g·depth holds the body up with exactly its
//! weight and accelerates nothing. The discrete step keeps it as one when three things hold,
//! and each test here failed before they did:
//!
//! - φ_L carried into the body continues the free surface at the liquid's own height (it
//!   was marked liquid a cell above the waterline inside every curved body);
//! - a face the body covers in part above the water takes the extrapolated liquid velocity
//!   (it kept its advected velocity plus g·Δt, a step after step, and fed it to the liquid);
//! - a ball's rotation does not reach the liquid (the discrete pressure torque, about 1e-4
//!   of a cell off the ball's axis, spun it up and the spin stirred the water).
//!
//! Before: a ball of density 500 at its floating height drove the liquid's kinetic energy
//! from 0.001 J to 55 J in 1.6 s. Now nothing moves: the energy available is what separates
//! the exact equilibrium from the discrete one, about 1e-11 J.

use crate::common::tank_toml;
use diffluid::Scene;

/// A ball of radius 0.12 m and density 500 whose centre sits on the still surface (half of
/// it under water: its Archimedes height), off the grid's symmetry planes.
fn ball_scene(steps: usize, extra: &str) -> Scene {
    let text = tank_toml("ball_at_rest", [0.8, 0.6, 0.8], 0.04, 0.32, steps)
        + &format!(
            r#"
[[body]]
name = "ball"
shape = {{ kind = "ball", radius = 0.12 }}
density = 500.0
position = [0.413, 0.32, 0.387]
{extra}
"#
        );
    Scene::from_toml(&text, "<ball>").unwrap()
}

/// 3 s of the ball at rest, with the default settings: the liquid's kinetic energy stays
/// under 1e-9 J (measured 1e-15), its fastest speed under 0.1 mm/s, and the ball within
/// 0.1 mm of its Archimedes height (measured 1e-9 m).
#[test]
fn a_ball_at_its_floating_height_leaves_still_water_still() {
    let scene = ball_scene(300, "");
    let mut sim = scene.build().unwrap();
    let (mut energy, mut speed, mut drift) = (0.0f64, 0.0f64, 0.0f64);
    for _ in 0..300 {
        let r = sim.step().unwrap();
        energy = energy.max(r.kinetic_energy).max(r.energy.liquid_kinetic);
        speed = speed.max(r.max_speed);
        drift = drift.max((sim.bodies()[0].x.y - 0.32).abs());
    }
    eprintln!("kinetic energy {energy:.3e} J, speed {speed:.3e} m/s, drift {drift:.3e} m");
    assert!(energy < 1e-9, "the liquid gained {energy:e} J");
    assert!(speed < 1e-4, "the liquid moves at {speed} m/s");
    assert!(drift < 1e-4, "the ball left its floating height by {drift} m");
    let b = &sim.bodies()[0];
    assert!(b.w.length() < 1e-9, "the ball spins at {} rad/s", b.w.length());
}

/// The same ball with the surface frozen (particles held, φ_L its initial value): the
/// grid's stages alone, which reached 482 J before.
#[test]
fn a_ball_at_rest_under_a_frozen_surface_stays_still() {
    let scene = ball_scene(200, "[solver]\nfreeze_surface = true");
    let mut sim = scene.build().unwrap();
    let mut energy = 0.0f64;
    for _ in 0..200 {
        energy = energy.max(sim.step().unwrap().kinetic_energy);
    }
    assert!(energy < 1e-9, "the liquid gained {energy:e} J");
}

/// A horizontal capsule, yawed 30° off the grid's axes, and a closed boat hull from an OBJ
/// (`assets/meshes/hull.obj`, 0.5 × 0.12 × 0.2 m), both of density 500 at their Archimedes
/// height, 3 s with the default settings. Before issue 33 the capsule drove the liquid to
/// 4.0 J and 4.2 m/s and the hull to 0.89 J and 1.9 m/s. Not yet still: measured 5.5e-4 J
/// (3.2e-4 J after the projections alone) and 0.014 m/s (capsule), 0.015 J and 0.062 m/s
/// (hull), the bodies rocking slowly up from the
/// first step's small imbalance (under a frozen surface both settle; the gain is in the
/// moving surface's step, see docs/performance.md). The bounds hold that figure and fail
/// far below the old one.
#[test]
fn a_capsule_and_a_hull_at_rest_stay_nearly_still() {
    for (body, most) in [(CAPSULE, 1e-3), (HULL, 0.04)] {
        let energy = most_energy_at_rest(body, "");
        eprintln!("{}: liquid kinetic energy at most {energy:.3e} J", body.0);
        assert!(energy < most, "{}: the liquid gained {energy} J", body.0);
    }
}

/// A body at rest: its name, shape, height and orientation (a quaternion `[w, x, y, z]`).
type Resting = (&'static str, &'static str, f64, &'static str);

/// A horizontal capsule yawed 30° off the grid's axes, at its Archimedes height.
const CAPSULE: Resting = (
    "capsule",
    r#"{ kind = "capsule", half_height = 0.12, radius = 0.06 }"#,
    0.32,
    "[0.683012702, 0.183012702, 0.183012702, 0.683012702]",
);

/// The closed boat hull of `assets/meshes/hull.obj`, at its Archimedes height.
const HULL: Resting = (
    "hull",
    concat!(
        r#"{ kind = "mesh", obj = ""#,
        env!("CARGO_MANIFEST_DIR"),
        r#"/assets/meshes/hull.obj" }"#
    ),
    0.364,
    "[0.976296007, 0.0, 0.216439614, 0.0]",
);

/// The liquid's largest kinetic energy over 3 s of `body` (density 500) at rest in the
/// still water of `ball_scene`'s tank, the scene's `extra` lines after the body.
fn most_energy_at_rest((name, shape, y, q): Resting, extra: &str) -> f64 {
    let text = tank_toml(&format!("{name}_at_rest"), [0.8, 0.6, 0.8], 0.04, 0.32, 300)
        + &format!(
            r#"
[[body]]
name = "{name}"
shape = {shape}
density = 500.0
position = [0.413, {y}, 0.387]
quaternion = {q}
{extra}
"#
        );
    let mut sim = Scene::from_toml(&text, name).unwrap().build().unwrap();
    let mut energy = 0.0f64;
    for _ in 0..300 {
        let r = sim.step().unwrap();
        energy = energy.max(r.kinetic_energy).max(r.energy.liquid_kinetic);
    }
    energy
}

/// With φ_L as the soft minimum of the particles' distances (`solver.surface_softness`,
/// 0.35 cells), which counts the particles about as near as the nearest one: each body's
/// ghosts (the seeding sites it displaced, riding with it) stand in for the particles it
/// keeps out, so the ball, the capsule and the hull at rest, 3 s each, leave still water as
/// still as the nearest particle's distance does. Without the ghosts the ball gave the liquid
/// 6.7e-4 J in 1.5 s. Measured: the ball 1.1e-17 J, the capsule 9.6e-6 J, the hull
/// 2.6e-4 J (against 5.5e-4 J and 1.5e-2 J with the nearest particle).
#[test]
fn with_a_soft_surface_bodies_at_rest_leave_still_water_still() {
    let ball = ("ball", r#"{ kind = "ball", radius = 0.12 }"#, 0.32, "[1.0, 0.0, 0.0, 0.0]");
    for (body, most) in [(ball, 1e-9), (CAPSULE, 5e-5), (HULL, 1e-3)] {
        let energy = most_energy_at_rest(body, "[solver]\nsurface_softness = 0.35");
        eprintln!("soft surface, {}: liquid kinetic energy at most {energy:.3e} J", body.0);
        assert!(energy < most, "{}: the liquid gained {energy} J", body.0);
    }
}
