//! Plates thinner than a cell still couple to the liquid.
//!
//! (1) Hydrostatics: a neutrally buoyant plate a quarter (and an eighth) of a cell thick,
//! submerged and tilted off the grid's planes, feels ρ·g·V up and no torque about its centre
//! in the first solve, as closely as a thick plate does there: its face fractions, sampled
//! finely enough for its thickness, hold its whole volume about the right centroid. Sampled
//! every dx/2 it fell between the samples and lost 75% (95%) of its buoyancy.
//!
//! (2) Leakage: a static quarter-cell plate across the tank, holding 0.5 m of water against
//! 0.1 m, lets no liquid through in 0.3 s, whether it sits on a grid plane of faces, off it,
//! through the cell centres, or tilted. By volume fractions alone all of the flow went
//! through: three quarters of each crossed face stayed open.

use diffluid::experiments::scene::Scene;
use diffluid::math::Vec3;

const DX: f64 = 0.05;

/// Relative force error |F_y − ρ·g·V| / ρ·g·V and torque |τ| / (ρ·g·V·0.2) of the first solve
/// on a submerged 0.4 × 0.3 m plate `cells` thick, turned `degrees` about `axis`.
fn hydrostatic_errors(cells: f64, axis: [f64; 3], degrees: f64) -> (f64, f64) {
    let t = cells * DX;
    let text = format!(
        r#"
name = "thin"
[domain]
size = [1.0, 0.7, 0.6]
dx = {DX}
[time]
dt = 0.005
steps = 1
[fluid]
density = 1000.0
gravity = [0.0, -9.81, 0.0]
[[liquid]]
shape = {{ kind = "box", min = [0.0, 0.0, 0.0], max = [1.0, 0.6, 0.6] }}
[[body]]
name = "plate"
shape = {{ kind = "cuboid", half_extents = [0.2, {}, 0.15] }}
density = 1000.0
position = [0.513, 0.307, 0.291]
axis_angle = {{ axis = {axis:?}, degrees = {degrees} }}
[solver]
density_correction = false
tolerance = 1e-10
[output]
particles = false
"#,
        t / 2.0
    );
    let mut sim = Scene::from_toml(&text, "<test>").unwrap().build().unwrap();
    let r = sim.step().unwrap();
    let buoyancy = 1000.0 * 9.81 * 0.4 * 0.3 * t;
    let torque = Vec3::from_array(r.bodies[0].torque).length();
    ((r.bodies[0].force[1] - buoyancy).abs() / buoyancy, torque / (buoyancy * 0.2))
}

#[test]
fn sub_cell_plates_keep_their_hydrostatic_force_and_torque() {
    let mut worst = (0.0f64, 0.0f64);
    for cells in [0.25, 0.125] {
        for (axis, degrees) in [([0.0, 0.0, 1.0], 30.0), ([0.3, 1.0, 0.2], 17.0)] {
            let (f, t) = hydrostatic_errors(cells, axis, degrees);
            eprintln!("{cells} cells, {degrees}° about {axis:?}: force {f:.2e}, torque {t:.2e}");
            worst = (worst.0.max(f), worst.1.max(t));
        }
    }
    // Measured: force 4e-7 to 3.3e-6, torque 5.1e-4 to 1.2e-3, as for thick plates at this
    // pose (2 and 4 cells: force 4e-6 to 5e-5, torque 1.0e-3 to 1.9e-3); the issue's target
    // is 2% for both.
    assert!(worst.0 < 3e-5 && worst.1 < 1e-2, "force, torque errors {worst:?}");
}

/// Liquid (marker particles) that ends on the far side of the plane n·x = d in 0.3 s, less
/// what starts there, in a 1.0 × 0.6 × 0.3 m tank with 0.5 m of water left of x = 0.45 and
/// 0.1 m right of x = 0.55, and an obstacle `obstacle` (TOML) or none.
fn crossed(obstacle: &str, n: Vec3, d: f64) -> f64 {
    let text = format!(
        r#"
name = "leak"
[domain]
size = [1.0, 0.6, 0.3]
dx = {DX}
[time]
dt = 0.01
steps = 30
[fluid]
density = 1000.0
gravity = [0.0, -9.81, 0.0]
[[liquid]]
shape = {{ kind = "box", min = [0.0, 0.0, 0.0], max = [0.45, 0.5, 0.3] }}
[[liquid]]
shape = {{ kind = "box", min = [0.55, 0.0, 0.0], max = [1.0, 0.1, 0.3] }}
{obstacle}
[output]
particles = false
"#
    );
    let mut sim = Scene::from_toml(&text, "<test>").unwrap().build().unwrap();
    let count = |p: &[Vec3]| p.iter().filter(|x| n.dot(**x) > d).count() as f64;
    let before = count(&sim.particles);
    for _ in 0..30 {
        sim.step().unwrap();
    }
    count(&sim.particles) - before
}

/// Leakage of a static plate `cells` thick centred at `centre`, turned `degrees` about z:
/// the liquid past its far face over the liquid past the same plane with no plate.
fn leakage(cells: f64, centre: [f64; 3], degrees: f64) -> f64 {
    let t = cells * DX;
    let a = degrees.to_radians();
    let n = Vec3::new(a.cos(), a.sin(), 0.0);
    let obstacle = format!(
        r#"[[obstacle]]
shape = {{ kind = "cuboid", half_extents = [{}, 0.5, 0.3] }}
position = {centre:?}
axis_angle = {{ axis = [0.0, 0.0, 1.0], degrees = {degrees} }}"#,
        t / 2.0
    );
    let d = n.dot(Vec3::from_array(centre)) + t / 2.0;
    crossed(&obstacle, n, d) / crossed("", n, d)
}

#[test]
fn static_quarter_cell_plates_do_not_leak() {
    let mut worst: f64 = 0.0;
    for (offset, degrees) in [(0.0, 0.0), (0.3, 0.0), (0.5, 0.0), (0.3, 20.0)] {
        let l = leakage(0.25, [0.5 + offset * DX, 0.3, 0.15], degrees);
        eprintln!("centre {offset} cells off x = 0.5, {degrees}°: leakage {l:.3}");
        worst = worst.max(l.abs());
    }
    // Measured 0 for all but the plate 0.3 cells off, -0.011 there (a particle or two of the
    // right pool ends up left of the plate's far face); 0.99 to 1.0 by volume fractions alone.
    assert!(worst < 0.05, "leakage {worst}");
}
