//! The projection makes the velocity divergence-free to solver tolerance.
//!
//! Row i of the pressure system is "volume flux out of cell i after the update = 0", so the
//! CG residual b − A·p equals minus the flux out of each cell after the velocity update.
//! This test projects a rough velocity field in a tank with a free surface and a tilted
//! obstacle (partial face weights), then checks that (1) the solve met its tolerance, (2)
//! the flux actually left in every cell after the update equals the solver's residual, so
//! the relative divergence is the relative residual, and (3) the largest divergence is
//! correspondingly small. (2) fails if the velocity update and the operator disagree on a
//! single face weight, θ or sign.

use crate::common::tank_toml;
use diffluid::experiments::shapes::{AxisAngle, Placed, ShapeSpec};
use diffluid::geometry::fractions::face_weights;
use diffluid::geometry::grid::{dot, Grid, Mac};
use diffluid::geometry::weights::FaceWeights;
use diffluid::solvers::{LinearSolve, Preconditioner};
use diffluid::stages::pressure::{GhostFluid, PressureParams, PressureSystem};

fn rough_field(grid: &Grid) -> Mac {
    let mut u = Mac::zeros(grid);
    for a in 0..3 {
        let lat = grid.faces(a);
        let mut c = vec![0.0; lat.len()];
        lat.fill_par(&mut c, |i, j, k| {
            (((i * 31 + j * 17 + k * 7 + a * 5) % 23) as f64 / 11.0 - 1.0) * 0.7
        });
        u.c[a] = c;
    }
    u
}

#[test]
fn projection_leaves_divergence_at_solver_tolerance() {
    let grid = Grid { n: [18, 14, 12], dx: 0.05 };
    let obstacle = Placed {
        shape: ShapeSpec::Cuboid { half_extents: [0.12, 0.08, 0.1] },
        position: [0.45, 0.2, 0.3],
        quaternion: None,
        axis_angle: Some(AxisAngle { axis: [0.3, 1.0, 0.2], degrees: 33.0 }),
    }
    .build(std::path::Path::new("."))
    .unwrap();
    let weights = FaceWeights::new(&face_weights(&grid, &[obstacle]));
    let partial: usize =
        (0..3).map(|a| weights.cut(a).filter(|&(_, w)| w > 0.0 && w < 1.0).count()).sum();
    assert!(partial > 50, "the obstacle must cut faces partially ({partial})");
    // A wavy free surface: φ_L < 0 below y = 0.45 + 0.05 sin(...).
    let cells = grid.cells();
    let mut phi = vec![0.0; cells.len()];
    cells.fill_par(&mut phi, |i, j, k| {
        let p = cells.position(i, j, k);
        p.y - (0.45 + 0.05 * (7.0 * p.x).sin() * (5.0 * p.z).cos())
    });
    let params = PressureParams { dt: 0.01, density: 1000.0, ghost: GhostFluid::clamped(0.01) };
    let sys = PressureSystem::build(&grid, &phi, &weights, params);
    assert!(sys.has_air && sys.len() > 1000);
    let mut u = rough_field(&grid);
    let b = sys.rhs(&u, &weights, &[]);
    let tol = 1e-8;
    let (p, stats) = sys.solve(&b, &LinearSolve::new(Preconditioner::Mic0, tol, 1000));
    assert!(stats.converged && stats.relative_residual <= tol, "{stats:?}");
    sys.update_velocity(&p, &mut u);
    let flux = sys.fluid_flux(&u, &weights);
    let rel_div = dot(&flux, &flux).sqrt() / dot(&b, &b).sqrt();
    assert!(
        (rel_div - stats.relative_residual).abs() <= 1e-6 * stats.relative_residual + 1e-15,
        "flux left after the update ({rel_div:e}) is not the solver residual ({:e})",
        stats.relative_residual
    );
    let vol = grid.dx.powi(3);
    let max_div = flux.iter().fold(0.0f64, |m, f| m.max(f.abs())) / vol;
    let bound = tol * dot(&b, &b).sqrt() / vol;
    let before = b.iter().fold(0.0f64, |m, f| m.max(f.abs())) / vol;
    assert!(max_div <= bound, "max divergence {max_div:e} 1/s above {bound:e}");
    assert!(max_div < 1e-7 * before, "divergence fell only from {before:e} to {max_div:e}");
}

/// A step's face weights, built into the memory of the last step's (a `FaceWeights` a byte a
/// face, the static solids' copied in and each body's fractions subtracted), are the dense
/// `clamp(w_static − β, 0, 1)` face by face, to the bit, step after step: with two obstacles
/// that cut faces (a ball and a tilted box) and two bodies, a ball a fifth of a cell above
/// the obstacle ball, so that some faces are cut by both.
#[test]
fn a_steps_weights_are_the_dense_weights() {
    let text = tank_toml("weights", [1.6, 0.8, 0.8], 0.05, 0.45, 4)
        + r#"
[[obstacle]]
shape = { kind = "ball", radius = 0.13 }
position = [1.2, 0.1, 0.4]
[[obstacle]]
shape = { kind = "cuboid", half_extents = [0.06, 0.2, 0.15] }
position = [0.6, 0.2, 0.41]
axis_angle = { axis = [0.2, 1.0, 0.3], degrees = 27.0 }
[[body]]
name = "ball"
shape = { kind = "ball", radius = 0.11 }
density = 600.0
position = [1.2, 0.35, 0.4]
[[body]]
name = "block"
shape = { kind = "cuboid", half_extents = [0.08, 0.05, 0.1] }
density = 500.0
position = [0.79, 0.43, 0.4]
axis_angle = { axis = [1.0, 0.3, 0.0], degrees = 12.0 }
"#;
    let mut sim =
        diffluid::Scene::from_toml(&text, "weights").expect("scene").build().expect("build");
    let grid = *sim.grid();
    let statics = sim.statics().weights.to_dense();
    let cut = |w: &[Vec<f64>; 3]| w.iter().flatten().filter(|w| **w > 0.0 && **w < 1.0).count();
    assert!(cut(&statics) > 100, "the obstacles cut faces ({})", cut(&statics));
    for step in 0..4 {
        let geometry = sim.geometry();
        let mut dense = statics.clone();
        let mut shared = 0;
        for body in sim.bodies() {
            for (a, list) in body.face_fractions(&grid).faces.iter().enumerate() {
                for &(f, beta) in list {
                    shared += usize::from(beta > 0.0 && statics[a][f] > 0.0 && statics[a][f] < 1.0);
                    dense[a][f] = (dense[a][f] - beta).clamp(0.0, 1.0);
                }
            }
        }
        assert!(shared > 0, "step {step}: faces that an obstacle and a body both cut");
        assert!(cut(&dense) > cut(&statics), "step {step}: the bodies cut faces");
        for (a, dense) in dense.iter().enumerate() {
            for (f, w) in dense.iter().enumerate() {
                let got = geometry.weights.weight(a, f);
                assert_eq!(got.to_bits(), w.to_bits(), "step {step}, axis {a}, face {f}");
            }
        }
        sim.step().expect("step");
    }
}
