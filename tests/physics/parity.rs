//! Determinism: the same scene gives bit-identical results with 1 and 2 rayon threads, with
//! either preconditioner. Every parallel loop writes disjoint outputs and every reduction
//! sums fixed chunks in a fixed order (MIC(0)'s triangular solves compute each row as the
//! sequential sweep does, whatever the wave schedule; the multigrid smoother updates one
//! colour from the other), so the thread count must not change a single bit of the state.
//! Nor must the memory a step is built into: the last step's arrays (kept for the next, see
//! `world::step::Spare`) or fresh ones.

use diffluid::solvers::Preconditioner;
use diffluid::{Scene, Simulation};

fn run(threads: usize, preconditioner: Preconditioner) -> Simulation {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
    pool.install(|| {
        let mut scene = Scene::builtin("dam_break").unwrap();
        scene.solver.preconditioner = preconditioner;
        let mut sim = scene.build().unwrap();
        for _ in 0..15 {
            sim.step().unwrap();
        }
        sim
    })
}

#[test]
fn one_and_two_threads_agree_bit_for_bit_with_mic0() {
    agree(Preconditioner::Mic0);
}

#[test]
fn one_and_two_threads_agree_bit_for_bit_with_multigrid() {
    agree(Preconditioner::Multigrid);
}

fn agree(preconditioner: Preconditioner) {
    let (a, b) = (run(1, preconditioner), run(2, preconditioner));
    for axis in 0..3 {
        let same = a.velocity_field().c[axis]
            .iter()
            .zip(&b.velocity_field().c[axis])
            .all(|(x, y)| x.to_bits() == y.to_bits());
        assert!(same, "velocity component {axis} differs");
    }
    assert!(a
        .particles()
        .iter()
        .zip(b.particles())
        .all(|(p, q)| p.to_array().map(f64::to_bits) == q.to_array().map(f64::to_bits)));
    assert!(a.pressure().iter().zip(b.pressure()).all(|(x, y)| x.to_bits() == y.to_bits()));
    assert!(
        a.velocity_field().max_abs() > 1.0,
        "the flow must be under way for the comparison to mean something"
    );
}

/// `steps` steps of the dam break with a ball, each built into the last step's arrays, or
/// (`fresh`) into newly allocated ones.
fn dam_break_ball(fresh: bool, preconditioner: Preconditioner) -> Simulation {
    let mut scene = Scene::builtin("dam_break_ball").unwrap();
    scene.solver.preconditioner = preconditioner;
    let mut sim = scene.build().unwrap();
    for _ in 0..12 {
        if fresh {
            sim.release_spare();
        }
        sim.step().unwrap();
    }
    sim
}

#[test]
fn reused_and_fresh_memory_agree_bit_for_bit() {
    for preconditioner in [Preconditioner::Multigrid, Preconditioner::Mic0] {
        let (a, b) = (dam_break_ball(false, preconditioner), dam_break_ball(true, preconditioner));
        for axis in 0..3 {
            let same = a.velocity_field().c[axis]
                .iter()
                .zip(&b.velocity_field().c[axis])
                .all(|(x, y)| x.to_bits() == y.to_bits());
            assert!(same, "velocity component {axis} differs ({preconditioner:?})");
        }
        assert!(a.pressure().iter().zip(b.pressure()).all(|(x, y)| x.to_bits() == y.to_bits()));
        let (p, q) = (&a.bodies()[0], &b.bodies()[0]);
        assert_eq!(p.x.to_array().map(f64::to_bits), q.x.to_array().map(f64::to_bits));
        assert_eq!(p.v.to_array().map(f64::to_bits), q.v.to_array().map(f64::to_bits));
        assert!(a.velocity_field().max_abs() > 1.0, "the flow must be under way");
    }
}
