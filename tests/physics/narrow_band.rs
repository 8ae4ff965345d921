//! Narrow-band marker particles (`solver.narrow_band`, see `stages/band.rs`) against the
//! full-volume liquid: still water, the dam break's volume, Archimedes, and the live-surface
//! gradient.

use crate::common::tank_toml;
use diffluid::gradients::{gradcheck, GradcheckSettings};
use diffluid::stages::surface::per_axis;
use diffluid::{Scene, Simulation};

/// The liquid's volume as the band counts it: deep cells full, each particle 1/ppc of a
/// cell, and what the deep cells still owe the band (m³).
fn counted(sim: &Simulation) -> f64 {
    let grid = sim.grid();
    let ppc = per_axis(sim.settings().solver.particles_per_cell).pow(3) as f64;
    let cell = grid.dx.powi(3);
    let band = sim.band().expect("a band");
    let owed: f64 = band.owed.iter().sum();
    (band.deep_cells() as f64 + sim.particles().len() as f64 / ppc) * cell + owed
}

fn with_band(name: &str, width: usize) -> Scene {
    let mut scene = Scene::builtin(name).unwrap();
    scene.solver.narrow_band = width.into();
    scene
}

/// Still water with a band stays still, its surface is the full-volume one exactly, and it
/// holds a third of the particles.
#[test]
fn still_water_with_a_band_is_the_full_volume_still_water() {
    let mut band = with_band("still_water", 3).build().unwrap();
    let mut full = with_band("still_water", 0).build().unwrap();
    let deep = band.band().unwrap().deep_cells();
    assert_eq!(deep, 20 * 20 * 6, "rows 0..6 are more than 4 cells under the surface");
    assert_eq!(band.particles().len() * 10, full.particles().len() * 4);
    let v0 = band.liquid_volume();
    assert!((v0 - full.liquid_volume()).abs() < 1e-12);
    for _ in 0..20 {
        let r = band.step().unwrap();
        full.step().unwrap();
        assert!(r.max_speed < 1e-6, "step {}: max speed {} m/s", r.step, r.max_speed);
    }
    // Measured: 3e-12 m³ of 0.5 (the full-volume liquid 7e-12), the particles' drift in a
    // field the solve holds to 1e-8.
    assert!((band.liquid_volume() - v0).abs() < 3e-11);
    // The same φ_L wherever it is less than a cell deep (the ghost-fluid boundary reads it
    // there), and the same pressure.
    let dx = band.grid().dx;
    for (c, (a, b)) in band.liquid_phi().iter().zip(full.liquid_phi()).enumerate() {
        if *b > -dx {
            assert!((a - b).abs() < 1e-9 * dx, "cell {c}: {a} against {b}");
        }
    }
    for (a, b) in band.pressure().iter().zip(full.pressure()) {
        assert!((a - b).abs() <= 1e-9 * b.abs().max(1.0), "pressure {a} against {b}");
    }
}

/// The dam break at 2.5 cm cells with a band of 3 keeps its volume like the full-volume
/// one: within 2% every step over 50 (measured: at most 1.54%, the full-volume liquid
/// 1.71%; 0.69% and 1.17% before the density projection drew in interior deficits too), and
/// the band's count (deep cells, particles, what is owed) within 0.2%.
#[test]
fn dam_break_with_a_band_keeps_its_volume() {
    let mut scene = with_band("dam_break", 3);
    scene.domain.dx = 0.025;
    scene.time.dt = 0.0125;
    scene.output.particles = false;
    let mut sim = scene.build().unwrap();
    assert!(sim.band().unwrap().deep_cells() > 5000, "the column has deep cells");
    let v0 = sim.liquid_volume();
    let n0 = counted(&sim);
    assert!((v0 - 0.28).abs() < 1e-9 && (n0 - 0.28).abs() < 1e-9);
    let (mut worst, mut worst_count) = (0.0f64, 0.0f64);
    for _ in 0..50 {
        let r = sim.step().unwrap();
        worst = worst.max((r.liquid_volume - v0).abs() / v0);
        worst_count = worst_count.max((counted(&sim) - n0).abs() / n0);
    }
    eprintln!("worst volume {worst:.2e}, worst count {worst_count:.2e}");
    assert!(worst < 0.02, "volume {:.2}% off", 100.0 * worst);
    assert!(worst_count < 2e-3, "count {:.3}% off", 100.0 * worst_count);
}

/// A floating box settles at the same height with a band as without (Archimedes: the
/// full-volume box floats at its draft, `tests/physics/coupling.rs`); measured: the same to the
/// last bit after 40 steps (the band's φ_L and densities are the full volume's there).
#[test]
fn floating_box_with_a_band_floats_as_without() {
    let mut band = with_band("floating_box", 2).build().unwrap();
    let mut full = with_band("floating_box", 0).build().unwrap();
    assert!(band.band().unwrap().deep_cells() > 0);
    for _ in 0..40 {
        band.step().unwrap();
        full.step().unwrap();
    }
    let (a, b) = (band.bodies()[0].x.y, full.bodies()[0].x.y);
    let dx = band.grid().dx;
    eprintln!("height with a band {a}, without {b}");
    assert!((a - b).abs() < 1e-9 * dx, "{a} against {b}");
}

