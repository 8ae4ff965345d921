//! A pool for a game prototype: a 3.2 × 1.6 × 3.2 m tank, 0.7 m of water, a crate, a ball
//! and a log floating in it, advanced one display frame (1/60 s) at a time, as a game loop
//! would, printing the frames per second it sustains.
//!
//! ```text
//! cargo run --release --example realtime_pool -- [CELLS] [SECONDS]
//! ```
//!
//! `CELLS` is the cells across the tank (default 64: a 64 × 32 × 64 grid, 131k cells);
//! `SECONDS` the simulated time (default 4). Every setting is the default one: the narrow band
//! of marker particles is chosen from the scene (the line `model:` says so); only the step
//! report's measures of the liquid, which a game never reads, are turned off. A second thread
//! runs the step's loops where they are large enough to pay for it (`RAYON_NUM_THREADS=1`
//! runs everything on one). What it measured on this project's machine is in
//! docs/performance.md ("A pool at 30 frames a second"); `diffluid bench --only realtime`
//! charts the frame time against the grid's size. It runs on the allocator the `diffluid`
//! binary runs on ([`GridAllocator`]): glibc keeps what a step frees for the next step,
//! instead of handing each whole-grid array back to the kernel and faulting it in again.

use diffluid::geometry::body::RigidBody;
use diffluid::geometry::shape::Solid;
use diffluid::math::memory::GridAllocator;
use diffluid::math::{Pose, Rotation, SharedShape, Vec3};
use diffluid::world::Simulation;
use std::time::Instant;

#[global_allocator]
static ALLOCATOR: GridAllocator = GridAllocator;

fn main() -> diffluid::Result<()> {
    // Before rayon starts its threads.
    GridAllocator::tune();
    let mut args = std::env::args().skip(1);
    let cells: usize = args.next().map_or(64, |a| a.parse().expect("CELLS: a whole number"));
    let seconds: f64 = args.next().map_or(4.0, |a| a.parse().expect("SECONDS: a number"));
    let dx = 3.2 / cells as f64;
    let at = |x: f64, y: f64, z: f64| Pose::from_translation(Vec3::new(x, y, z));
    let log =
        Pose::from_parts(Vec3::new(2.3, 0.7, 1.1), Rotation::from_rotation_z(90f64.to_radians()));
    let mut sim = Simulation::builder([3.2, 1.6, 3.2], dx)
        .dt(1.0 / 60.0)
        .liquid(Solid::aabb(Vec3::ZERO, Vec3::new(3.2, 0.7, 3.2)))
        .body(RigidBody::with_density(
            "crate".into(),
            SharedShape::cuboid(0.2, 0.15, 0.2),
            at(0.8, 0.72, 0.9),
            400.0,
        ))
        .body(RigidBody::with_density(
            "ball".into(),
            SharedShape::ball(0.2),
            at(1.7, 0.72, 2.1),
            600.0,
        ))
        .body(RigidBody::with_density("log".into(), SharedShape::capsule_y(0.3, 0.1), log, 700.0))
        .build()?;
    // A game reads the bodies, not the step report's measures of the liquid (its energy,
    // volume and fastest speed: a sixth of a frame here).
    sim.set_report_measures(false);
    let grid = *sim.grid();
    println!(
        "{}×{}×{} cells, {} threads; model: {}",
        grid.n[0],
        grid.n[1],
        grid.n[2],
        rayon::current_num_threads(),
        sim.model()
    );
    let frames = (seconds * 60.0).round() as usize;
    let mut times = Vec::with_capacity(frames);
    // Per step: each stage's seconds (the report's `stage_seconds`).
    let mut stages: Vec<[(&str, f64); 11]> = Vec::new();
    let mut steps = 0;
    let (mut window, mut shown) = (Instant::now(), 0);
    for frame in 1..=frames {
        let t = Instant::now();
        let reports = sim.advance(1.0 / 60.0)?;
        times.push(t.elapsed().as_secs_f64());
        steps += reports.len();
        stages.extend(reports.iter().map(|r| r.stage_seconds.named()));
        if window.elapsed().as_secs_f64() >= 1.0 || frame == frames {
            let fps = (frame - shown) as f64 / window.elapsed().as_secs_f64();
            let heights: Vec<String> =
                sim.bodies().iter().map(|b| format!("{} {:.3} m", b.name, b.x.y)).collect();
            println!("t = {:.2} s: {fps:.1} frames/s ({})", sim.time(), heights.join(", "));
            (window, shown) = (Instant::now(), frame);
        }
    }
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let slowest = times.iter().copied().fold(0.0, f64::max);
    let frame = median(times);
    println!(
        "{frames} frames in {steps} steps: median frame {:.1} ms ({:.1} frames/s), slowest {:.1} ms",
        1e3 * frame,
        1.0 / frame,
        1e3 * slowest
    );
    // Where a step's time goes: each stage's median, and the median of their sums.
    let sum = median(stages.iter().map(|s| s.iter().map(|(_, t)| t).sum()).collect());
    let each: Vec<String> = (0..11)
        .map(|i| (stages[0][i].0, median(stages.iter().map(|s| s[i].1).collect())))
        .filter(|(_, t)| *t >= 5e-5)
        .map(|(name, t)| format!("{name} {:.1}", 1e3 * t))
        .collect();
    println!("stages a step (medians, ms): {:.1} in all; {}", 1e3 * sum, each.join(", "));
    Ok(())
}
