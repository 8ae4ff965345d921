//! The path a Rust program walks when it embeds diffluid: bodies added by handle, moved by
//! the caller's own engine, checked when they come in.
//!
//! - A [`Motion::External`] body is where the caller's engine put it. rapier resolves a body
//!   resting on the floor with a few micrometres of overlap, which
//!   [`Simulation::set_body_state`] accepts (up to a quarter cell into a wall); the step after
//!   it must accept it too, contact on or off, or a game loop stops at the floor.
//! - `add_body` refuses what would give a silently wrong answer: a far-from-unit quaternion
//!   (its rotation is not a rotation: the forces come out wrong), a non-finite pose or
//!   velocity (named as such), a handle from another simulation, bodies that overlap with
//!   contact off (nothing would keep them apart), and it warns at once about a body thinner
//!   than its face fractions are sampled at.
//! - A game loop that reads none of the step report's measures of the liquid turns them off
//!   ([`Simulation::set_report_measures`]); its steps are the same bits as with them on.

use crate::common::TempDir;
use diffluid::math::Rotation;
use diffluid::prelude::*;
use diffluid::world::SolverSettings;

fn pool() -> Simulation {
    Simulation::builder([0.6, 0.4, 0.4], 0.05)
        .dt(0.01)
        .liquid(Solid::aabb(Vec3::ZERO, Vec3::new(0.6, 0.2, 0.4)))
        .build()
        .unwrap()
}

fn cube(name: &str, half: f64, at: Vec3) -> RigidBody {
    RigidBody::builder(name, SharedShape::cuboid(half, half, half))
        .density(1500.0)
        .pose(Pose::from_translation(at))
        .build()
        .unwrap()
}

#[test]
fn external_body_a_few_micrometres_into_the_floor_steps() {
    let mut sim = pool();
    let h = sim
        .add_body(cube("crate", 0.05, Vec3::new(0.3, 0.1, 0.2)).with_motion(Motion::External))
        .unwrap();
    // Resting on the floor as rapier leaves it: 3 µm into it.
    let state = BodyState { x: Vec3::new(0.3, 0.05 - 3e-6, 0.2), ..sim[h].state() };
    sim.set_body_state(h, &state).unwrap();
    for _ in 0..3 {
        sim.step().expect("an external body resting on the floor is the caller's to place");
    }
    assert_eq!(sim[h].x, state.x, "diffluid leaves an external body's pose alone");
}

#[test]
fn a_far_from_unit_quaternion_is_refused() {
    let mut sim = pool();
    let mut b = cube("tilted", 0.05, Vec3::new(0.3, 0.25, 0.2));
    b.q = Rotation::from_xyzw(0.0, 0.0, 0.3, 0.5); // length 0.58
    let err = sim.add_body(b.clone()).unwrap_err().to_string();
    assert!(err.contains("unit quaternion") && err.contains("tilted"), "{err}");
    // One within round-off of unit length is taken as it is.
    b.q = Rotation::from_xyzw(0.0, 0.0, 0.0, 1.0 + 1e-12);
    sim.add_body(b).unwrap();
}

#[test]
fn non_finite_pose_and_velocity_are_named() {
    let mut sim = pool();
    let mut b = cube("nan", 0.05, Vec3::new(0.3, 0.25, 0.2));
    b.q = Rotation::from_xyzw(f64::NAN, 0.0, 0.0, 1.0);
    let err = sim.add_body(b).unwrap_err().to_string();
    assert!(err.contains("orientation must be finite"), "{err}");
    assert!(!err.contains("spans"), "{err}");
    let b = cube("fast", 0.05, Vec3::new(0.3, 0.25, 0.2))
        .with_velocity(Vec3::new(f64::INFINITY, 0.0, 0.0), Vec3::ZERO);
    let err = sim.add_body(b).unwrap_err().to_string();
    assert!(err.contains("velocity") && err.contains("finite"), "{err}");
}

