//! End-to-end gradients against central finite differences of the same forward map.
//!
//! With the surface frozen (`solver.freeze_surface`), the forward step is a smooth map of
//! the state away from the places where a face opens or a cell changes kind, and the
//! backward pass must reproduce its derivative: ⟨∇L, d⟩ = (L(x + εd) − L(x − εd)) / 2ε.

use diffluid::adjoint::{backward, AdjointState, GradientMode, Tape};
use diffluid::grid::Mac;
use diffluid::{Scene, Simulation};

fn small_tank(body: &str, steps: usize) -> Scene {
    let text = format!(
        r#"
name = "grad"
[domain]
size = [0.8, 0.6, 0.8]
dx = 0.05
[time]
dt = 0.01
steps = {steps}
[fluid]
density = 1000.0
gravity = [0.0, -9.81, 0.0]
[[liquid]]
shape = {{ kind = "box", min = [0.0, 0.0, 0.0], max = [0.8, 0.3, 0.8] }}
{body}
[solver]
tolerance = 1e-12
freeze_surface = true
"#
    );
    Scene::from_toml(&text, "<test>").unwrap()
}

/// A fixed linear functional of the final fluid velocity.
fn weights_for(sim: &Simulation) -> Mac {
    let mut c = Mac::zeros(sim.grid());
    for a in 0..3 {
        for (f, x) in c.c[a].iter_mut().enumerate() {
            *x = (((f * 7919 + a * 104729) % 211) as f64 / 105.0 - 1.0) * 1e-3;
        }
    }
    c
}

fn run(scene: &Scene, u0: &Mac, c: &Mac) -> f64 {
    let mut sim = Simulation::new(scene.clone()).unwrap();
    sim.u = u0.clone();
    for _ in 0..scene.time.steps {
        sim.step().unwrap();
    }
    sim.u.dot(c)
}

#[test]
fn fluid_velocity_gradient_matches_central_differences() {
    let scene = small_tank("", 10);
    let sim0 = Simulation::new(scene.clone()).unwrap();
    // A swirling initial field.
    let mut u0 = Mac::zeros(sim0.grid());
    let g = *sim0.grid();
    for a in 0..3 {
        let lat = g.faces(a);
        lat.fill_par(&mut u0.c[a], |i, j, k| {
            let p = lat.position(i, j, k);
            0.3 * ((3.0 * p.x + a as f64).sin() * (4.0 * p.z).cos() + 0.5 * (5.0 * p.y).sin())
        });
    }
    let c = weights_for(&sim0);
    let mut sim = sim0.clone();
    sim.u = u0.clone();
    let mut tape = Tape::default();
    for _ in 0..scene.time.steps {
        sim.step_taped(&mut tape).unwrap();
    }
    let adj = AdjointState { u: c.clone(), bodies: vec![] };
    let mut init = sim0.clone();
    init.u = u0.clone();
    let grad = backward(&init, &tape, adj, GradientMode::Full).unwrap();
    // A smooth direction.
    let mut d = Mac::zeros(&g);
    for a in 0..3 {
        let lat = g.faces(a);
        lat.fill_par(&mut d.c[a], |i, j, k| {
            let p = lat.position(i, j, k);
            (2.0 * p.y + a as f64).cos() * (3.0 * p.x).sin()
        });
    }
    let eps = 1e-6;
    let shifted = |s: f64| {
        let mut u = u0.clone();
        for a in 0..3 {
            for (x, y) in u.c[a].iter_mut().zip(&d.c[a]) {
                *x += s * y;
            }
        }
        run(&scene, &u, &c)
    };
    let fd = (shifted(eps) - shifted(-eps)) / (2.0 * eps);
    let ad = grad.u.dot(&d);
    let rel = (ad - fd).abs() / fd.abs();
    eprintln!(
        "∂L/∂u₀·d: adjoint {ad:.10e}, central difference {fd:.10e}, relative error {rel:.2e}"
    );
    // ε = 1e-6: larger steps cross the kinks of trilinear interpolation (1e-4 gave 2e-4).
    assert!(rel < 1e-7, "relative error {rel:e}");
}