/// A heavy ball (density 3000, radius 0.08 m) in a deep pool at 4 cm cells, 40 steps, with a
/// narrow band of `band` cells (0: none).
fn sinking_ball(band: usize) -> Scene {
    let text = tank_toml("sink", [0.8, 0.8, 0.8], 0.04, 0.7, 40)
        + &format!(
            r#"
[[body]]
name = "ball"
shape = {{ kind = "ball", radius = 0.08 }}
density = 3000.0
position = [0.41, 0.5, 0.39]
[solver]
narrow_band = {band}
"#
        );
    Scene::from_toml(&text, "<test>").unwrap()
}

/// The sinking ball of the test below with the density projection's faces fading with
/// their weight (`solver.density_face_ramp = 0.2`), whose forward step read the weights the
/// band's projection closes at its deep cells and no longer keeps (it panicked): with a band
/// it sinks as without, within the same bounds, and the ramp moves its path.
#[test]
fn a_ball_sinking_with_a_band_and_the_face_ramp_sinks_as_without() {
    let run = |band: usize, ramp: f64| {
        let mut scene = sinking_ball(band);
        scene.solver.density_face_ramp = ramp;
        let mut sim = scene.build().unwrap();
        assert_eq!(sim.band().is_some_and(|b| b.deep_cells() > 1000), band > 0);
        for _ in 0..40 {
            sim.step().unwrap();
        }
        let b = &sim.bodies()[0];
        (b.x.y, b.v.y)
    };
    let (a, b, plain) = (run(2, 0.2), run(0, 0.2), run(0, 0.0));
    eprintln!(
        "face ramp: height, v_y {a:?} with a band, {b:?} without; {plain:?} without the ramp"
    );
    assert!((a.0 - b.0).abs() < 0.075 * 0.04, "{a:?} against {b:?}");
    assert!((a.1 - b.1).abs() < 0.015 * b.1.abs(), "{a:?} against {b:?}");
    assert!(b != plain, "the ramp faded no face: it goes unchecked");
}

/// The live-surface gradient through a band (particles taken out and seeded, deep cells
/// traded) agrees with central differences of the same map as the full-volume one does
/// (measured worst 3.6e-5 with a band of 2, whose density projection is closed at the
/// deep cells; 1.8e-4 without a band).
#[test]
fn live_gradient_with_a_band_matches_central_differences() {
    let scene = with_band("gradcheck_live", 2);
    let sim = scene.build().unwrap();
    assert!(sim.band().unwrap().deep_cells() > 0);
    let loss = scene.loss().unwrap();
    let settings = GradcheckSettings { rtol: 1e-3, atol: 1e-12, ..Default::default() };
    let report = gradcheck(&sim, scene.time.steps, &loss, &settings).unwrap();
    for r in &report.params {
        eprintln!("{} adjoint {:e} fd {:e} rel {:.2e}", r.name, r.adjoint, r.fd, r.rel_error);
        assert!(r.pass, "{}: adjoint {:e}, fd {:e}", r.name, r.adjoint, r.fd);
    }
}

/// A heavy ball sinking through a deep pool carries the band with it (the cells it leaves
/// are seeded, the ones it nears leave the deep set) and ends where it does without a band:
/// measured 0.04 cells lower (0.4% of the 0.39 m it sinks), 1.2% faster (0.8% with the
/// yes/no surface rules that were the defaults before 6 December 2026; without the band the
/// ball's last speed, a cell over the floor, moves by 3.6% as air pockets are closed or
/// not), and the volume within 0.3% every step.
#[test]
fn a_ball_sinking_through_the_deep_cells_sinks_as_without_a_band() {
    let mut band = sinking_ball(2).build().unwrap();
    let mut full = sinking_ball(0).build().unwrap();
    assert!(band.band().unwrap().deep_cells() > 1000);
    let v0 = band.liquid_volume();
    let mut worst = 0.0f64;
    for _ in 0..40 {
        let r = band.step().unwrap();
        full.step().unwrap();
        worst = worst.max((r.liquid_volume - v0).abs() / v0);
    }
    let (a, b) = (&band.bodies()[0], &full.bodies()[0]);
    let dx = band.grid().dx;
    eprintln!(
        "height {} against {}, v_y {} against {}, volume {worst:.2e}",
        a.x.y, b.x.y, a.v.y, b.v.y
    );
    assert!(b.x.y < 0.15, "the ball reached the floor's neighbourhood: {}", b.x.y);
    assert!((a.x.y - b.x.y).abs() < 0.075 * dx);
    assert!((a.v.y - b.v.y).abs() < 0.015 * b.v.y.abs());
    assert!(worst < 1e-2, "volume {:.2}% off", 100.0 * worst);
}
