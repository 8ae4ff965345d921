//! The dam break of Patel et al.: a 0.4 × 0.7 × 1.0 m block of water collapses along a 4 m
//! tank. Two physical facts are checked over the paper's 50 steps of 0.05 s:
//! - volume: the liquid is incompressible, so its volume (measured from the marker
//!   particles' density on the grid, see `surface::liquid_volume`) stays within 2% of the
//!   start;
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
    let front = |sim: &Simulation| sim.particles.iter().map(|p| p.x).fold(f64::MAX, f64::min);
    let mut last = front(&sim);
    assert!((last - 3.6).abs() < 0.5 * dx);
    let mut reached = None;
    for _ in 0..50 {
        let r = sim.step().unwrap();
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
    let reached = reached.expect("the front reaches the −x wall within 2.5 s");
    eprintln!("front reached the wall at step {reached}");
    assert!(reached >= 10, "the front cannot cross 3.6 m in {reached} steps of 0.05 s");
}
