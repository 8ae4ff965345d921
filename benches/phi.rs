//! φ_L from the particles, the nearest particle's distance against the soft minimum of
//! their distances (`solver.surface_softness = 0.35`), on `large_tank` (1M cells, a narrow
//! band of particles) after two steps, the soft minimum made in every cell and only where a
//! step reads its value (`surface::Reads`, the default). The bodies' ghosts are left out.
//! Run it with `cargo bench --bench phi`.

use criterion::{criterion_group, criterion_main, Criterion};
use diffluid::stages::band::Band;
use diffluid::stages::solid_phi::extension_reads;
use diffluid::stages::surface::{liquid_sdf, Bins, Reads, SurfaceModel};
use diffluid::Scene;
use std::hint::black_box;
use std::time::Duration;

fn phi(c: &mut Criterion) {
    let scene = Scene::builtin("large_tank").expect("built-in scene");
    let mut sim = scene.build().expect("valid scene");
    for _ in 0..2 {
        sim.step().expect("step");
    }
    let (grid, particles) = (sim.grid(), sim.particles());
    let solver = &sim.settings().solver;
    let dx = grid.dx;
    let deep = sim.band().map(Band::deep);
    let bins = Bins::new(particles, grid);
    let nearest = solver.surface_model(dx, solver.particle_radius(dx));
    let per_axis = nearest.per_axis;
    let soft = SurfaceModel::soft(dx, per_axis, 0.35);
    let geometry = sim.geometry();
    let near_solids = extension_reads(grid, &geometry.centre_in_solid, &geometry.partial);
    let reads = Some(Reads { near_solids: &near_solids });
    let mut group = c.benchmark_group("phi");
    for (name, model, reads) in
        [("nearest", &nearest, None), ("soft", &soft, None), ("soft_read", &soft, reads)]
    {
        group.bench_function(name, |b| {
            b.iter(|| black_box(liquid_sdf(particles, &bins, &[], grid, model, deep, reads)))
        });
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(Duration::from_secs(8));
    targets = phi
}
criterion_main!(benches);
