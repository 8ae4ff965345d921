//! A long checkpointed gradient on the 1M-cell `large_tank`, with its forward and backward
//! times, the backward pass split into re-running segments and the adjoint sweep, and the
//! sweep per stage adjoint (the figures of docs/performance.md, "Gradients at 1M cells"):
//!
//! ```sh
//! cargo run --release --example checkpointed_gradient -- 50 7
//! cargo run --release --example checkpointed_gradient -- 12 4 --live
//! ```
//!
//! Arguments: steps (default 50), checkpoint every (default 7; 0 keeps the whole tape),
//! `--live` for the moving surface (default: frozen), `--re-solve` to solve again in the
//! re-runs. It runs on the allocator the `diffluid` binary runs on
//! ([`GridAllocator`](diffluid::math::memory::GridAllocator)); peak memory is the process's
//! (`/usr/bin/time -v`).
use diffluid::gradients::{
    backward::SurfaceGradient, value_and_gradient, BodyTargetLoss, GradientOptions,
    GradientSettings,
};
use diffluid::math::memory::GridAllocator;
use diffluid::math::Vec3;
use diffluid::Scene;

#[global_allocator]
static ALLOCATOR: GridAllocator = GridAllocator;

fn main() -> diffluid::Result<()> {
    GridAllocator::tune();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let number = |i: usize, default: usize| {
        args.iter()
            .filter(|a| !a.starts_with("--"))
            .nth(i)
            .map_or(default, |a| a.parse().unwrap_or_else(|_| panic!("not a whole number: {a}")))
    };
    let (steps, every) = (number(0, 50), number(1, 7));
    let live = args.iter().any(|a| a == "--live");
    let re_solve = args.iter().any(|a| a == "--re-solve");
    let scene = Scene::builtin("large_tank")?;
    let scene = if live { scene } else { scene.with_frozen_surface() };
    let sim = scene.build()?;
    let loss = BodyTargetLoss {
        body: 0,
        position: Some((sim.bodies()[0].x + Vec3::new(0.05, 0.0, 0.0), 1.0)),
        orientation: None,
        velocity: None,
    };
    let surface = if live { SurfaceGradient::Live } else { SurfaceGradient::Frozen };
    let settings = GradientSettings {
        options: GradientOptions { surface, ..Default::default() },
        checkpoint_every: (every > 0).then_some(every),
        re_solve,
    };
    let run = value_and_gradient(&sim, steps, &loss, &settings)?;
    let a = run.adjoint_seconds;
    let sweep = a.assemble
        + a.rigid
        + a.correct_velocity
        + a.pressure
        + a.advect_velocity
        + a.advect_particles;
    println!(
        "{steps} steps, checkpoint every {every}, surface {}: loss {:.6e}",
        if live { "moving" } else { "frozen" },
        run.loss
    );
    println!(
        "forward {:.2} s, backward {:.2} s ({:.2}x): re-runs {:.2} s, adjoint sweep {:.2} s",
        run.forward_seconds,
        run.backward_seconds,
        run.backward_seconds / run.forward_seconds,
        run.backward_seconds - sweep,
        sweep
    );
    println!("sweep per stage adjoint: {a:?}");
    println!("tape {} MB a step", run.tape_bytes_per_step / 1_000_000);
    Ok(())
}
