//! A program that owns its bodies in rapier couples them to diffluid's liquid: a box and a
//! mesh fall into a pool. rapier keeps gravity, integration and contact; each step it hands
//! diffluid the bodies' poses and velocities, diffluid solves the liquid and the bodies in one
//! pressure solve, and rapier takes back the pressure impulse.
//! `cargo run --release --example rapier_coupling` (also run by `cargo test`).
use diffluid::prelude::*;
use rapier3d_f64::prelude::{ColliderBuilder, PhysicsWorld, RigidBodyBuilder};

/// Runs `steps` steps and returns the bodies' final heights.
fn run(steps: usize) -> diffluid::Result<Vec<f64>> {
    let dt = 0.01;
    let mut world = PhysicsWorld::new(); // gravity −9.81 along y
    world.integration_parameters.dt = dt;
    world.insert(
        RigidBodyBuilder::fixed(),
        ColliderBuilder::cuboid(1.0, 0.05, 1.0).translation(Vec3::new(0.4, -0.05, 0.3)),
    );
    let mesh =
        load_obj(concat!(env!("CARGO_MANIFEST_DIR"), "/assets/meshes/cube.obj").as_ref(), 0.6)?;
    let shapes = [(SharedShape::cuboid(0.08, 0.05, 0.06), 0.25, 600.0), (mesh, 0.55, 400.0)];
    let mut sim = Simulation::builder([0.8, 0.6, 0.6], 0.04)
        .dt(dt)
        .liquid(Solid::aabb(Vec3::ZERO, Vec3::new(0.8, 0.28, 0.6)))
        .build()?;
    let mut pairs = Vec::new();
    for (shape, x, density) in shapes {
        let rb = RigidBodyBuilder::dynamic()
            .translation(Vec3::new(x, 0.45, 0.3))
            .rotation(Vec3::new(0.0, 0.0, 0.3));
        let (h, _) = world.insert(rb, ColliderBuilder::new(shape.clone()).density(density));
        let b = &world.bodies[h];
        let body = RigidBody::builder(format!("b{}", pairs.len()), shape)
            .mass_properties(b.mass_properties().local_mprops)
            .pose(*b.position())
            .motion(Motion::External)
            .build()?;
        pairs.push((h, sim.add_body(body)?));
    }
    for _ in 0..steps {
        for &(h, body) in &pairs {
            let b = &world.bodies[h];
            let state = BodyState {
                x: b.center_of_mass(),
                q: b.position().rotation,
                v: b.linvel(),
                w: b.angvel(),
            };
            sim.set_body_state(body, &state)?;
        }
        sim.step()?;
        for &(h, body) in &pairs {
            let (force, torque) = sim.fluid_force(body)?;
            world.bodies[h].apply_impulse(dt * force, true);
            world.bodies[h].apply_torque_impulse(dt * torque, true);
        }
        world.step();
    }
    Ok(pairs.iter().map(|&(h, _)| world.bodies[h].center_of_mass().y).collect())
}

fn main() -> diffluid::Result<()> {
    println!("heights after 1.5 s: {:.3?} m (water surface at 0.28 m)", run(150)?);
    Ok(())
}

/// Both bodies, lighter than water, end floating at the surface: neither sank to the floor
/// nor stayed in the air where they were dropped.
#[test]
fn rapier_bodies_float_in_the_pool() {
    for y in run(150).unwrap() {
        assert!((0.2..0.33).contains(&y), "height {y}");
    }
}
