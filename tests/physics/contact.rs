//! Rigid contact through rapier (`ContactWorld`, feature `contact`).
//!
//! The fluid step updates every body's velocity (gravity and pressure included); the contact
//! world then moves the bodies over one step with zero gravity, resolving body–wall and
//! body–body contact. These tests emulate the fluid step by adding `g·Δt` to `v` before each
//! contact step, and check: resting contact on the floor, exact free flight far from the
//! walls, no deep interpenetration of colliding bodies, and that fixed bodies stay put.
#![cfg(feature = "contact")]

use diffluid::geometry::body::{quat_step, RigidBody};
use diffluid::math::{Pose, Rotation, SharedShape, Vec3};
use diffluid::stages::contact::ContactWorld;
use diffluid::world::ContactSettings as Contact;
use parry3d_f64::query;

const G: Vec3 = Vec3::new(0.0, -9.81, 0.0);

fn settings(friction: f64, restitution: f64) -> Contact {
    Contact { enabled: true, friction, restitution }
}

fn ball(r: f64, at: Vec3) -> RigidBody {
    RigidBody::with_density("ball".into(), SharedShape::ball(r), Pose::from_translation(at), 800.0)
}

fn cube(h: f64, at: Vec3) -> RigidBody {
    RigidBody::with_density(
        "box".into(),
        SharedShape::cuboid(h, h, h),
        Pose::from_translation(at),
        600.0,
    )
}

/// Penetration depth of two bodies (0 when apart).
fn penetration(a: &RigidBody, b: &RigidBody) -> f64 {
    let c = query::contact(&a.pose(), &*a.shape, &b.pose(), &*b.shape, 0.0).unwrap();
    c.map_or(0.0, |c| (-c.dist).max(0.0))
}

/// (1) A ball thrown down at the floor with restitution 0 comes to rest on it: gravity is
/// added to v before each step (as the fluid step would), the floor's normal impulse cancels
/// it, and the ball's lowest point ends within 1% of its radius of y = 0. Run both with one
/// persistent world and with a fresh world per step (what `Simulation` does).
#[test]
fn ball_comes_to_rest_on_floor() {
    let r = 0.05;
    let domain = Vec3::splat(0.4);
    let dt = 0.005;
    for fresh in [false, true] {
        let mut bodies = vec![ball(r, Vec3::new(0.2, 0.2, 0.2))];
        bodies[0].v = Vec3::new(0.0, -0.5, 0.0);
        let mut world = ContactWorld::new(domain, &bodies, &settings(0.5, 0.0));
        let mut lowest_seen = f64::INFINITY;
        for _ in 0..400 {
            bodies[0].v += G * dt;
            if fresh {
                world = ContactWorld::new(domain, &bodies, &settings(0.5, 0.0));
            }
            world.step(&mut bodies, dt);
            lowest_seen = lowest_seen.min(bodies[0].x.y - r);
        }
        let b = &bodies[0];
        let gap = b.x.y - r;
        println!(
            "fresh={fresh}: rest gap {gap:.3e} m ({:.3}% of r), deepest {lowest_seen:.3e} m, \
             v {:?}",
            100.0 * gap / r,
            b.v
        );
        assert!(gap.abs() <= 0.01 * r, "fresh={fresh}: resting gap {gap}");
        assert!(b.v.length() < 0.1 * G.length() * dt, "fresh={fresh}: still moving {:?}", b.v);
        // It stays where it fell (no sideways drift).
        assert!((b.x.x - 0.2).abs() < 1e-9 && (b.x.z - 0.2).abs() < 1e-9, "{:?}", b.x);
    }
}

