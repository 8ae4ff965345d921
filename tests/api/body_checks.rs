//! Rigid bodies from any shape, heavy bodies on the floor, and bad bodies.
//!
//! - Mesh against primitive: an OBJ cube and a parry cuboid of the same size are the same
//!   solid, so their signed distances, mass properties and hence whole coupled trajectories
//!   must agree (to 1% of the distance travelled; in practice to round-off).
//! - Heavy body: a body three times as dense as water sinks and, with contact on, comes to
//!   rest on the floor: its lowest point just above y = 0 and its speed near zero.
//! - Resting contact leaves still water still: a heavy cube placed on the floor of a tank of
//!   still water must not stir it. Contact resolved only after the projection did (the
//!   liquid was made divergence-free around a sinking body that contact then stopped),
//!   pumping 0.38 m/s of flow; with the contact impulse held in the solve it stays under
//!   2 cm/s (measured 0.96 cm/s).
//! - Bad input: every malformed body is rejected with a message naming it.

use crate::common::{asset, tank_toml, TempDir};
use diffluid::math::Vec3;
use diffluid::Scene;

fn tank(body: &str, steps: usize, contact: bool) -> String {
    tank_toml("bodies", [0.8, 0.8, 0.8], 0.05, 0.4, steps)
        + &format!(
            r#"{body}
[contact]
enabled = {contact}
[output]
particles = false
"#
        )
}

fn trajectory(shape: &str) -> Vec<(Vec3, diffluid::math::Rotation)> {
    let body = format!(
        r#"[[body]]
shape = {shape}
density = 1500.0
position = [0.41, 0.47, 0.38]
axis_angle = {{ axis = [0.3, 1.0, 0.2], degrees = 25 }}
velocity = [0.3, -0.5, 0.1]
angular_velocity = [0.4, -0.2, 0.6]"#
    );
    let scene = Scene::from_toml(&tank(&body, 30, false), "<test>").unwrap();
    let mut sim = scene.build().unwrap();
    (0..30)
        .map(|_| {
            sim.step().unwrap();
            (sim.bodies()[0].x, sim.bodies()[0].q)
        })
        .collect()
}