#[test]
fn a_handle_from_another_simulation_is_refused() {
    let mut a = pool();
    let mut b = pool();
    let ha = a.add_body(cube("a", 0.05, Vec3::new(0.2, 0.25, 0.2))).unwrap();
    let hb = b.add_body(cube("b", 0.05, Vec3::new(0.4, 0.25, 0.2))).unwrap();
    assert_eq!(ha.id(), hb.id(), "the same number in two simulations");
    assert!(matches!(a.body(hb), Err(Error::UnknownBody { .. })));
    assert!(a.index_of(hb).is_none());
    assert!(matches!(a.fluid_force(hb), Err(Error::UnknownBody { .. })));
    assert!(a.remove_body(hb).is_err());
    // A clone is the same simulation: its handles still name its bodies.
    let c = a.clone();
    assert_eq!(c[ha].name, "a");
}

#[test]
fn overlapping_bodies_with_contact_off_are_refused() {
    let mut sim = pool();
    sim.add_body(cube("first", 0.05, Vec3::new(0.3, 0.25, 0.2))).unwrap();
    let err = sim.add_body(cube("second", 0.05, Vec3::new(0.33, 0.25, 0.2))).unwrap_err();
    let err = err.to_string();
    assert!(err.contains("overlaps body first") && err.contains("contact"), "{err}");
    // Apart, it comes in; and a builder refuses the overlap the same way.
    sim.add_body(cube("third", 0.05, Vec3::new(0.45, 0.25, 0.2))).unwrap();
    let built = Simulation::builder([0.6, 0.4, 0.4], 0.05)
        .body(cube("one", 0.05, Vec3::new(0.3, 0.25, 0.2)))
        .body(cube("two", 0.05, Vec3::new(0.33, 0.25, 0.2)))
        .build();
    let err = built.unwrap_err().to_string();
    assert!(err.contains("body[1]") && err.contains("overlaps body one"), "{err}");
}

#[cfg(feature = "contact")]
#[test]
fn overlapping_bodies_with_contact_on_are_taken() {
    let mut sim = Simulation::builder([0.6, 0.4, 0.4], 0.05)
        .contact(ContactSettings { enabled: true, ..ContactSettings::default() })
        .build()
        .unwrap();
    sim.add_body(cube("first", 0.05, Vec3::new(0.3, 0.25, 0.2))).unwrap();
    sim.add_body(cube("second", 0.05, Vec3::new(0.33, 0.25, 0.2))).unwrap();
}

#[test]
fn a_mesh_scaled_past_f64_is_refused_at_load() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/meshes/cube.obj");
    let err = load_obj(path.as_ref(), 1e300).unwrap_err();
    assert!(matches!(err, Error::Mesh { .. }), "{err}");
    let err = err.to_string();
    assert!(err.contains("cube.obj") && err.contains("not finite"), "{err}");
    assert!(load_obj(path.as_ref(), 1.0).is_ok());
}

#[test]
fn an_open_mesh_error_names_the_ways_out() {
    let dir = TempDir::new("embedding");
    let path = dir.join("open.obj");
    // A square sheet: two triangles, four boundary edges.
    std::fs::write(&path, "v 0 0 0\nv 1 0 0\nv 1 0 1\nv 0 0 1\nf 1 3 2\nf 1 4 3\n").unwrap();
    let err = load_obj(&path, 0.1).unwrap_err().to_string();
    for way in ["shell_thickness", "load_obj_or_shell", "close the mesh"] {
        assert!(err.contains(way), "{way} missing from: {err}");
    }
    assert!(load_obj_or_shell(&path, 0.1, 0.002).is_ok());
}

#[test]
fn a_sub_cell_body_is_warned_about_when_added() {
    let mut sim = pool();
    assert!(sim.warnings().is_empty());
    // A plate 1 mm thick in cells of 5 cm: thinner than the finest sampling (dx/16).
    let b = RigidBody::builder("plate", SharedShape::cuboid(0.1, 0.0005, 0.1))
        .density(500.0)
        .pose(Pose::from_translation(Vec3::new(0.3, 0.3, 0.2)))
        .build()
        .unwrap();
    sim.add_body(b).unwrap();
    assert!(
        sim.warnings().iter().any(|w| w.contains("plate") && w.contains("thinner than")),
        "{:?}",
        sim.warnings()
    );
    let before = sim.warnings().len();
    sim.step().unwrap();
    assert_eq!(sim.warnings().len(), before, "the step repeats no warning about the plate");
}

