//! Gradient of a loss on a floating box's final position with respect to its initial
//! state, through the Rust API: `cargo run --release --example gradient`.
use diffluid::gradients::{value_and_gradient, BodyTargetLoss, GradientSettings};
use diffluid::math::Vec3;
use diffluid::Scene;

fn main() -> diffluid::Result<()> {
    let scene = Scene::builtin("gradcheck_box")?;
    let steps = scene.time.steps;
    let sim = scene.build()?;
    let loss = BodyTargetLoss {
        body: 0,
        position: Some((Vec3::new(0.35, 0.2, 0.45), 1.0)),
        orientation: None,
        velocity: None,
    };
    let run = value_and_gradient(&sim, steps, &loss, &GradientSettings::default())?;
    let g = run.gradient.bodies[0];
    println!("loss {:.6e}", run.loss);
    println!("dL/dv0 {:?}\ndL/dw0 {:?}\ndL/dx0 {:?}\ndL/dq0 {:?}", g.v, g.w, g.x, g.q);
    println!("forward {:.3} s, backward {:.3} s", run.forward_seconds, run.backward_seconds);
    Ok(())
}
