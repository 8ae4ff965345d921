//! Forward and backward passes of the paper's two experiments, and one block-drop
//! optimisation epoch, as the optimiser runs them:
//!
//! - `block_drop/forward_50` and `block_drop/backward_50`: the 50 taped steps, and the
//!   backward pass over their tape, with the surface held fixed (the scene's `[optimize]`
//!   setting);
//! - `dam_break_ball/forward_50` and `dam_break_ball/backward_50`: the same for the dam
//!   break with a ball (moving surface, contact taken as free flight in the gradient);
//! - `block_drop/epoch`: `Optimization::evaluate`, the loss and its gradient (forward plus
//!   backward) at the initial parameters.
//!
//! Run with `cargo bench --bench gradient`; add e.g. `-- --warm-up-time 1
//! --measurement-time 5` for a quicker look, or `-- block_drop/epoch` for one.

use criterion::{criterion_group, criterion_main, Criterion, SamplingMode};
use diffluid::experiments::optimize::Optimization;
use diffluid::gradients::{backward, Loss};
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
        group.bench_function("epoch", |b| b.iter(|| opt.evaluate(black_box(&p)).expect("epoch")));
    }
    group.finish();
}

fn block_drop(c: &mut Criterion) {
    passes(c, "block_drop");
}

fn dam_break_ball(c: &mut Criterion) {
    passes(c, "dam_break_ball");
}

criterion_group! {
    name = gradient;
    config = Criterion::default().sample_size(10).measurement_time(Duration::from_secs(10));
    targets = block_drop, dam_break_ball
}
criterion_main!(gradient);