#[test]
fn the_body_builder_checks_density_and_mass() {
    let ball = || RigidBody::builder("ball", SharedShape::ball(0.1));
    let v = 4.0 / 3.0 * std::f64::consts::PI * 1e-3;
    assert!((ball().build().unwrap().mass - 1000.0 * v).abs() < 1e-9, "water by default");
    assert!((ball().mass(2.0).build().unwrap().mass - 2.0).abs() < 1e-12);
    for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        let err = ball().density(bad).build().unwrap_err().to_string();
        assert!(err.contains("ball") && err.contains("density"), "{err}");
        assert!(ball().mass(bad).build().is_err());
    }
    let b = ball().motion(Motion::Kinematic).velocity(Vec3::X, Vec3::ZERO).build().unwrap();
    assert_eq!((b.motion, b.v), (Motion::Kinematic, Vec3::X));
}

#[test]
fn setters_check_what_they_are_given() {
    let mut sim = pool();
    let h = sim.add_body(cube("box", 0.05, Vec3::new(0.3, 0.25, 0.2))).unwrap();
    assert!(sim.set_mass(h, -1.0).is_err());
    sim.set_mass(h, 2.0).unwrap();
    assert_eq!(sim[h].mass, 2.0);
    let mut u = sim.velocity_field().clone();
    u.c[1][3] = f64::NAN;
    let err = sim.set_velocity_field(u).unwrap_err().to_string();
    assert!(err.contains("not finite"), "{err}");
    let small = diffluid::geometry::grid::Mac::zeros(&diffluid::geometry::grid::Grid {
        n: [2, 2, 2],
        dx: 0.05,
    });
    assert!(sim.set_velocity_field(small).unwrap_err().to_string().contains("faces"));
    let mut p = sim.particles().to_vec();
    p.push(Vec3::new(0.3, -1.0, 0.2));
    assert!(sim.set_particles(p).unwrap_err().to_string().contains("inside the tank"));
}

/// A body denser than water sinks to the floor; with contact off, the loop stops there with
/// a message a Rust caller can act on: the builder method, as well as the scene section.
#[test]
fn body_left_tank_names_the_builder_method() {
    let mut sim = Simulation::builder([0.6, 0.4, 0.4], 0.05)
        .dt(0.01)
        .contact(ContactSettings { enabled: false, ..ContactSettings::default() })
        .build()
        .unwrap();
    let h = sim.add_body(cube("stone", 0.05, Vec3::new(0.3, 0.07, 0.2))).unwrap();
    sim.set_body_state(h, &BodyState { v: Vec3::new(0.0, -3.0, 0.0), ..sim[h].state() }).unwrap();
    let err = sim.step().unwrap_err();
    assert!(matches!(err, Error::BodyLeftTank { .. }), "{err}");
    let err = err.to_string();
    assert!(err.contains("SimulationBuilder::contact") && err.contains("[contact]"), "{err}");
}

#[test]
fn a_loss_and_a_gradient_name_a_body_by_its_handle() {
    use diffluid::gradients::BodyTargetLoss;
    let mut sim = pool();
    let a = sim.add_body(cube("a", 0.05, Vec3::new(0.2, 0.25, 0.2))).unwrap();
    let b = sim.add_body(cube("b", 0.05, Vec3::new(0.4, 0.25, 0.2))).unwrap();
    sim.remove_body(a).unwrap();
    let loss = BodyTargetLoss::on(&sim, b).unwrap();
    assert_eq!(loss.body, 0, "b is now the first body");
    assert!(matches!(BodyTargetLoss::on(&sim, a), Err(Error::UnknownBody { .. })));
    assert!(matches!(BodyTargetLoss::on(&pool(), b), Err(Error::UnknownBody { .. })));
}

