//! The dam break of Patel et al.: a 0.4 × 0.7 × 1.0 m block of water collapses along a 4 m
//! tank. Two physical facts are checked over the paper's 50 steps of 0.05 s:
//! - volume: the liquid is incompressible, so its volume (measured from the marker
//!   particles' density on the grid, see `surface::liquid_volume`) stays within 2% of the
//!   start; and, by a measure the density projection does not drive (the particles counted
//!   in each cell against the 8 it was seeded with, capped at a full cell), within 10% at
//!   every step and 4% at the end (measured 8.3% and 3.3%: counting a 3.5 cm layer in 10 cm
//!   cells is noisier than the trilinear deposit; with the blend's θ₁ at 0.46, 0.48, 0.52
//!   and 0.54 instead of 0.5 the end reads 2.5%, 2.1%, 2.6% and 2.5%, and before its corner
//!   was rounded 2.6%);
//! - the surge: gravity drives the front toward −x; until it reaches the far wall it never
//!   moves back (the leading edge of a dam-break surge advances monotonically, Ritter's
//!   solution), and at these scales it reaches the wall within the run (a shallow-water
//!   front travels at about 2·√(g·h) ≈ 5 m/s for h = 0.7 m).

use diffluid::{Scene, Simulation};

#[test]
fn dam_break_keeps_volume_and_the_front_advances_to_the_wall() {
    let scene = Scene::builtin("dam_break").unwrap();
    let dx = scene.domain.dx;
    let mut sim = scene.build().unwrap();
    let v0 = sim.liquid_volume();
    assert!((v0 - 0.4 * 0.7 * 1.0).abs() < 1e-9, "seeded volume {v0}");
    let front = |sim: &Simulation| sim.particles().iter().map(|p| p.x).fold(f64::MAX, f64::min);
    let mut last = front(&sim);
    assert!((last - 3.6).abs() < 0.5 * dx);
    let counted = |sim: &Simulation| {
        let grid = *sim.grid();
        let mut n = vec![0usize; grid.num_cells()];
        for x in sim.particles() {
            n[diffluid::stages::surface::cell_of(&grid, *x)] += 1;
        }
        n.iter().map(|&k| (k as f64 / 8.0).min(1.0)).sum::<f64>() * dx.powi(3)
    };
    assert!((counted(&sim) - v0).abs() < 1e-9);
    let mut reached = None;
    for _ in 0..50 {
        let r = sim.step().unwrap();
        let c = (counted(&sim) - v0).abs() / v0;
        assert!(c < 0.10, "step {}: counted volume {:.2}% off", r.step, 100.0 * c);
        let rel = (r.liquid_volume - v0).abs() / v0;
        assert!(
            rel < 0.02,
            "step {}: volume {:.4} m³ is {:.2}% off {v0:.4}",
            r.step,
            r.liquid_volume,
            100.0 * rel
        );
        let x = front(&sim);
        if reached.is_none() {
            assert!(
                x <= last + 1e-9,
                "step {}: front moved back from {last:.4} to {x:.4} m",
                r.step
            );
            if x < dx {
                reached = Some(r.step);
            }
        }
        last = x;
    }
    let end = (counted(&sim) - v0).abs() / v0;
    assert!(end < 0.04, "counted volume {:.2}% off at the end", 100.0 * end);
    let reached = reached.expect("the front reaches the −x wall within 2.5 s");
    eprintln!("front reached the wall at step {reached}");
    assert!(reached >= 10, "the front cannot cross 3.6 m in {reached} steps of 0.05 s");
}

