//! Gradient of a loss on a floating box's final position with respect to its initial
//! state, through the Rust API: `cargo run --release --example gradient`.
//!
//! `cargo run --release --example gradient -- SCENE [RUNS]` takes a scene's own `[loss]`
//! instead and runs it RUNS times (default 1), printing each run's forward and backward
//! seconds: how docs/performance.md times whole gradients.
use diffluid::gradients::{value_and_gradient, BodyTargetLoss, GradientSettings};
use diffluid::math::Vec3;
use diffluid::Scene;

fn main() -> diffluid::Result<()> {
    let mut args = std::env::args().skip(1);
    let (scene, loss, runs) = match args.next() {
        Some(name) => {
            // A built-in name, or a scene file.
            let scene = match Scene::builtin(&name) {
                Ok(scene) => scene,
                Err(_) => Scene::from_file(std::path::Path::new(&name))?,
            };
            let Some(loss) = scene.loss() else {
                eprintln!("the scene {name} has no [loss] section");
                std::process::exit(2);
            };
            let runs = match args.next().map(|r| r.parse::<usize>()) {
                None => 1,
                Some(Ok(r)) if r > 0 => r,
                Some(_) => {
                    eprintln!("RUNS is a whole number of runs, at least 1");
                    std::process::exit(2);
                }
            };
            (scene, loss, runs)
        }
        None => {
            let loss = BodyTargetLoss {
                body: 0,
                position: Some((Vec3::new(0.35, 0.2, 0.45), 1.0)),
                orientation: None,
                velocity: None,
            };
            (Scene::builtin("gradcheck_box")?, loss, 1)
        }
    };
    let steps = scene.time.steps;
    let sim = scene.build()?;
    for _ in 0..runs {
        let run = value_and_gradient(&sim, steps, &loss, &GradientSettings::default())?;
        let g = run.gradient.bodies[0];
        println!("loss {:.6e}", run.loss);
        println!("dL/dv0 {:?}\ndL/dw0 {:?}\ndL/dx0 {:?}\ndL/dq0 {:?}", g.v, g.w, g.x, g.q);
        println!(
            "forward {:.3} s, backward {:.3} s ({:.2}x)",
            run.forward_seconds,
            run.backward_seconds,
            run.backward_seconds / run.forward_seconds
        );
    }
    Ok(())
}