/// (2) Far from walls and other bodies, one contact step is free flight: x ← x + Δt·v
/// exactly (to rounding) and v, ω unchanged (no damping, no gyroscopic term, no speed cap).
/// The body has an off-centre COM and a full inertia tensor, so the COM bookkeeping of the
/// pose is exercised.
///
/// Rotation: rapier integrates q per solver substep as normalise((1, h·ω/2)⊗q) with
/// h = Δt/4 (4 substeps), our `quat_step` does normalise(q + Δt/2·[0, ω]⊗q) once. Both turn
/// about ω, by 8·atan(|ω|Δt/8) and 2·atan(|ω|Δt/2) respectively. At |ω| = 1 rad/s and
/// Δt = 0.005 the two orientations differ by 9.766e-9 rad (measured; ≈ (|ω|Δt)³/12·15/16,
/// the exact angle |ω|Δt is missed by 1.04e-8 rad by ours and 6.5e-10 rad by rapier's).
/// That is below O(Δt²) = 2.5e-5: third order per step, second order over a fixed time.
#[test]
fn free_flight_matches_own_integrator() {
    let pts = [
        Vec3::new(0.0, 0.0, 0.0),
        Vec3::new(0.12, 0.0, 0.0),
        Vec3::new(0.0, 0.07, 0.0),
        Vec3::new(0.0, 0.0, 0.05),
        Vec3::new(0.06, 0.05, 0.04),
    ];
    let shape = SharedShape::convex_hull(&pts).unwrap();
    let q0 = Rotation::from_axis_angle(Vec3::new(1.0, 2.0, 3.0).normalize(), 0.7);
    let pose = Pose::from_parts(Vec3::new(0.45, 0.5, 0.48), q0);
    let mut b = RigidBody::with_density("hull".into(), shape, pose, 700.0);
    assert!(b.local_com.length() > 0.01, "COM should be off the shape origin");
    b.v = Vec3::new(0.3, -0.2, 0.1);
    let w = Vec3::new(0.2, -0.5, 0.7);
    b.w = w / w.length(); // |ω| = 1 rad/s
    let dt = 0.005;

    let mut ours = b.clone();
    ours.integrate(dt);

    let mut bodies = vec![b.clone()];
    let mut world = ContactWorld::new(Vec3::ONE, &bodies, &settings(0.5, 0.0));
    world.step(&mut bodies, dt);
    let r = &bodies[0];

    let dx = (r.x - (b.x + dt * b.v)).abs().max_element();
    let dv = (r.v - b.v).abs().max_element();
    let dw = (r.w - b.w).abs().max_element();
    // Angle of the rotation taking our orientation to rapier's.
    let d = r.q * ours.q.inverse();
    let dangle = 2.0 * d.xyz().length().atan2(d.w.abs());
    let theta = b.w.length() * dt;
    let predicted = 8.0 * (theta / 8.0).atan() - 2.0 * (theta / 2.0).atan();
    println!(
        "free flight: |Δx| {dx:.2e}, |Δv| {dv:.2e}, |Δω| {dw:.2e}, rotation vs quat_step \
         {dangle:.4e} rad (predicted {predicted:.4e})"
    );
    assert!(dx < 1e-12, "x: {dx}");
    assert!(dv < 1e-12, "v: {dv}");
    assert!(dw < 1e-12, "ω: {dw}");
    assert!((dangle - predicted).abs() < 1e-11, "{dangle} vs {predicted}");
    // Same as our integrator for x (it is x + Δt·v too).
    assert!((r.x - ours.x).abs().max_element() < 1e-12);
    // The rotation turned about ω: the difference quaternion is along ω.
    assert!(d.xyz().normalize().cross(b.w).length() < 1e-6);
    assert_eq!(quat_step(b.q, b.w, dt), ours.q);
}