/// Without the density projection, volume control (`solver.volume_control = 4`) keeps the
/// dam break's volume: over its first 60 steps (the collapse and the surge's first run-up
/// and return, where bunching is worst) within 2.5% at every step and 1% at the end
/// (measured 1.75%, at step 41, and 0.51%; with the yes/no surface rules that were the
/// defaults before 6 December 2026, 1.85% and 0.52% at step 40), where the same run
/// without it loses over 5% (measured 6.4%).
#[test]
fn volume_control_keeps_the_volume_without_the_density_projection() {
    let worst_and_last = |control: &str| {
        let mut scene = Scene::builtin("dam_break").unwrap();
        scene.solver.density_correction = false;
        scene.solver.volume_control = match control {
            "off" => None,
            _ => Some(4.0),
        };
        let mut sim = scene.build().unwrap();
        let v0 = sim.liquid_volume();
        let mut worst = 0.0f64;
        let mut last = 0.0;
        for _ in 0..60 {
            let r = sim.step().unwrap();
            last = (r.liquid_volume - v0).abs() / v0;
            worst = worst.max(last);
            assert!(r.max_divergence < 1e-4, "step {}: divergence {:e}", r.step, r.max_divergence);
        }
        eprintln!(
            "volume control {control}: worst {:.2}%, last {:.2}%",
            100.0 * worst,
            100.0 * last
        );
        (worst, last)
    };
    let (worst, last) = worst_and_last("4");
    assert!(worst < 0.025 && last < 0.01, "with volume control: worst {worst}, last {last}");
    let (worst_off, _) = worst_and_last("off");
    assert!(worst_off > 0.05, "without it the dam break should lose volume: worst {worst_off}");
}

/// The density projection's gain (`solver.density_gain`): the trilinear deposit sees only
/// part of a displacement (none of it for a particle moving within the half cell next to a
/// wall), so a displacement that carries exactly each cell's excess took out 41% of it in a
/// step, and the dam break's particles, bunched in the cells along the floor and the far
/// wall's corners, ended its landing 1.39% short of the liquid's volume. At the default
/// gain the worst over 100 steps is within the 1% the long-horizon work asks of every mode
/// (measured 0.58%), and at a gain of 1 it is not (measured 1.39%).
#[test]
fn the_density_gain_keeps_the_dam_break_within_one_percent() {
    let worst = |gain: f64| {
        let mut scene = Scene::builtin("dam_break").unwrap();
        scene.solver.density_gain = gain;
        let worst = worst_volume_error(&scene, 100);
        eprintln!("density gain {gain}: worst volume error {:.2}%", 100.0 * worst);
        worst
    };
    let default = diffluid::world::SolverSettings::default().density_gain;
    assert!(worst(default) < 0.01, "the default gain should keep the volume within 1%");
    assert!(worst(1.0) > 0.01, "a gain of 1 should lose more (measured 1.12%)");
}

/// The smooth mode's settings (the liquid–air faces blended, φ_L ramped into bodies, air
/// pockets closed, no sparse-cell rule, θ clamped at 1e-5) keep the dam break's volume
/// within the 1% the long-horizon work asks of every mode with one density pass (measured
/// 0.60% over 100 steps; 1.28% before the particles next to a wall moved by the face
/// inside), and a second pass a step keeps more of what one leaves (measured 0.42%).
#[test]
fn the_smooth_mode_keeps_the_dam_break_within_one_percent() {
    let worst = |passes: usize| {
        let mut scene = Scene::builtin("dam_break").unwrap();
        scene.solver.use_smooth_surface_rules();
        scene.solver.density_passes = passes;
        let worst = worst_volume_error(&scene, 100);
        eprintln!("smooth mode, {passes} density passes: worst volume error {:.2}%", 100.0 * worst);
        worst
    };
    let one = worst(1);
    assert!(one < 0.01, "one pass should keep the smooth mode within 1%");
    assert!(worst(2) < 0.8 * one, "a second pass should keep more of the volume");
}

/// The largest |V − V₀|/V₀ of the liquid's volume (from the particles) over `steps` steps of
/// `scene`.
fn worst_volume_error(scene: &Scene, steps: usize) -> f64 {
    let mut sim = scene.build().unwrap();
    let v0 = sim.liquid_volume();
    let mut worst = 0.0f64;
    for _ in 0..steps {
        let r = sim.step().unwrap();
        worst = worst.max((r.liquid_volume - v0).abs() / v0);
    }
    worst
}
