//! Crafted files in bulk: generated optimisation checkpoints, surface PLY frames (with the
//! run's `summary.json`) and OBJ meshes must each be read (and resumed, drawn or loaded) or
//! refused with one error line: never a panic. A checkpoint's error never speaks of a scene
//! file.
//!
//! - Checkpoints: the checkpoint of a 3-epoch gradient-descent, Adam or L-BFGS run of a small
//!   recovery scene, then edits: any key removed or set to a hostile value (a huge or
//!   negative number, a string, null, a list of another length, an empty object), a
//!   `next_epoch` moved, and lines of L-BFGS's TOML text replaced, dropped or doubled; then
//!   resumed for one more epoch.
//! - PLY frames: headers with small, huge and wrapping counts, missing or unexpected lines,
//!   data of the promised length or not, coordinates that are NaN, infinite or huge, indices
//!   in and out of range; drawn by `render_run` beside a summary that is valid, or not.
//! - OBJ files: vertices and faces of every form tobj reads (relative and out-of-range
//!   indices, texture and normal indices, polygons, points, lines, a material library that
//!   is `/dev/zero`), non-finite coordinates, and sets of cubes that cross, nest or stand
//!   apart; loaded as a body's mesh at a hostile scale, as its convex hull, and as a frame.
//!
//! CI runs `PROPTEST_CASES` cases of each (default 200); a 10⁵-case run:
//! `PROPTEST_CASES=100000 cargo test --release --test robustness fuzz_files -- --nocapture`.

#![cfg(all(feature = "csv", feature = "plots"))] // render_run and the checkpoints' writers

use crate::common::builtin_text;
use diffluid::experiments::optimize::{Checkpoint, Optimization};
use diffluid::experiments::outputs::{render_run, RenderRequest};
use diffluid::geometry::mesh::{load_obj, load_obj_hull};
use diffluid::io::output::read_mesh;
use diffluid::io::render::View;
use diffluid::Scene;
use proptest::prelude::*;
use proptest::test_runner::{Config, TestRng, TestRunner};
use serde_json::Value;
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};
use std::sync::OnceLock;

fn cases() -> u32 {
    std::env::var("PROPTEST_CASES").ok().and_then(|s| s.parse().ok()).unwrap_or(200)
}

