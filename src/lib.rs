//! diffluid: differentiable Eulerian liquid simulation with strong two-way rigid coupling.
//!
//! A liquid on a MAC grid with marker particles for its free surface, and rigid bodies of any
//! parry shape coupled to it through one monolithic pressure solve (Batty et al. 2007); an
//! adjoint backward pass gives the gradient of a loss on the final state with respect to the
//! initial state (Patel et al., "Differentiable Two-Way Eulerian Fluid-Solid Coupling").
//!
//! The layers, each a folder, lowest first (ARCHITECTURE.md draws them; `tests/api/layers.rs`
//! holds every module to them): [`math`] and [`error`]; [`geometry`] (grid, shapes, meshes,
//! bodies, face fractions); [`solvers`] (CG, MIC(0), multigrid); [`stages`] (each stage of a
//! step with its adjoint); [`world`] (the [`Simulation`], its settings, the step assembly the
//! forward and backward passes share, the tape); [`gradients`] (losses, the backward pass,
//! gradient checks); [`io`] (writers); [`experiments`] (scene files, optimisation, benches).
//!
//! # Step a world
//!
//! A world is built from plain parts; bodies come and go through handles. [`prelude`] holds
//! what an embedding program needs, and `docs/rust-api.md` walks the path.
//!
//! ```
//! use diffluid::prelude::*;
//!
//! let mut sim = Simulation::builder([0.6, 0.4, 0.4], 0.05)
//!     .dt(0.01)
//!     .liquid(Solid::aabb(Vec3::ZERO, Vec3::new(0.6, 0.2, 0.4)))
//!     .build()?;
//! let cube = RigidBody::builder("cube", SharedShape::cuboid(0.05, 0.05, 0.05))
//!     .density(500.0)
//!     .pose(Pose::from_translation(Vec3::new(0.3, 0.2, 0.2)))
//!     .build()?;
//! let h = sim.add_body(cube)?;
//! sim.set_external_force(h, Vec3::new(2.0, 0.0, 0.0), Vec3::ZERO)?; // a push along x
//! for _ in 0..10 {
//!     sim.step()?;
//! }
//! let (force, _torque) = sim.fluid_force(h)?;
//! assert!(force.y > 0.0, "the water holds the half-submerged cube up");
//! assert!(sim[h].v.x > 0.0);
//! sim.advance(1.0 / 30.0)?; // a frame of a game loop, in CFL-limited steps
//! sim.remove_body(h)?;
//! assert!(matches!(sim.body(h), Err(Error::UnknownBody { .. })), "a removed body is gone");
//! # Ok::<(), diffluid::Error>(())
//! ```
//!
//! # Load a mesh
//!
//! A closed OBJ mesh becomes a body's shape ([`load_obj`](geometry::mesh::load_obj)); an
//! open one (a hull without a deck) loads as a shell with
//! [`load_obj_or_shell`](geometry::mesh::load_obj_or_shell). Either error is
//! [`Error::Mesh`], naming the file and what is wrong with it.
//!
//! ```
//! use diffluid::prelude::*;
//!
//! // A boat hull 0.5 m long, its deck at y = 0 in its own frame.
//! let path = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/meshes/hull.obj");
//! let hull = load_obj(path.as_ref(), 1.0)?;
//! let mut sim = Simulation::builder([0.8, 0.6, 0.6], 0.05)
//!     .liquid(Solid::aabb(Vec3::ZERO, Vec3::new(0.8, 0.25, 0.6)))
//!     .build()?;
//! let boat = RigidBody::builder("boat", hull)
//!     .density(500.0)
//!     .pose(Pose::from_translation(Vec3::new(0.4, 0.3, 0.3)))
//!     .build()?;
//! let boat = sim.add_body(boat)?;
//! sim.step()?;
//! assert!(sim.fluid_force(boat)?.0.y > 0.0, "the water pushes the hull up");
//! # Ok::<(), diffluid::Error>(())
//! ```
//!
//! # Take a gradient
//!
//! The gradient of a loss on a body's final position with respect to its initial state.
//!
//! ```
//! use diffluid::gradients::{value_and_gradient, BodyTargetLoss, GradientSettings};
//! use diffluid::math::Vec3;
//! use diffluid::Scene;
//!
//! let mut scene = Scene::builtin("gradcheck_box")?;
//! scene.time.steps = 4;
//! let sim = scene.build()?;
//! let boxed = sim.handles()[0];
//! let loss = BodyTargetLoss {
//!     position: Some((Vec3::new(0.35, 0.2, 0.45), 1.0)),
//!     ..BodyTargetLoss::on(&sim, boxed)?
//! };
//! let run = value_and_gradient(&sim, 4, &loss, &GradientSettings::default())?;
//! let g = run.gradient.body(&sim, boxed)?; // ∂L/∂v₀, ∂L/∂ω₀, ∂L/∂x₀, ∂L/∂θ₀
//! assert!(g.x.length() > 0.0 && run.loss > 0.0);
//! # Ok::<(), diffluid::Error>(())
//! ```
//!
//! # Embed with rapier
//!
//! A program whose bodies live in its own rapier world adds each as a
//! [`Motion::External`](geometry::body::Motion::External) body, and every step hands
//! diffluid the pose and velocity ([`Simulation::set_body_state`]) and gives rapier back the
//! pressure impulse Δt·[`Simulation::fluid_force`]; rapier keeps gravity, integration and
//! contact. `examples/rapier_coupling.rs` runs a box and a mesh so.
//!
//! ```
//! # #[cfg(feature = "contact")] {
//! use diffluid::prelude::*;
//! use rapier3d_f64::prelude::{ColliderBuilder, PhysicsWorld, RigidBodyBuilder};
//!
//! let dt = 0.01;
//! let mut world = PhysicsWorld::new();
//! world.integration_parameters.dt = dt;
//! let shape = SharedShape::ball(0.06);
//! let (h, _) = world.insert(
//!     RigidBodyBuilder::dynamic().translation(Vec3::new(0.3, 0.25, 0.2)),
//!     ColliderBuilder::new(shape.clone()).density(500.0),
//! );
//! let mut sim = diffluid::Simulation::builder([0.6, 0.4, 0.4], 0.05)
//!     .dt(dt)
//!     .liquid(Solid::aabb(Vec3::ZERO, Vec3::new(0.6, 0.2, 0.4)))
//!     .build()?;
//! let rb = &world.bodies[h];
//! let body = RigidBody::builder("ball", shape)
//!     .mass_properties(rb.mass_properties().local_mprops)
//!     .pose(*rb.position())
//!     .motion(Motion::External)
//!     .build()?;
//! let ball = sim.add_body(body)?;
//! for _ in 0..10 {
//!     let rb = &world.bodies[h];
//!     let state = BodyState { x: rb.center_of_mass(), q: rb.position().rotation,
//!         v: rb.linvel(), w: rb.angvel() };
//!     sim.set_body_state(ball, &state)?;
//!     sim.step()?;
//!     let (force, torque) = sim.fluid_force(ball)?;
//!     world.bodies[h].apply_impulse(dt * force, true);
//!     world.bodies[h].apply_torque_impulse(dt * torque, true);
//!     world.step();
//! }
//! assert!(world.bodies[h].linvel().y < 0.0, "the ball falls, slowed by the water");
//! # }
//! # Ok::<(), diffluid::Error>(())
//! ```
#![warn(missing_docs)]
// Loops over the three axes index several per-axis arrays at once; an index reads better.
#![allow(clippy::needless_range_loop)]