/// (3) Two boxes sliding toward each other (no gravity, restitution 0) meet in the middle;
/// contact keeps their overlap under 1% of their size at every step after they meet, they
/// never pass through each other, and momentum is conserved by the contact impulses.
#[test]
fn colliding_boxes_do_not_interpenetrate() {
    let h = 0.05;
    let size = 2.0 * h;
    let dt = 0.005;
    let mut bodies = vec![cube(h, Vec3::new(0.3, 0.5, 0.5)), cube(h, Vec3::new(0.7, 0.5, 0.5))];
    bodies[0].v = Vec3::new(1.0, 0.0, 0.0);
    bodies[1].v = Vec3::new(-1.0, 0.0, 0.0);
    let p0 = bodies[0].mass * bodies[0].v + bodies[1].mass * bodies[1].v;
    let mut world = ContactWorld::new(Vec3::ONE, &bodies, &settings(0.5, 0.0));
    let mut deepest: f64 = 0.0;
    let mut met = false;
    for _ in 0..100 {
        world.step(&mut bodies, dt);
        let gap = (bodies[1].x.x - bodies[0].x.x) - size;
        met |= gap < 1e-3;
        deepest = deepest.max(penetration(&bodies[0], &bodies[1]));
        assert!(bodies[0].x.x < bodies[1].x.x, "boxes passed through each other");
    }
    let p1 = bodies[0].mass * bodies[0].v + bodies[1].mass * bodies[1].v;
    println!(
        "boxes: deepest overlap {deepest:.3e} m ({:.3}% of size), final v {:?} {:?}, \
         |Δp| {:.2e}",
        100.0 * deepest / size,
        bodies[0].v,
        bodies[1].v,
        (p1 - p0).length()
    );
    assert!(met, "the boxes never met");
    assert!(deepest <= 0.01 * size, "overlap {deepest}");
    assert!((p1 - p0).length() < 1e-9 * bodies[0].mass, "momentum {p0} → {p1}");
    // Restitution 0: they end up (nearly) moving together; what is left is rapier's
    // penetration-recovery push (measured 0.0082 m/s apart, 0.4% of the closing speed).
    assert!(
        (bodies[0].v - bodies[1].v).length() < 0.01 * 2.0,
        "{:?} {:?}",
        bodies[0].v,
        bodies[1].v
    );
}

/// (4) A fixed (non-dynamic) body is an obstacle: a ball falling onto it under gravity is
/// stopped on top of it, and the fixed body itself is never moved nor written back.
#[test]
fn fixed_body_is_not_moved() {
    let dt = 0.005;
    let mut block = cube(0.1, Vec3::new(0.5, 0.2, 0.5));
    block.motion = diffluid::geometry::body::Motion::Fixed;
    let r = 0.05;
    let mut bodies = vec![block, ball(r, Vec3::new(0.5, 0.5, 0.5))];
    let before = bodies[0].clone();
    let mut world = ContactWorld::new(Vec3::ONE, &bodies, &settings(0.5, 0.0));
    for _ in 0..300 {
        bodies[1].v += G * dt;
        world.step(&mut bodies, dt);
    }
    let (a, b) = (&bodies[0], &bodies[1]);
    assert_eq!((a.x, a.q, a.v, a.w), (before.x, before.q, before.v, before.w));
    // The ball rests on the block's top face at y = 0.3.
    let gap = b.x.y - r - 0.3;
    println!("fixed block: ball rest gap {gap:.3e} m");
    assert!(gap.abs() <= 0.01 * r, "gap {gap}");
}

/// (5) No contact work when no contact is possible: a body whose swept, padded bounding box
/// keeps clear of the walls and of the other bodies flies freely, with the integrator used
/// without contact, and rapier is not called. Near a wall, moving fast toward one, or close
/// to another body, contact is possible.
#[test]
fn contact_is_skipped_only_when_no_contact_is_possible() {
    use diffluid::stages::contact::contact_possible;
    let domain = Vec3::ONE;
    let dt = 0.01;
    let mut b = cube(0.05, Vec3::new(0.5, 0.5, 0.5));
    assert!(!contact_possible(std::slice::from_ref(&b), domain, dt));
    // 1 mm from the floor: the pad (1% of the 0.17 m diagonal) reaches it; 2 mm does not.
    b.x.y = 0.051;
    assert!(contact_possible(std::slice::from_ref(&b), domain, dt));
    b.x.y = 0.052;
    assert!(!contact_possible(std::slice::from_ref(&b), domain, dt));
    // ... unless it moves 1 mm toward the floor within the step.
    b.v = Vec3::new(0.0, -0.1, 0.0);
    assert!(contact_possible(std::slice::from_ref(&b), domain, dt));
    assert!(contact_possible(std::slice::from_ref(&b), domain, dt));
    // 0.2 m from the floor, but falling at 25 m/s: within reach in one step.
    b.x.y = 0.25;
    b.v = Vec3::new(0.0, -25.0, 0.0);
    assert!(contact_possible(std::slice::from_ref(&b), domain, dt));
    b.v = Vec3::ZERO;
    assert!(!contact_possible(std::slice::from_ref(&b), domain, dt));
    // Two bodies 1 mm apart.
    let other = cube(0.05, Vec3::new(0.5, 0.351, 0.5));
    assert!(contact_possible(&[b.clone(), other.clone()], domain, dt));
    let far = cube(0.05, Vec3::new(0.2, 0.7, 0.2));
    assert!(!contact_possible(&[b, far], domain, dt));
}