#[test]
fn obj_cube_and_cuboid_give_the_same_trajectory() {
    // A relative mesh path starts from the current folder (the crate root under `cargo
    // test`), not from a folder fixed when diffluid was compiled.
    let mesh = trajectory(r#"{ kind = "mesh", obj = "assets/meshes/cube.obj" }"#);
    let cuboid = trajectory(r#"{ kind = "cuboid", half_extents = [0.1, 0.1, 0.1] }"#);
    let travelled = (mesh.last().unwrap().0 - mesh[0].0).length().max(1e-3);
    let mut worst: f64 = 0.0;
    for ((xm, qm), (xc, qc)) in mesh.iter().zip(&cuboid) {
        worst = worst.max((*xm - *xc).length() / travelled);
        worst = worst.max(1.0 - qm.dot(*qc).abs());
    }
    eprintln!(
        "mesh vs cuboid: worst relative trajectory difference {worst:.2e} over {travelled:.3} m"
    );
    // The issue asks for 1%. The two shapes have the same mass properties and the same
    // distance outside; inside, the cuboid's distance is smoothed across the planes that
    // bisect its edges and the mesh's is not (`geometry/interior.rs`), which is all that
    // parts them: measured 1.06e-4 (4e-16 before the smoothing). A mesh loaded a hair off
    // in scale, place or turn would part them by more than 1e-3 (a 1 mm offset: 3e-3).
    assert!(worst < 1e-3, "trajectories differ by {worst}");
}

#[test]
fn heavy_body_sinks_and_rests_on_the_floor() {
    let body = r#"[[body]]
shape = { kind = "cuboid", half_extents = [0.1, 0.1, 0.1] }
density = 3000.0
position = [0.41, 0.25, 0.38]"#;
    let scene = Scene::from_toml(&tank(body, 300, true), "<test>").unwrap();
    let mut sim = scene.build().unwrap();
    let mut speeds = Vec::new();
    for _ in 0..300 {
        sim.step().unwrap();
        speeds.push(sim.bodies()[0].v.length());
    }
    let (lo, _) = sim.bodies()[0].bounds();
    let tail = speeds[280..].iter().cloned().fold(0.0, f64::max);
    eprintln!(
        "heavy body: lowest point {:.4} m, max speed over the last 20 steps {tail:.2e} m/s",
        lo.y
    );
    assert!(lo.y > -0.002 && lo.y < 0.004, "lowest point {} m is not on the floor", lo.y);
    assert!(tail < 0.01, "still moving at {tail} m/s");
}

fn rejected(body: &str, needles: &[&str]) {
    let text = tank(body, 5, false);
    let err = match Scene::from_toml(&text, "<test>") {
        Err(e) => e.to_string(),
        Ok(s) => match s.build() {
            Err(e) => e.to_string(),
            Ok(_) => panic!("accepted: {body}"),
        },
    };
    for n in needles {
        assert!(err.contains(n), "message {err:?} lacks {n:?}");
    }
}

#[test]
fn bad_bodies_are_rejected_with_a_clear_message() {
    let ball =
        |extra: &str| format!("[[body]]\nshape = {{ kind = \"ball\", radius = 0.1 }}\n{extra}");
    rejected(
        &ball("density = 500.0\nposition = [0.75, 0.5, 0.4]"),
        &["body[0]", "inside the tank"],
    );
    rejected(&ball("density = 500.0\nposition = [0.1, 0.5, 0.4]"), &["body[0]", "touching a wall"]);
    rejected(&ball("density = 0.0\nposition = [0.4, 0.5, 0.4]"), &["body[0].density", "positive"]);
    rejected(&ball("density = -5.0\nposition = [0.4, 0.5, 0.4]"), &["body[0].density", "positive"]);
    rejected(&ball("mass = 0.0\nposition = [0.4, 0.5, 0.4]"), &["body[0].mass", "positive"]);
    rejected(
        &ball("density = 1.0\nmass = 1.0\nposition = [0.4, 0.5, 0.4]"),
        &["exactly one of density and mass"],
    );
    rejected(&ball("position = [0.4, 0.5, 0.4]"), &["exactly one of density and mass"]);
    rejected(
        &ball("density = 500.0\nposition = [0.4, 0.5, 0.4]\nvelocity = [nan, 0.0, 0.0]"),
        &["body[0].velocity", "finite"],
    );
    rejected(
        "[[body]]\nshape = { kind = \"ball\", radius = 0.0 }\ndensity = 500.0\nposition = [0.4, 0.5, 0.4]",
        &["body[0]", "radius"],
    );
    rejected(
        "[[body]]\nshape = { kind = \"convex_hull\", points = [[0,0,0],[1,0,0],[0,1,0],[1,1,0]] }\ndensity = 500.0\nposition = [0.4, 0.5, 0.4]",
        &["body[0]", "degenerate"],
    );
    rejected(
        "[[body]]\nshape = { kind = \"mesh\", obj = \"no/such/file.obj\" }\ndensity = 500.0\nposition = [0.4, 0.5, 0.4]",
        &["body[0]", "cannot read mesh", "no/such/file.obj"],
    );
    // An open mesh: the cube without its last triangle.
    let cube = std::fs::read_to_string(asset("meshes/cube.obj")).unwrap();
    let mut lines: Vec<&str> = cube.lines().collect();
    let last_face = lines.iter().rposition(|l| l.starts_with("f ")).unwrap();
    lines.remove(last_face);
    let dir = TempDir::new("open-mesh");
    let path = dir.join("open.obj");
    std::fs::write(&path, lines.join("\n")).unwrap();
    rejected(
        &format!(
            "[[body]]\nshape = {{ kind = \"mesh\", obj = \"{}\" }}\ndensity = 500.0\nposition = [0.4, 0.5, 0.4]",
            path.display()
        ),
        &["body[0]", "not closed", "convex_hull"],
    );
    // With repair = "convex_hull" the same mesh is used as its hull (here the whole cube:
    // 0.2³ m³ at 500 kg/m³ is 4 kg), and the simulation warns that it was.
    let body = format!(
        "[[body]]\nshape = {{ kind = \"mesh\", obj = \"{}\", repair = \"convex_hull\" }}\ndensity = 500.0\nposition = [0.4, 0.5, 0.4]",
        path.display()
    );
    let sim = Scene::from_toml(&tank(&body, 1, false), "<test>").unwrap().build().unwrap();
    assert!((sim.bodies()[0].mass - 4.0).abs() < 1e-9, "mass {}", sim.bodies()[0].mass);
    assert!(
        sim.warnings().iter().any(|w| w.contains("not closed") && w.contains("convex hull")),
        "{:?}",
        sim.warnings()
    );
}

#[test]
fn resting_contact_leaves_still_water_still() {
    let body = r#"[[body]]
shape = { kind = "cuboid", half_extents = [0.1, 0.1, 0.1] }
density = 3000.0
position = [0.41, 0.1001, 0.38]"#;
    let scene = Scene::from_toml(&tank(body, 200, true), "<test>").unwrap();
    let mut sim = scene.build().unwrap();
    let mut liquid: f64 = 0.0;
    let mut body_speed: f64 = 0.0;
    let mut solves = 0;
    for _ in 0..200 {
        let r = sim.step().unwrap();
        liquid = liquid.max(r.max_speed);
        body_speed = body_speed.max(sim.bodies()[0].v.length());
        solves += r.contact_iterations;
    }
    eprintln!(
        "cube resting on the floor: liquid max speed {liquid:.2e} m/s, body {body_speed:.2e} \
         m/s, {solves} extra solves in 200 steps"
    );
    assert!(liquid < 0.02, "the resting cube stirred the liquid to {liquid} m/s");
    assert!(body_speed < 0.01, "the resting cube moved at {body_speed} m/s");
}

/// A body the grid cannot represent says so instead of silently losing its coupling. A plate
/// a fifth of a cell thick is sampled finely enough to keep its volume (its first step's
/// face fractions hold it) and seals the liquid as it moves: no warning at all (before moving
/// thin bodies were sealed, one said that liquid passes through it). A plate a fiftieth of a cell thick is
/// thinner than the finest sampling: the warning says so, and its first step reports that
/// its face fractions miss most of its volume (the volume correction's λ clamped). A plate
/// two cells thick gets neither.
#[test]
fn bodies_too_thin_for_the_grid_are_reported() {
    let plate = |half: f64| {
        let body = format!(
            "[[body]]\nname = \"plate\"\nshape = {{ kind = \"cuboid\", half_extents = [0.2, {half}, 0.2] }}\ndensity = 500.0\nposition = [0.41, 0.31, 0.38]"
        );
        let mut sim = Scene::from_toml(&tank(&body, 1, false), "<test>").unwrap().build().unwrap();
        let built = sim.warnings().to_vec();
        let r = sim.step().unwrap();
        (built, r.warnings, r.bodies[0].volume_error)
    };
    let (built, step, err) = plate(0.005);
    assert!(built.is_empty() && step.is_empty(), "{built:?} {step:?}");
    assert!(err < 1e-12, "volume error {err}");
    let (built, step, err) = plate(0.0005);
    assert!(built.iter().any(|w| w.contains("plate") && w.contains("1/16 cell")), "{built:?}");
    assert!(step.iter().any(|w| w.contains("miss")), "{step:?}");
    assert!(err > 0.5, "volume error {err}");
    let (built, step, err) = plate(0.05);
    assert!(built.is_empty() && step.is_empty(), "{built:?} {step:?}");
    assert!(err < 1e-9, "volume error {err}");
}

/// A body too thin for its face fractions is warned about once, not every step its missing
/// volume changes (a resting box warned "too small or thin" 24 times in 300 steps).
#[test]
fn a_thin_body_is_warned_about_once() {
    let body = "[[body]]\nname = \"plate\"\nshape = { kind = \"cuboid\", half_extents = [0.2, 0.0005, 0.2] }\ndensity = 500.0\nposition = [0.41, 0.31, 0.38]\nangular_velocity = [0.0, 0.0, 0.5]";
    let mut sim = Scene::from_toml(&tank(body, 20, false), "<test>").unwrap().build().unwrap();
    let mut warned = Vec::new();
    let mut errors = Vec::new();
    for _ in 0..20 {
        let r = sim.step().unwrap();
        warned.extend(r.warnings.into_iter().filter(|w| w.contains("miss")));
        errors.push(r.bodies[0].volume_error);
    }
    errors.dedup();
    assert!(errors.len() > 5, "the missing volume should change as the plate turns: {errors:?}");
    assert_eq!(warned.len(), 1, "{warned:#?}");
    assert_eq!(sim.warnings().iter().filter(|w| w.contains("miss")).count(), 1);
}

/// A body touching the lid is refused as one touching the floor is: the tank's top is
/// n·dx, which for 6 cells of 0.1 m is 0.6000000000000001, so a cube whose top is at 0.6 was
/// inside by round-off while one whose bottom is at 0 touched the floor.
#[test]
fn touching_the_lid_is_touching_a_wall_as_the_floor_is() {
    use diffluid::geometry::body::RigidBody;
    use diffluid::math::{Pose, SharedShape};
    let cube = |y: f64| {
        let pose = Pose::from_translation(Vec3::new(0.3, y, 0.3));
        RigidBody::with_density("cube".into(), SharedShape::cuboid(0.1, 0.1, 0.1), pose, 500.0)
    };
    for (y, wall) in [(0.1, "floor"), (0.5, "lid"), (0.1 + 1e-12, "floor"), (0.5 - 1e-12, "lid")] {
        let built = diffluid::Simulation::builder([0.6, 0.6, 0.6], 0.1).body(cube(y)).build();
        let err = built.err().map(|e| e.to_string()).unwrap_or_default();
        assert!(err.contains("without touching a wall"), "the {wall} (y = {y}): {err:?}");
    }
    for y in [0.1 + 1e-6, 0.5 - 1e-6] {
        assert!(diffluid::Simulation::builder([0.6, 0.6, 0.6], 0.1).body(cube(y)).build().is_ok());
    }
}