/// A folder of this test process, removed at the end of each test that made it.
fn folder(name: &str) -> PathBuf {
    let dir =
        std::env::temp_dir().join(format!("diffluid-fuzz-files-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Runs `f` on every generated case: a panic or a multi-line error fails the test. `f`
/// returns how far the case got (an index into `outcomes`).
fn fuzz<S: Strategy>(
    strategy: S,
    outcomes: &[&str],
    f: impl Fn(&S::Value) -> Result<usize, String>,
) -> Vec<usize>
where
    S::Value: std::fmt::Debug,
{
    let counts: Vec<AtomicUsize> = outcomes.iter().map(|_| AtomicUsize::new(0)).collect();
    let cases = cases();
    // The same cases every run: the checks on how far the cases got (some refused, some
    // resumed) count rare outcomes (a few resumed checkpoints in 200), which a fresh seed
    // per run missed about one run in twenty.
    let config = Config { cases, failure_persistence: None, ..Config::default() };
    let rng = TestRng::deterministic_rng(config.rng_algorithm);
    let mut runner = TestRunner::new_with_rng(config, rng);
    let result = runner.run(&strategy, |value| {
        let reached = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| f(&value)));
        match reached {
            Err(_) => Err(TestCaseError::fail("panicked")),
            Ok(Err(message)) => Err(TestCaseError::fail(message)),
            Ok(Ok(k)) => {
                counts[k].fetch_add(1, Relaxed);
                Ok(())
            }
        }
    });
    if let Err(e) = result {
        panic!("{e}");
    }
    let n: Vec<usize> = counts.iter().map(|c| c.load(Relaxed)).collect();
    let summary: Vec<String> = outcomes.iter().zip(&n).map(|(o, n)| format!("{n} {o}")).collect();
    eprintln!("{cases} cases: {}", summary.join(", "));
    n
}

/// An error is fine if it is one line (and, for a checkpoint, never a scene file's).
fn one_line(e: &diffluid::Error) -> Result<(), String> {
    let text = e.to_string();
    if text.contains('\n') {
        return Err(format!("a multi-line error: {text}"));
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------
// Checkpoints

/// The recovery scene, small (8 × 6 × 8 cells, 3 steps), with `optimizer`.
fn small_recovery(optimizer: &str) -> Scene {
    let text = builtin_text("recover_box")
        .replacen("optimizer = { kind = \"gd\", learning_rate = 5.0 }", optimizer, 1)
        .replacen("steps = 20", "steps = 3", 1)
        .replacen("dx = 0.05", "dx = 0.1", 1);
    Scene::from_toml(&text, "<fuzz>").unwrap()
}

/// The three problems and the checkpoint each writes after 3 epochs, made once.
fn problems() -> &'static Vec<(Optimization, Value)> {
    static MADE: OnceLock<Vec<(Optimization, Value)>> = OnceLock::new();
    MADE.get_or_init(|| {
        let dir = folder("base");
        let out = [
            "optimizer = { kind = \"gd\", learning_rate = 5.0 }",
            "optimizer = { kind = \"adam\", learning_rate = 0.1 }",
            "optimizer = { kind = \"lbfgs\", memory = 3 }",
        ]
        .iter()
        .enumerate()
        .map(|(k, optimizer)| {
            let mut problem = Optimization::new(small_recovery(optimizer)).unwrap();
            problem.epochs = 3;
            let path = dir.join(format!("{k}.json"));
            problem.run(Some(&path), None, |_| {}).unwrap();
            let ck: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
            assert_eq!(ck["next_epoch"], 3);
            problem.epochs = 4;
            (problem, ck)
        })
        .collect();
        std::fs::remove_dir_all(&dir).ok();
        out
    })
}

/// One edit of a checkpoint's JSON: at the `at`-th node (in a walk of the current value),
/// do `what`.
#[derive(Clone, Debug)]
struct Edit {
    at: usize,
    what: EditKind,
}

#[derive(Clone, Debug)]
enum EditKind {
    /// Replace the node with this JSON.
    Set(String),
    /// Remove it from its object or list.
    Remove,
    /// Append a copy of a list's last element (or of the node to its list).
    Grow,
    /// In a string (L-BFGS's TOML): replace line `line` (modulo the count) with `text`,
    /// or drop it (None).
    Line { line: usize, text: Option<String> },
}

fn hostile_json() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("0".to_string()),
        Just("-1".to_string()),
        Just("1.5".to_string()),
        Just("1e308".to_string()),
        Just("-1e308".to_string()),
        Just("18446744073709551615".to_string()),
        Just("4611686018427387904".to_string()),
        Just("\"text\"".to_string()),
        Just("null".to_string()),
        Just("true".to_string()),
        Just("[]".to_string()),
        Just("[1.0, 2.0]".to_string()),
        Just("[0.0, 0.0, 0.0, 0.0, 0.0]".to_string()),
        Just("{}".to_string()),
        Just("\"Gd\"".to_string()),
        Just("{\"Adam\": {\"m\": [], \"v\": [], \"t\": 0}}".to_string()),
        (0u64..8).prop_map(|n| n.to_string()),
        (-2.0f64..2.0).prop_map(|x| format!("{x:?}")),
    ]
}

fn hostile_toml_line() -> impl Strategy<Value = String> {
    let key = prop_oneof![
        Just("param"),
        Just("grad"),
        Just("cost"),
        Just("iter"),
        Just("s"),
        Just("y"),
        Just("m"),
        Just("best_param"),
        Just("prev_param"),
        Just("termination_status"),
        Just("search_direction"),
        Just("ftol"),
        Just("stpmax"),
    ];
    let value = prop_oneof![
        Just("[]"),
        Just("[1.0]"),
        Just("[1.0, 2.0, 3.0]"),
        Just("[nan, inf, -inf]"),
        Just("[[1.0, 2.0, 3.0]]"),
        Just("[[1.0], [2.0]]"),
        Just("0"),
        Just("-1"),
        Just("nan"),
        Just("inf"),
        Just("1e308"),
        Just("\"Terminated\""),
        Just("{ Terminated = \"MaxItersReached\" }"),
        Just("\"text\""),
        Just("= ="),
    ];
    (key, value).prop_map(|(k, v)| format!("{k} = {v}"))
}

