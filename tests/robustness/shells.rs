//! Open meshes load as shells.
//!
//! An OBJ that is not closed (a sail, a leaf, a hull without a deck) is refused as a solid,
//! and the error names the `shell_thickness` key; with it, the surface loads as a shell that
//! thick, whose volume, and so its mass at a density, is thickness × area (exact for a flat
//! sheet, to first order in thickness over curvature radius for a bent one). A closed mesh
//! keeps today's rules: the key changes nothing. A shell thinner than a cell seals the
//! liquid as it moves (its depth is half its thickness).

use crate::common::{tank_toml, TempDir};
use diffluid::Scene;
use std::path::{Path, PathBuf};

/// An n × n grid of squares (two triangles each) on the surface `at(u, v)`, u, v in [0, 1],
/// written as the OBJ file `name` in `dir`; open along its four edges.
fn sheet(dir: &Path, name: &str, n: usize, at: impl Fn(f64, f64) -> [f64; 3]) -> PathBuf {
    let mut text = String::new();
    for j in 0..=n {
        for i in 0..=n {
            let p = at(i as f64 / n as f64, j as f64 / n as f64);
            text += &format!("v {} {} {}\n", p[0], p[1], p[2]);
        }
    }
    let id = |i: usize, j: usize| j * (n + 1) + i + 1;
    for j in 0..n {
        for i in 0..n {
            text += &format!("f {} {} {}\n", id(i, j), id(i + 1, j), id(i + 1, j + 1));
            text += &format!("f {} {} {}\n", id(i, j), id(i + 1, j + 1), id(i, j + 1));
        }
    }
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

fn scene(obj: &str, shell: &str) -> String {
    tank_toml("shell", [0.8, 0.6, 0.8], 0.05, 0.3, 5)
        + &format!(
            r#"
[[body]]
name = "sail"
shape = {{ kind = "mesh", obj = "{obj}" }}
density = 1000.0
position = [0.41, 0.2, 0.38]
{shell}
"#
        )
}

#[test]
fn an_open_mesh_without_a_thickness_names_the_key() {
    let dir = TempDir::new("shells");
    let flat = sheet(&dir, "flat.obj", 4, |u, v| [0.3 * u - 0.15, 0.0, 0.3 * v - 0.15]);
    let err = Scene::from_toml(&scene(flat.to_str().unwrap(), ""), "<test>")
        .and_then(|s| s.build())
        .map(drop)
        .expect_err("an open mesh is refused as a solid")
        .to_string();
    assert!(err.contains("not closed") && err.contains("shell_thickness"), "{err}");
}

#[test]
fn open_meshes_load_as_shells_of_their_thickness() {
    let t = 0.0125;
    // A flat 0.3 m square: volume exactly t × area.
    let dir = TempDir::new("shells");
    let flat = sheet(&dir, "flat.obj", 4, |u, v| [0.3 * u - 0.15, 0.0, 0.3 * v - 0.15]);
    let text = scene(flat.to_str().unwrap(), &format!("shell_thickness = {t}"));
    let mut sim = Scene::from_toml(&text, "<test>").unwrap().build().unwrap();
    let b = &sim.bodies()[0];
    let want = 1000.0 * t * 0.09;
    eprintln!("flat sail: mass {} kg against {want}", b.mass);
    assert!((b.mass - want).abs() < 1e-9 * want, "mass {}", b.mass);
    assert!(b.seals(0.05), "a quarter-cell shell seals the liquid");
    for _ in 0..5 {
        let r = sim.step().unwrap();
        assert!(r.bodies[0].volume_error < 1e-9, "volume error {}", r.bodies[0].volume_error);
    }
    // A sail bent on a cylinder of radius 0.3 m through 60°: area 0.3 × 0.3·π/3.
    let bent = sheet(&dir, "bent.obj", 12, |u, v| {
        let a = (u - 0.5) * std::f64::consts::FRAC_PI_3;
        [0.3 * a.sin(), 0.3 * (1.0 - a.cos()), 0.3 * v - 0.15]
    });
    let text = scene(bent.to_str().unwrap(), &format!("shell_thickness = {t}"));
    let b = Scene::from_toml(&text, "<test>").unwrap().build().unwrap().bodies()[0].clone();
    // The facets' area (a chord polygon of 12 sides), times t, at density 1000.
    let chord = 2.0 * 0.3 * (std::f64::consts::FRAC_PI_3 / 24.0).sin();
    let want = 1000.0 * t * 12.0 * chord * 0.3;
    eprintln!("bent sail: mass {} kg against {want}", b.mass);
    assert!((b.mass - want).abs() < 1e-3 * want, "mass {}", b.mass);
}

#[test]
fn closed_meshes_keep_their_rules() {
    let cube = concat!(env!("CARGO_MANIFEST_DIR"), "/assets/meshes/cube.obj");
    let build = |shell: &str| {
        let text = scene(cube, shell);
        Scene::from_toml(&text, "<test>").unwrap().build().unwrap().bodies()[0].clone()
    };
    let (solid, with_key) = (build(""), build("shell_thickness = 0.01"));
    assert_eq!(solid.mass.to_bits(), with_key.mass.to_bits());
    assert_eq!(solid.volume().to_bits(), with_key.volume().to_bits());
    let err = Scene::from_toml(&scene(cube, "shell_thickness = -1.0"), "<test>")
        .and_then(|s| s.build())
        .map(drop)
        .expect_err("a negative thickness is refused")
        .to_string();
    assert!(err.contains("shell_thickness"), "{err}");
}
