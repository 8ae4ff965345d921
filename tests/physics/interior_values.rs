//! With the soft φ_L, a step makes the soft minimum's sum only where it reads φ's value, not
//! just its sign (`surface::Reads`): the liquid's interior holds the deep value instead. The
//! claim is that nothing in the step reads those cells' values, so the step's results must
//! be the same bits as with the sum made in every cell (`solver.surface_interior_values`).
//! Any stage that read an interior value would part the two runs within a step or two.

use crate::common::{asset, builtin_text};
use diffluid::Scene;

/// Runs `scene` for `steps` steps with φ_L's value made everywhere and only where it is
/// read, and checks that the particles, the velocity field and the bodies are the same
/// bits after every step. Returns the most cells of φ_L that held the deep value in a step
/// (so a test can check that there was an interior to leave out).
fn same_bits(mut scene: Scene, steps: usize) -> usize {
    scene.solver.surface_softness = 0.35;
    scene.solver.surface_interior_values = true;
    let mut everywhere = scene.build().unwrap();
    scene.solver.surface_interior_values = false;
    let mut read_only = scene.build().unwrap();
    let mut differs = 0;
    for step in 0..steps {
        everywhere.step().unwrap();
        read_only.step().unwrap();
        let (a, b) = (everywhere.liquid_phi(), read_only.liquid_phi());
        differs = differs.max(a.iter().zip(b).filter(|(x, y)| x != y).count());
        assert!(
            a.iter().zip(b).all(|(x, y)| (*x < 0.0) == (*y < 0.0)),
            "{}: step {step}: φ_L's sign differs",
            scene.name
        );
        assert_eq!(everywhere.particles(), read_only.particles(), "{}: step {step}", scene.name);
        let (u, v) = (everywhere.velocity_field(), read_only.velocity_field());
        for axis in 0..3 {
            assert!(u.c[axis] == v.c[axis], "{}: step {step}: velocity {axis}", scene.name);
        }
        for (p, q) in everywhere.bodies().iter().zip(read_only.bodies()) {
            assert_eq!(p.state(), q.state(), "{}: step {step}: body", scene.name);
        }
    }
    eprintln!("{}: at most {differs} cells of φ_L held the deep value", scene.name);
    differs
}

/// The surge on a ball (a body crossing the surface, the ghosts, the density projection)
/// and the dam break with a ball (a collapsing column, splashes, a body struck).
#[test]
fn the_interior_skip_leaves_the_step_unchanged() {
    for (name, steps) in [("surge_ball", 30), ("dam_break_ball", 30)] {
        let differs = same_bits(Scene::builtin(name).unwrap(), steps);
        assert!(differs > 100, "{name}: only {differs} interior cells left out");
    }
}

/// The same with a narrow band (its deep cells carry no particles) around two floating
/// bodies, one of them an OBJ mesh, in a collapsing column: `large_tank` made small.
#[test]
fn the_interior_skip_leaves_a_banded_step_unchanged() {
    let text = builtin_text("large_tank")
        .replace("dx = 0.025", "dx = 0.1")
        .replace("narrow_band = 3", "narrow_band = 2");
    let scene = Scene::from_toml_in(&text, "<small tank>", asset("scenes")).unwrap();
    let differs = same_bits(scene, 20);
    assert!(differs > 100, "only {differs} interior cells left out");
}
