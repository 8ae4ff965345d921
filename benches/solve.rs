//! Pressure-solve speed: the coupled pressure system of one step (a tank filled to a wavy free
//! surface with a dynamic ball floating in it, so fractional face weights, ghost-fluid
//! diagonals and a rank-6 body term are all present) solved to a relative residual of 1e-6,
//! at 32³, 64³ and 128³, with MIC(0) and with multigrid. The time includes building the
//! preconditioner, as in every step. Run it with `cargo bench --bench solve` (compare
//! `RAYON_NUM_THREADS=1` and `=2` for the parallel speed-up); the CG iteration counts are
//! printed once per case before timing.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, SamplingMode};
use diffluid::experiments::shapes::{Placed, ShapeSpec};
use diffluid::geometry::body::RigidBody;
use diffluid::geometry::fractions::{body_jacobian, face_weights};
use diffluid::geometry::grid::{Grid, Mac};
use diffluid::geometry::weights::FaceWeights;
use diffluid::solvers::{LinearSolve, Preconditioner};
use diffluid::stages::pressure::{BodyCoupling, GhostFluid, PressureParams, PressureSystem};
use diffluid::world::step::{dt_minv, generalized_velocity};
use std::hint::black_box;
use std::time::Duration;

/// Relative residual the benchmark solves to.
const TOLERANCE: f64 = 1e-6;

/// The coupled system on an n³ grid of the unit cube and its right-hand side.
fn coupled_system(n: usize) -> (PressureSystem, Vec<f64>) {
    let grid = Grid { n: [n; 3], dx: 1.0 / n as f64 };
    let dt = 0.01;
    let ball = Placed {
        shape: ShapeSpec::Ball { radius: 0.15 },
        position: [0.45, 0.55, 0.5],
        quaternion: None,
        axis_angle: None,
    }
    .build(std::path::Path::new("."))
    .expect("a ball");
    let mut body = RigidBody::with_density("ball".into(), ball.shape.clone(), ball.pose, 600.0);
    body.v = diffluid::math::v3([0.1, -0.5, 0.05]);
    body.w = diffluid::math::v3([0.0, 0.3, 2.0]);
    let faces = body.face_fractions(&grid);
    let mut weights = FaceWeights::new(&face_weights(&grid, &[]));
    weights.subtract(&faces.faces);
    let cells = grid.cells();
    let mut phi = vec![0.0; cells.len()];
    cells.fill_par(&mut phi, |i, j, k| {
        let p = cells.position(i, j, k);
        p.y - 0.6 - 0.05 * (std::f64::consts::TAU * p.x).sin() * (std::f64::consts::PI * p.z).cos()
    });
    let mut sys = PressureSystem::build(
        &grid,
        &phi,
        &weights,
        PressureParams { dt, density: 1000.0, ghost: GhostFluid::clamped(0.01) },
    );
    let jac = body_jacobian(&grid, &faces, body.x, body.spin());
    sys.bodies.push(BodyCoupling::new(&sys.row_of_cell, &jac, dt_minv(&body, dt)));
    // Gravity's velocity increment plus a seeded rough field.
    let mut u = Mac::zeros(&grid);
    for a in 0..3 {
        for (f, x) in u.c[a].iter_mut().enumerate() {
            let rough = ((f.wrapping_mul(2654435761) >> 7) % 1000) as f64 / 1000.0 - 0.5;
            *x = 0.1 * rough - if a == 1 { 9.81 * dt } else { 0.0 };
        }
    }
    let b = sys.rhs(&u, &weights, &[generalized_velocity(&body)]);
    (sys, b)
}

fn solve(c: &mut Criterion) {
    let mut group = c.benchmark_group("coupled_solve");
    group.sampling_mode(SamplingMode::Flat);
    for n in [32, 64, 128] {
        let (sys, b) = coupled_system(n);
        for (name, pre) in
            [("mic0", Preconditioner::Mic0), ("multigrid", Preconditioner::Multigrid)]
        {
            let (_, stats) = sys.solve(&b, &LinearSolve::new(pre, TOLERANCE, 5000));
            assert!(stats.converged, "{name} at {n}³: {stats:?}");
            eprintln!(
                "{n}³ ({} unknowns), {name}: {} iterations, relative residual {:.2e}",
                sys.len(),
                stats.iterations,
                stats.relative_residual
            );
            group.bench_with_input(BenchmarkId::new(name, format!("{n}^3")), &pre, |bch, &pre| {
                bch.iter(|| {
                    black_box(sys.solve(black_box(&b), &LinearSolve::new(pre, TOLERANCE, 5000)))
                })
            });
        }
    }
    group.finish();
}

criterion_group! {
    name = benches;
    // Set on the runner (not the group) so `--measurement-time` on the command line wins.
    config = Criterion::default().sample_size(10).measurement_time(Duration::from_secs(10));
    targets = solve
}
criterion_main!(benches);
