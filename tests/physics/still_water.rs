//! Still water stays still, with hydrostatic pressure.
//!
//! A closed tank half full of water at rest is an exact steady state of the incompressible
//! Euler equations: gravity is balanced by the pressure gradient, so p = ρ·g·depth and the
//! velocity stays zero. Discretely, the ghost-fluid free surface reconstructed from freshly
//! seeded particles sits exactly on the cell face where the water ends, so the projection
//! must cancel each step's gravity impulse to solver tolerance. Any error in the stencil,
//! the ghost-fluid θ, the surface reconstruction or the velocity update shows up as motion
//! or as a pressure off the hydrostatic line.

use diffluid::Scene;

#[test]
fn still_water_stays_still_with_hydrostatic_pressure() {
    let scene = Scene::builtin("still_water").unwrap();
    let rho = scene.fluid.density;
    let g = -scene.fluid.gravity[1];
    let surface = 0.5; // the liquid box's top in still_water.toml
    let steps = scene.time.steps;
    assert_eq!(steps, 100);
    let mut sim = scene.build().unwrap();
    let v0 = sim.liquid_volume();
    for _ in 0..steps {
        let r = sim.step().unwrap();
        assert!(r.max_speed < 1e-3, "step {}: max speed {} m/s", r.step, r.max_speed);
    }
    let grid = *sim.grid();
    let cells = grid.cells();
    let p = sim.pressure();
    let mut checked = 0;
    let mut worst: f64 = 0.0;
    for c in sim.liquid_cells().collect::<Vec<_>>() {
        let [i, j, k] = cells.ijk(c);
        let y = cells.position(i, j, k).y;
        let expected = rho * g * (surface - y);
        let rel = (p[c] - expected).abs() / expected;
        worst = worst.max(rel);
        // The issue asks for 1%; the reconstruction is exact for a flat seeded surface, so
        // hold it to what the method gives (round-off and solver tolerance).
        assert!(
            rel < 1e-6,
            "cell ({i},{j},{k}) at depth {:.3}: p = {:.3} Pa, ρgh = {:.3} Pa",
            surface - y,
            p[c],
            expected
        );
        checked += 1;
    }
    // The whole lower half is liquid: 20 × 10 × 20 cells.
    assert_eq!(checked, 20 * 10 * 20);
    eprintln!("worst relative pressure error {worst:.2e}");
    assert!((sim.liquid_volume() - v0).abs() <= 1e-6 * v0);
}

/// `Simulation::stable_dt` reads the liquid's faces, not the air the extrapolation fills:
/// a fast face high in the air changes nothing, the same speed on a face of a liquid cell
/// shortens the step to cfl·dx over it.
#[test]
fn the_stable_step_reads_the_liquid_not_the_air() {
    let scene = Scene::builtin("still_water").unwrap();
    let mut sim = scene.build().unwrap();
    sim.step().unwrap();
    let dt = sim.dt();
    assert_eq!(sim.stable_dt(), dt, "still water steps at the fixed Δt");
    let grid = *sim.grid();
    let faces = grid.faces(1);
    // A face 0.3 m above the surface (0.5 m), then one 0.2 m under it.
    let air = faces.index(10, 16, 10);
    let water = faces.index(10, 6, 10);
    let mut u = sim.velocity_field().clone();
    u.c[1][air] = 50.0;
    sim.set_velocity_field(u.clone()).unwrap();
    assert_eq!(sim.stable_dt(), dt, "a fast face in the air set the step");
    u.c[1][air] = 0.0;
    u.c[1][water] = 50.0;
    sim.set_velocity_field(u).unwrap();
    let g = 9.81f64;
    let expect = sim.settings().solver.cfl * grid.dx / (50.0 + (grid.dx * g).sqrt());
    assert!((sim.stable_dt() - expect).abs() < 1e-12 * expect, "{} vs {expect}", sim.stable_dt());
}