fn edit() -> impl Strategy<Value = Edit> {
    let what = prop_oneof![
        6 => hostile_json().prop_map(EditKind::Set),
        2 => Just(EditKind::Remove),
        1 => Just(EditKind::Grow),
        4 => (0usize..64, prop::option::weighted(0.8, hostile_toml_line()))
            .prop_map(|(line, text)| EditKind::Line { line, text }),
    ];
    (0usize..10_000, what).prop_map(|(at, what)| Edit { at, what })
}

/// Every node of `v` as a path of keys and indices, depth first (the root first).
fn nodes(v: &Value, path: &mut Vec<Value>, out: &mut Vec<Vec<Value>>) {
    out.push(path.clone());
    match v {
        Value::Object(m) => {
            for (k, x) in m {
                path.push(Value::String(k.clone()));
                nodes(x, path, out);
                path.pop();
            }
        }
        Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                path.push(Value::from(i));
                nodes(x, path, out);
                path.pop();
            }
        }
        _ => {}
    }
}

fn at_path<'a>(v: &'a mut Value, path: &[Value]) -> &'a mut Value {
    path.iter().fold(v, |v, k| match k {
        Value::String(s) => &mut v[s.as_str()],
        k => &mut v[k.as_u64().unwrap() as usize],
    })
}

fn apply(ck: &mut Value, e: &Edit) {
    let mut all = Vec::new();
    nodes(ck, &mut Vec::new(), &mut all);
    // Line edits go to a string node (L-BFGS's TOML text, or any other string).
    let candidates: Vec<&Vec<Value>> = match e.what {
        EditKind::Line { .. } => {
            all.iter().filter(|p| at_path(&mut ck.clone(), p).is_string()).collect()
        }
        _ => all.iter().collect(),
    };
    if candidates.is_empty() {
        return;
    }
    let path = candidates[e.at % candidates.len()].clone();
    match &e.what {
        EditKind::Set(text) => *at_path(ck, &path) = serde_json::from_str(text).unwrap(),
        EditKind::Remove => {
            if let Some((last, parent)) = path.split_last() {
                match (at_path(ck, parent), last) {
                    (Value::Object(m), Value::String(k)) => {
                        m.remove(k);
                    }
                    (Value::Array(a), i) => {
                        a.remove(i.as_u64().unwrap() as usize);
                    }
                    _ => {}
                }
            }
        }
        EditKind::Grow => {
            let node = at_path(ck, &path);
            if let Value::Array(a) = node {
                if let Some(x) = a.last().cloned() {
                    a.push(x);
                }
            } else if let Some((_, parent)) = path.split_last() {
                let copy = node.clone();
                if let Value::Array(a) = at_path(ck, parent) {
                    a.push(copy);
                }
            }
        }
        EditKind::Line { line, text } => {
            let node = at_path(ck, &path);
            let old = node.as_str().unwrap_or("").to_string();
            let mut lines: Vec<&str> = old.lines().collect();
            if lines.is_empty() {
                lines.push("");
            }
            let k = line % lines.len();
            match text {
                Some(t) => lines[k] = t,
                None => {
                    lines.remove(k);
                }
            }
            *node = Value::String(lines.join("\n"));
        }
    }
}

#[test]
fn generated_checkpoints_resume_or_give_one_error_line() {
    std::panic::set_hook(Box::new(|_| {}));
    let problems = problems();
    let dir = folder("checkpoints");
    let strategy = (0usize..3, prop::collection::vec(edit(), 1..4));
    let counter = AtomicUsize::new(0);
    let n = fuzz(strategy, &["refused when read", "refused on resume", "resumed"], |(k, edits)| {
        let (problem, base) = &problems[*k];
        let mut ck = base.clone();
        for e in edits {
            apply(&mut ck, e);
        }
        let path = dir.join(format!("{}.json", counter.fetch_add(1, Relaxed)));
        std::fs::write(&path, serde_json::to_vec(&ck).unwrap()).unwrap();
        let scene_file = |e: &diffluid::Error| -> Result<(), String> {
            one_line(e)?;
            if e.to_string().contains("scene file") || !e.to_string().contains("checkpoint") {
                return Err(format!("not a checkpoint's error: {e}"));
            }
            Ok(())
        };
        let loaded = Checkpoint::load(&path);
        std::fs::remove_file(&path).ok();
        let resume = match loaded {
            Ok(c) => c,
            Err(e) => return scene_file(&e).map(|()| 0),
        };
        match problem.run(None, Some(resume), |_| {}) {
            Ok(_) => Ok(2),
            Err(e @ diffluid::Error::Checkpoint { .. }) => scene_file(&e).map(|()| 1),
            Err(e) => one_line(&e).map(|()| 2),
        }
    });
    let _ = std::panic::take_hook();
    std::fs::remove_dir_all(&dir).ok();
    assert!(n[1] > 0 && n[2] > 0, "the edits reach neither the checks nor a resumed run: {n:?}");
}

