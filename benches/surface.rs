//! The liquid surface mesh against the step it is drawn from: the dam break with a ball at
//! dx 0.05 (80×30×40 cells, dt 0.025), stepped to 10 and to 30 steps (the surge spreading,
//! then splashing), then one step and the mesh at 1, 2 and 3 samples per cell timed from that
//! state. Run it with `cargo bench --bench surface`.

use criterion::{criterion_group, criterion_main, BatchSize, Criterion};
use diffluid::io::liquid_mesh::liquid_surface;
use diffluid::Scene;
use std::hint::black_box;
use std::time::Duration;

fn surface(c: &mut Criterion) {
    let mut scene = Scene::builtin("dam_break_ball").expect("built-in scene");
    scene.domain.dx = 0.05;
    scene.time.dt = 0.025;
    let mut sim = scene.build().expect("valid scene");
    let mut group = c.benchmark_group("surface");
    for (from, to) in [(0, 10), (10, 30)] {
        for _ in from..to {
            sim.step().expect("step");
        }
        group.bench_function(format!("step_at_{to}"), |b| {
            b.iter_batched_ref(
                || sim.clone(),
                |s| black_box(s.step().expect("step")),
                BatchSize::LargeInput,
            )
        });
        for r in 1..=3 {
            group.bench_function(format!("mesh_{r}_samples_at_{to}"), |b| {
                b.iter(|| black_box(liquid_surface(&sim, r)))
            });
        }
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(Duration::from_secs(5));
    targets = surface
}
criterion_main!(benches);