#[test]
fn particles_of_a_narrow_band_cannot_be_replaced() {
    let solver = diffluid::world::SolverSettings { narrow_band: 2.into(), ..Default::default() };
    let mut sim = Simulation::builder([0.6, 0.4, 0.4], 0.05)
        .solver(solver)
        .liquid(Solid::aabb(Vec3::ZERO, Vec3::new(0.6, 0.3, 0.4)))
        .build()
        .unwrap();
    let p = sim.particles().to_vec();
    let err = sim.set_particles(p).unwrap_err().to_string();
    assert!(err.contains("solver.narrow_band"), "{err}");
}

#[test]
fn steps_without_the_report_measures_are_the_same_steps() {
    let run = |measures: bool| {
        let mut sim = pool();
        sim.add_body(cube("crate", 0.06, Vec3::new(0.3, 0.2, 0.2))).unwrap();
        sim.set_report_measures(measures);
        assert_eq!(sim.report_measures(), measures);
        let reports: Vec<_> = (0..3).flat_map(|_| sim.advance(1.0 / 60.0).unwrap()).collect();
        (sim, reports)
    };
    let (on, with) = run(true);
    let (off, without) = run(false);
    assert_eq!(on.particles(), off.particles());
    assert_eq!(on.velocity_field(), off.velocity_field());
    assert_eq!(on.bodies()[0].state(), off.bodies()[0].state());
    for (a, b) in with.iter().zip(&without) {
        assert_eq!(a.cg_iterations, b.cg_iterations);
        assert!(a.liquid_volume > 0.0 && a.energy.total() != 0.0 && a.max_speed.is_finite());
        assert!(b.liquid_volume.is_nan() && b.max_speed.is_nan() && b.max_divergence.is_nan());
        assert_eq!(b.energy.total(), 0.0);
    }
}

/// Bodies added and removed by handle keep their own ghosts (with
/// `solver.surface_softness`, the sites each displaced when placed, which the soft φ_L counts
/// where the body is): a fixed cube held in the air above still water (it displaced none)
/// and a cube of density 500 at its floating height leave the water still, and so does the
/// second once the first is removed. A removal that left the ghosts out of step with the
/// bodies would hand the floating cube the first one's (none), and the water beside it would
/// move (9.4e-4 J in the 0.2 s after the removal, with the removed body's ghosts left in
/// place). Measured 4e-18 J.
#[test]
fn added_and_removed_bodies_keep_their_own_ghosts() {
    let solver = SolverSettings { surface_softness: 0.35, ..SolverSettings::default() };
    let mut sim = Simulation::builder([0.6, 0.4, 0.4], 0.05)
        .dt(0.01)
        .solver(solver)
        .liquid(Solid::aabb(Vec3::ZERO, Vec3::new(0.6, 0.2, 0.4)))
        .build()
        .unwrap();
    let cube = |name: &str, at: Vec3| {
        RigidBody::builder(name, SharedShape::cuboid(0.05, 0.05, 0.05))
            .density(500.0)
            .pose(Pose::from_translation(at))
            .build()
            .unwrap()
    };
    let held = cube("held", Vec3::new(0.15, 0.33, 0.2)).with_motion(Motion::Fixed);
    let first = sim.add_body(held).unwrap();
    let floating = sim.add_body(cube("floating", Vec3::new(0.45, 0.2, 0.2))).unwrap();
    let mut energy = 0.0f64;
    for _ in 0..10 {
        energy = energy.max(sim.step().unwrap().kinetic_energy);
    }
    sim.remove_body(first).unwrap();
    for _ in 0..20 {
        energy = energy.max(sim.step().unwrap().kinetic_energy);
    }
    eprintln!("liquid kinetic energy at most {energy:e} J, the cube at {}", sim[floating].x.y);
    assert!(energy < 1e-9, "the liquid gained {energy:e} J");
    assert!((sim[floating].x.y - 0.2).abs() < 1e-6, "the cube moved to {}", sim[floating].x.y);
}