// ---------------------------------------------------------------------------------------
// Surface PLY frames and summaries

/// A count that is not the data's: small, huge, wrapping, or not a number.
fn count() -> impl Strategy<Value = String> {
    prop_oneof![
        5 => (0u64..6).prop_map(|n| n.to_string()),
        1 => Just("4611686018427387904".to_string()),
        1 => Just("1537228672809129302".to_string()),
        1 => Just("18446744073709551615".to_string()),
        1 => Just("18446744073709551616".to_string()),
        1 => Just("-1".to_string()),
        1 => Just("1e3".to_string()),
        1 => Just(String::new()),
    ]
}

fn coordinate() -> impl Strategy<Value = f32> {
    prop_oneof![
        20 => 0.0f32..0.4,
        1 => Just(f32::NAN),
        1 => Just(f32::INFINITY),
        1 => Just(f32::NEG_INFINITY),
        1 => Just(3e38f32),
        1 => Just(-3e38f32),
        1 => Just(1e-40f32),
    ]
}

/// A PLY file: a header (mostly as `MeshFormat::write` writes it), then the data.
fn ply() -> impl Strategy<Value = Vec<u8>> {
    let header_line = prop_oneof![
        Just("comment x"),
        Just("format ascii 1.0"),
        Just("element edge 1"),
        Just("property double x"),
        Just("property list uchar short vertex_indices"),
        Just("obj_info y"),
        Just("element vertex 2"),
        Just(""),
    ];
    let vertices = prop::collection::vec([coordinate(), coordinate(), coordinate()], 0..8);
    let faces = prop::collection::vec(
        (
            prop_oneof![10 => Just(3u8), 1 => any::<u8>()],
            [0u32..8, 0u32..8, 0u32..8],
            any::<bool>(),
        ),
        0..8,
    );
    (
        prop::option::weighted(0.1, count()),
        prop::option::weighted(0.1, count()),
        prop::option::weighted(0.1, (0usize..9, header_line)),
        any::<bool>(),
        vertices,
        faces,
        prop_oneof![10 => Just(None), 1 => prop::collection::vec(any::<u8>(), 0..80).prop_map(Some)],
        prop_oneof![20 => Just(0usize), 1 => 1usize..30],
    )
        .prop_map(|(nv, nf, extra, uint, vertices, faces, raw, cut)| {
            let nv = nv.unwrap_or_else(|| vertices.len().to_string());
            let nf = nf.unwrap_or_else(|| faces.len().to_string());
            let mut header = vec![
                "ply".to_string(),
                "format binary_little_endian 1.0".to_string(),
                format!("element vertex {nv}"),
                "property float x".to_string(),
                "property float y".to_string(),
                "property float z".to_string(),
                format!("element face {nf}"),
                format!("property list uchar {} vertex_indices", if uint { "uint" } else { "int" }),
                "end_header".to_string(),
            ];
            if let Some((at, line)) = extra {
                header.insert(at.min(header.len()), line.to_string());
            }
            let mut out = (header.join("\n") + "\n").into_bytes();
            match raw {
                Some(bytes) => out.extend(bytes),
                None => {
                    for v in &vertices {
                        for c in v {
                            out.extend(c.to_le_bytes());
                        }
                    }
                    for (n, idx, wild) in &faces {
                        out.push(*n);
                        for i in idx {
                            let i = if *wild {
                                i.wrapping_mul(0x9e37_79b9)
                            } else {
                                i % vertices.len().max(1) as u32
                            };
                            out.extend(i.to_le_bytes());
                        }
                    }
                }
            }
            out.truncate(out.len() - cut.min(out.len()));
            out
        })
}

