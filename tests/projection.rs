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

use diffluid::experiments::shapes::{AxisAngle, Placed, ShapeSpec};
use diffluid::geometry::fractions::face_weights;
use diffluid::geometry::grid::{dot, Grid, Mac};
use diffluid::geometry::weights::FaceWeights;
use diffluid::solvers::{LinearSolve, Preconditioner};
use diffluid::stages::pressure::{PressureParams, PressureSystem};

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
    let params = PressureParams { dt: 0.01, density: 1000.0, theta_min: 0.01 };
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