pub mod error;
pub mod experiments;
pub mod geometry;
pub mod gradients;
pub mod io;
pub mod math;
pub mod solvers;
pub mod stages;
pub mod world;

/// parry3d (the f64 build), whose shapes ([`math::SharedShape`]), poses and mass properties
/// are in diffluid's API: use it through this path to get the same version.
pub use parry3d_f64 as parry3d;

pub use error::{Error, GradientError, Result, Solve};
pub use experiments::scene::Scene;
pub use world::{BodyHandle, Simulation, StepReport};

/// What a program that embeds diffluid needs, in one import: `use diffluid::prelude::*;`.
///
/// The world and its handles ([`Simulation`], [`BodyHandle`], [`ContactSettings`]), bodies
/// and their state ([`RigidBody`], [`BodyState`], [`Motion`]), solids and the math types
/// ([`Solid`], [`SharedShape`], [`Pose`], [`Vec3`]), mesh loading ([`load_obj`],
/// [`load_obj_or_shell`]) and the error ([`Error`], [`Result`], whose second parameter
/// defaults to [`Error`], so that the standard `Result<T, E>` still reads as before).
///
/// [`Simulation`]: crate::Simulation
/// [`BodyHandle`]: crate::BodyHandle
/// [`ContactSettings`]: crate::world::ContactSettings
/// [`RigidBody`]: crate::geometry::body::RigidBody
/// [`BodyState`]: crate::geometry::body::BodyState
/// [`Motion`]: crate::geometry::body::Motion
/// [`Solid`]: crate::geometry::shape::Solid
/// [`SharedShape`]: crate::math::SharedShape
/// [`Pose`]: crate::math::Pose
/// [`Vec3`]: crate::math::Vec3
/// [`load_obj`]: crate::geometry::mesh::load_obj
/// [`load_obj_or_shell`]: crate::geometry::mesh::load_obj_or_shell
/// [`Error`]: crate::Error
/// [`Result`]: crate::Result
pub mod prelude {
    pub use crate::error::{Error, Result};
    pub use crate::geometry::body::{BodyState, Motion, RigidBody};
    pub use crate::geometry::mesh::{load_obj, load_obj_or_shell};
    pub use crate::geometry::shape::Solid;
    pub use crate::math::{Pose, SharedShape, Vec3};
    pub use crate::world::{BodyHandle, ContactSettings, Simulation, SimulationBuilder};
}