fn summary() -> impl Strategy<Value = String> {
    let axis = prop_oneof![10 => (1u64..12).prop_map(|n| n.to_string()), 1 => Just("0".to_string()),
        1 => Just("-3".to_string()), 1 => Just("2.5".to_string()), 1 => Just("100000000".to_string()),
        1 => Just("18446744073709551615".to_string())];
    let number = prop_oneof![10 => Just("0.05".to_string()), 1 => Just("0".to_string()),
        1 => Just("-1".to_string()), 1 => Just("1e308".to_string()), 1 => Just("\"x\"".to_string())];
    prop_oneof![
        10 => Just(r#"{"scene": "fuzz", "grid": [8, 8, 8], "dx": 0.05, "dt": 0.01}"#.to_string()),
        3 => (axis.clone(), axis.clone(), axis, number.clone(), number).prop_map(|(a, b, c, dx, dt)| {
            format!(r#"{{"scene": "fuzz", "grid": [{a}, {b}, {c}], "dx": {dx}, "dt": {dt}}}"#)
        }),
        1 => Just("[]".to_string()),
        1 => Just(r#"{"grid": [8, 8]}"#.to_string()),
    ]
}

#[test]
fn generated_surface_frames_render_or_give_one_error_line() {
    let dir = folder("frames");
    let counter = AtomicUsize::new(0);
    let strategy = (ply(), summary(), any::<bool>(), 64u32..200, any::<bool>());
    let n = fuzz(strategy, &["refused", "drawn"], |(ply, summary, body, width, top)| {
        let run = dir.join(counter.fetch_add(1, Relaxed).to_string());
        std::fs::create_dir_all(run.join("surface")).unwrap();
        std::fs::write(run.join("summary.json"), summary).unwrap();
        std::fs::write(run.join("surface/0000.ply"), ply).unwrap();
        if *body {
            std::fs::create_dir_all(run.join("bodies")).unwrap();
            std::fs::write(run.join("bodies/b_0000.ply"), ply).unwrap();
        }
        let request = RenderRequest {
            frame: Some(0),
            out: Some(run.join("frame.png")),
            width: *width,
            view: if *top { View::Top } else { View::Side },
        };
        let drawn = render_run(&run, &request);
        std::fs::remove_dir_all(&run).ok();
        match drawn {
            Ok(_) => Ok(1),
            Err(e) => one_line(&e).map(|()| 0),
        }
    });
    std::fs::remove_dir_all(&dir).ok();
    assert!(n[1] > 0, "no generated frame was drawn: {n:?}");
}

// ---------------------------------------------------------------------------------------
// OBJ meshes

fn obj_number() -> impl Strategy<Value = String> {
    prop_oneof![
        30 => (-0.2f64..0.2).prop_map(|x| format!("{x:?}")),
        1 => Just("nan".to_string()),
        1 => Just("inf".to_string()),
        1 => Just("-inf".to_string()),
        1 => Just("1e300".to_string()),
        1 => Just("1e-300".to_string()),
        1 => Just("abc".to_string()),
    ]
}

fn obj_index() -> impl Strategy<Value = String> {
    prop_oneof![
        30 => (1i64..12).prop_map(|i| i.to_string()),
        4 => (-12i64..0).prop_map(|i| i.to_string()),
        1 => Just("0".to_string()),
        1 => Just("4294967296".to_string()),
        1 => Just("99999999999999999999".to_string()),
        2 => (1i64..12, 1i64..4).prop_map(|(i, t)| format!("{i}/{t}")),
        2 => (1i64..12, 1i64..4).prop_map(|(i, n)| format!("{i}//{n}")),
        1 => Just("x".to_string()),
    ]
}

fn obj_line() -> impl Strategy<Value = String> {
    prop_oneof![
        12 => (obj_number(), obj_number(), obj_number()).prop_map(|(a, b, c)| format!("v {a} {b} {c}")),
        1 => (obj_number(), obj_number()).prop_map(|(a, b)| format!("v {a} {b}")),
        1 => (obj_number(), obj_number(), obj_number(), obj_number())
            .prop_map(|(a, b, c, w)| format!("v {a} {b} {c} {w}")),
        12 => prop::collection::vec(obj_index(), 1..7).prop_map(|i| format!("f {}", i.join(" "))),
        1 => (obj_number(), obj_number()).prop_map(|(a, b)| format!("vt {a} {b}")),
        1 => (obj_number(), obj_number(), obj_number()).prop_map(|(a, b, c)| format!("vn {a} {b} {c}")),
        1 => Just("o part".to_string()),
        1 => Just("g group".to_string()),
        1 => Just("s 1".to_string()),
        1 => Just("l 1 2".to_string()),
        1 => Just("p 1".to_string()),
        1 => Just("mtllib /dev/zero".to_string()),
        1 => Just("usemtl m".to_string()),
        1 => Just("# comment".to_string()),
        1 => Just("garbage line".to_string()),
    ]
}

const CUBE_VERTICES: [[f64; 3]; 8] = [
    [-1.0, -1.0, -1.0],
    [1.0, -1.0, -1.0],
    [1.0, 1.0, -1.0],
    [-1.0, 1.0, -1.0],
    [-1.0, -1.0, 1.0],
    [1.0, -1.0, 1.0],
    [1.0, 1.0, 1.0],
    [-1.0, 1.0, 1.0],
];
const CUBE_FACES: [[usize; 3]; 12] = [
    [1, 4, 3],
    [1, 3, 2],
    [5, 6, 7],
    [5, 7, 8],
    [1, 2, 6],
    [1, 6, 5],
    [4, 8, 7],
    [4, 7, 3],
    [1, 5, 8],
    [1, 8, 4],
    [2, 3, 7],
    [2, 7, 6],
];

/// Cubes (half-side, centre, inward), written as one OBJ file, with now and then a face
/// dropped, flipped or doubled.
fn cubes() -> impl Strategy<Value = String> {
    let cube =
        (0.01f64..0.15, [-0.2f64..0.2, -0.2f64..0.2, -0.2f64..0.2], prop::bool::weighted(0.2));
    let damage = prop::option::weighted(0.2, (0usize..100, 0u8..3));
    (prop::collection::vec(cube, 1..6), damage).prop_map(|(cubes, damage)| {
        let mut text = String::new();
        let mut faces = Vec::new();
        for (k, (h, c, inward)) in cubes.iter().enumerate() {
            for v in CUBE_VERTICES {
                text += &format!("v {} {} {}\n", c[0] + h * v[0], c[1] + h * v[1], c[2] + h * v[2]);
            }
            for f in CUBE_FACES {
                let [a, b, d] = f.map(|i| i + 8 * k);
                faces.push(if *inward { [a, d, b] } else { [a, b, d] });
            }
        }
        if let Some((at, how)) = damage {
            let at = at % faces.len();
            match how {
                0 => {
                    faces.remove(at);
                }
                1 => faces[at].swap(1, 2),
                _ => faces.push(faces[at]),
            }
        }
        for f in faces {
            text += &format!("f {} {} {}\n", f[0], f[1], f[2]);
        }
        text
    })
}

#[test]
fn generated_obj_files_load_or_give_one_error_line() {
    let dir = folder("obj");
    let counter = AtomicUsize::new(0);
    let text = prop_oneof![
        1 => prop::collection::vec(obj_line(), 0..30).prop_map(|l| l.join("\n")),
        1 => cubes(),
    ];
    let scale = prop_oneof![
        20 => Just(1.0f64),
        2 => 0.1f64..10.0,
        1 => Just(0.0),
        1 => Just(-1.0),
        1 => Just(f64::NAN),
        1 => Just(1e300),
        1 => Just(1e-300),
    ];
    let n =
        fuzz((text, scale), &["refused", "loaded as a hull only", "loaded"], |(text, scale)| {
            let path: PathBuf = dir.join(format!("{}.obj", counter.fetch_add(1, Relaxed)));
            std::fs::write(&path, text).unwrap();
            let check = |e: &str| -> Result<(), String> {
                if e.contains('\n') {
                    return Err(format!("a multi-line error: {e}"));
                }
                Ok(())
            };
            let loaded = load_obj(&path, *scale);
            let hull = load_obj_hull(&path, *scale);
            let frame = read_mesh(&path);
            std::fs::remove_file(&path).ok();
            if let Err(e) = &frame {
                one_line(e)?;
            }
            match (loaded, hull) {
                (Ok(_), _) => Ok(2),
                (Err(e), Ok(_)) => check(&e.to_string()).map(|()| 1),
                (Err(e), Err(h)) => {
                    check(&e.to_string()).and_then(|()| check(&h.to_string())).map(|()| 0)
                }
            }
        });
    std::fs::remove_dir_all(&dir).ok();
    assert!(n[2] > 0 && n[0] > 0, "{n:?}");
}
