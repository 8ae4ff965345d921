//! Optimise a body's initial velocity through the Rust API: a box must end 20 steps later
//! at a target. `cargo run --release --example optimize_velocity`.
use diffluid::geometry::body::BodyState;
use diffluid::gradients::{value_and_gradient, BodyTargetLoss, GradientSettings};
use diffluid::math::Vec3;
use diffluid::Scene;

fn main() -> diffluid::Result<()> {
    let scene = Scene::builtin("recover_box")?;
    let steps = scene.time.steps;
    let mut sim = scene.build()?;
    let loss = BodyTargetLoss {
        body: 0,
        position: Some((Vec3::new(0.5, 0.22, 0.3), 1.0)),
        orientation: None,
        velocity: None,
    };
    let learning_rate = 5.0;
    for epoch in 0..40 {
        let run = value_and_gradient(&sim, steps, &loss, &GradientSettings::default())?;
        let g = run.gradient.bodies[0].v;
        if epoch % 5 == 0 {
            println!(
                "epoch {epoch:2}: loss {:.3e}, v0 = {:.4?}",
                run.loss,
                sim.bodies()[0].v.to_array()
            );
        }
        let h = sim.handles()[0];
        let state = BodyState { v: sim[h].v - learning_rate * g, ..sim[h].state() };
        sim.set_body_state(h, &state)?;
    }
    println!("final v0 = {:.4?}", sim.bodies()[0].v.to_array());
    Ok(())
}
