//! Forward-simulation speed: wall time of a whole run of a shipped scene, from
//! `Simulation::new` (static geometry and particle seeding, part of every run) through all of
//! its steps — the dam break for its 50 steps and still water for its 100. Run it with
//! `cargo bench --bench forward` (add e.g. `-- --warm-up-time 1 --measurement-time 5` for a
//! quicker look).

use criterion::{criterion_group, criterion_main, Criterion, SamplingMode};
use diffluid::Scene;
use std::hint::black_box;
use std::time::Duration;

/// Times `steps` steps of the built-in scene `name`, construction included.
fn bench_scene(c: &mut Criterion, name: &str, steps: usize) {
    let scene = Scene::builtin(name).expect("built-in scene");
    assert_eq!(scene.time.steps, steps, "{name} no longer has {steps} steps");
    let mut group = c.benchmark_group("forward");
    // One run takes around a second or more: every sample gets the same number of runs
    // rather than criterion's linearly growing counts.
    group.sampling_mode(SamplingMode::Flat);
    group.bench_function(format!("{name}_{steps}_steps"), |b| {
        b.iter(|| {
            let mut sim = black_box(scene.clone()).build().expect("valid scene");
            for _ in 0..steps {
                black_box(sim.step().expect("step"));
            }
            sim
        })
    });
    group.finish();
}

fn dam_break(c: &mut Criterion) {
    bench_scene(c, "dam_break", 50);
}

fn still_water(c: &mut Criterion) {
    bench_scene(c, "still_water", 100);
}

criterion_group! {
    name = forward;
    // Set on the runner (not the group) so `--measurement-time` on the command line wins.
    config = Criterion::default().sample_size(10).measurement_time(Duration::from_secs(15));
    targets = dam_break, still_water
}
criterion_main!(forward);
