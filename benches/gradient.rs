//! Forward and backward passes of the paper's two experiments, and one block-drop
//! optimisation epoch, as the optimiser runs them:
//!
//! - `block_drop/forward_50` and `block_drop/backward_50`: the 50 taped steps, and the
//!   backward pass over their tape, with the surface held fixed (the scene's `[optimize]`
//!   setting);
//! - `dam_break_ball/forward_50` and `dam_break_ball/backward_50`: the same for the dam
//!   break with a ball (moving surface, contact taken as free flight in the gradient);
//! - `block_drop/epoch`: `Optimization::evaluate`, the loss and its gradient (forward plus
//!   backward) at the initial parameters;
//! - `large_tank_advection/forward` and `large_tank_advection/adjoint`: the velocity's
//!   advection and its adjoint (1ᵀ) on `large_tank`'s field after six steps (1M cells), on
//!   the faces the step reads: the adjoint's cost against the stage it transposes.
//!
//! Run with `cargo bench --bench gradient`; add e.g. `-- --warm-up-time 1
//! --measurement-time 5` for a quicker look, or `-- block_drop/epoch` for one.

use criterion::{criterion_group, criterion_main, Criterion, SamplingMode};
use diffluid::experiments::optimize::Optimization;
use diffluid::geometry::grid::Mac;
use diffluid::gradients::{backward, Loss};
use diffluid::stages::advect::{advect_adjoint_into, advect_into, needed_faces};
use diffluid::world::Tape;
use diffluid::{Scene, Simulation};
use std::hint::black_box;
use std::time::Duration;

/// The built-in scene `name` as its optimisation runs it (surface frozen if it asks).
fn prepared(name: &str) -> (Optimization, Simulation) {
    let opt = Optimization::new(Scene::builtin(name).expect("built-in scene")).expect("scene");
    let sim = opt.simulation(&opt.initial_params());
    (opt, sim)
}

fn passes(c: &mut Criterion, name: &str) {
    let (opt, sim) = prepared(name);
    let steps = opt.scene.time.steps;
    let mut group = c.benchmark_group(name);
    group.sampling_mode(SamplingMode::Flat);
    group.bench_function(format!("forward_{steps}"), |b| {
        b.iter(|| {
            let mut s = sim.clone();
            let mut tape = Tape::default();
            for _ in 0..steps {
                black_box(s.step_taped(&mut tape).expect("step"));
            }
            (s, tape)
        })
    });
    let mut last = sim.clone();
    let mut tape = Tape::default();
    for _ in 0..steps {
        last.step_taped(&mut tape).expect("step");
    }
    let adj = opt.loss.gradient(&last);
    group.bench_function(format!("backward_{steps}"), |b| {
        b.iter(|| backward(&sim, &tape, adj.clone(), &opt.gradient).expect("backward"))
    });
    if name == "block_drop" {
        let p = opt.initial_params();
        group
            .bench_function("epoch", |b| b.iter(|| opt.evaluate(black_box(&p), 0).expect("epoch")));
    }
    group.finish();
}

fn block_drop(c: &mut Criterion) {
    passes(c, "block_drop");
}

fn dam_break_ball(c: &mut Criterion) {
    passes(c, "dam_break_ball");
}

fn large_tank_advection(c: &mut Criterion) {
    let mut sim =
        Scene::builtin("large_tank").expect("scene").with_frozen_surface().build().expect("sim");
    let mut tape = Tape::default();
    for _ in 0..6 {
        sim.step_taped(&mut tape).expect("step");
    }
    let rec = tape.steps.last().expect("six steps");
    let (grid, dt) = (*sim.grid(), sim.dt());
    let mask = needed_faces(&grid, &sim.particle_phi(), &rec.body_faces);
    // An adjoint on the faces the step reads, varied so that no sum is trivially zero.
    let mut adj = Mac::zeros(&grid);
    for (a, c) in adj.c.iter_mut().enumerate() {
        for (f, x) in c.iter_mut().enumerate().filter(|(f, _)| mask[a][*f]) {
            *x = ((f * 7919 + a * 31) % 1000) as f64 * 1e-3 - 0.5;
        }
    }
    let mut out = Mac::zeros(&grid);
    let mut group = c.benchmark_group("large_tank_advection");
    group.bench_function("forward", |b| {
        b.iter(|| advect_into(&rec.u, &grid, dt, Some(&mask), black_box(&mut out)))
    });
    group.bench_function("adjoint", |b| {
        b.iter(|| advect_adjoint_into(&rec.u, &adj, &grid, dt, Some(&mask), black_box(&mut out)))
    });
    group.finish();
}

criterion_group! {
    name = gradient;
    config = Criterion::default().sample_size(10).measurement_time(Duration::from_secs(10));
    targets = block_drop, dam_break_ball, large_tank_advection
}
criterion_main!(gradient);