/// (6) The same scene with contact on and off runs bit-identically while the body is far
/// from everything: the contact stage does nothing it need not do.
#[test]
fn contact_on_changes_nothing_away_from_walls() {
    let mut scene = diffluid::Scene::builtin("block_drop").unwrap();
    scene.solver.freeze_surface = true;
    scene.time.steps = 10;
    scene.optimize = None;
    let mut on = scene.clone();
    on.contact.enabled = true;
    let (mut a, mut b) = (scene.build().unwrap(), on.build().unwrap());
    for _ in 0..10 {
        a.step().unwrap();
        b.step().unwrap();
    }
    let (x, y) = (&a.bodies()[0], &b.bodies()[0]);
    assert_eq!((x.x, x.q, x.v, x.w), (y.x, y.q, y.v, y.w));
    assert_eq!(a.velocity_field(), b.velocity_field());
}

/// A dense cube (10× the liquid's density) launched at 1 m/s across a closed tank full of
/// water at CFL 4 (Δt = 0.2 s, 5 cm cells) stays within the energy the scene can supply. It
/// reaches the wall within a step, so whether rapier integrates it must be decided at the
/// velocity the projection leaves it, not the one it started the step with: decided before
/// the solve, the contact was missed and the body left the tank.
#[test]
fn a_fast_heavy_body_at_a_wall_stays_within_the_energy_bound() {
    let text = r#"
name = "fast"
[domain]
size = [0.6, 0.6, 0.6]
dx = 0.05
[time]
dt = 0.2
steps = 30
[fluid]
density = 1000.0
gravity = [0.0, -9.81, 0.0]
[[liquid]]
shape = { kind = "box", min = [0.0, 0.0, 0.0], max = [0.6, 0.6, 0.6] }
[[body]]
shape = { kind = "cuboid", half_extents = [0.1, 0.1, 0.1] }
density = 10000.0
position = [0.3, 0.25, 0.3]
velocity = [1.0, 0.0, 0.0]
[contact]
enabled = true
[solver]
density_correction = false
[output]
particles = false
"#;
    let mut sim = diffluid::Scene::from_toml(text, "<test>").unwrap().build().unwrap();
    let (mass, volume) = (10000.0 * 0.008, 0.008);
    let bound = 2.0 * (0.5 * mass + (mass - 1000.0 * volume) * 9.81 * 0.6);
    for _ in 0..30 {
        let r = sim.step().unwrap();
        let b = &sim.bodies()[0];
        let e = r.kinetic_energy + 0.5 * b.mass * b.v.length_squared();
        assert!(e <= bound, "energy {e} over the bound {bound} at step {}", r.step);
    }
}

/// (8) A kinematic paddle moving at 0.5 m/s pushes a ball resting on the floor (the water
/// far off in a corner): rapier sees the paddle's velocity, so the ball leaves at the
/// paddle's speed and the two do not overlap. Held as a fixed body at each step's pose, the
/// paddle stepped 5 mm into the ball every step and rapier pushed the overlap out: the ball
/// crept along 4 cm inside the paddle with its velocity reading 0.
#[test]
fn a_kinematic_paddle_pushes_a_ball_at_its_speed() {
    let text = crate::common::paddle_and_ball(40, 0.35, "velocity = [0.5, 0.0, 0.0]");
    let scene = diffluid::Scene::from_toml(&text, "<push>").unwrap();
    let mut sim = scene.build().unwrap();
    let mut deepest: f64 = 0.0;
    for _ in 0..scene.time.steps {
        sim.step().unwrap();
        let b = sim.bodies();
        deepest = deepest.max(penetration(&b[0], &b[1]));
    }
    let ball = &sim.bodies()[1];
    eprintln!("ball vx {:.5}, x {:.4}; deepest overlap {deepest:.2e} m", ball.v.x, ball.x.x);
    assert!((ball.v.x - 0.5).abs() < 0.01, "the ball moves at {} m/s", ball.v.x);
    assert!(deepest < 1e-3, "the paddle and the ball overlap by {deepest} m");
}
