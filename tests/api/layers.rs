//! The layers of `src/`, and which may use which (ARCHITECTURE.md draws them):
//!
//! ```text
//! experiments  scene files, optimisation, bench studies, what the CLI writes
//!   io         PLY/JSON/CSV writers, the run recorder, VTK, pictures
//!   gradients  losses, the backward pass, gradient checks
//!     world    the simulation, its settings, the step's shared assembly, the tape
//!       stages   advection, forces, surface, density, pressure, extrapolation, contact
//!         solvers  CG, MIC(0), multigrid, the stencil
//!           geometry  grid, shapes, meshes, bodies, fractions
//!             math, error
//! ```
//!
//! A module may use its own layer and the layers below it (io sits beside gradients: it may
//! use world and below, and gradients may not use io). The test reads every file under
//! `src/`, skips comments and `#[cfg(test)]` modules (a test may build what it checks from
//! any layer), and fails on a `crate::<layer>` path its layer may not name. So a stage can
//! never reach the scene schema or the optimiser, and the world never the backward pass.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Each layer and the layers it may use besides itself.
fn allowed() -> BTreeMap<&'static str, Vec<&'static str>> {
    let base = ["math", "error"];
    let mut m = BTreeMap::new();
    m.insert("math", vec![]);
    m.insert("error", vec![]);
    let mut below: Vec<&str> = base.to_vec();
    for layer in ["geometry", "solvers", "stages", "world", "gradients"] {
        m.insert(layer, below.clone());
        below.push(layer);
    }
    m.insert("io", vec!["math", "error", "geometry", "world"]);
    let mut all = below.clone();
    all.push("io");
    m.insert("experiments", all);
    m
}

fn files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// The file's text without comments and without `#[cfg(test)]` items.
fn code(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut skip_depth: Option<i64> = None;
    let mut pending_test = false;
    for (n, line) in text.lines().enumerate() {
        let t = line.trim_start();
        if t.starts_with("//") {
            continue;
        }
        let code = match t.find("//") {
            Some(i) => &t[..i],
            None => t,
        };
        if let Some(depth) = skip_depth.as_mut() {
            *depth += code.matches('{').count() as i64 - code.matches('}').count() as i64;
            if *depth <= 0 {
                skip_depth = None;
            }
            continue;
        }
        if code.starts_with("#[cfg(test)]") {
            pending_test = true;
            continue;
        }
        if pending_test {
            let d = code.matches('{').count() as i64 - code.matches('}').count() as i64;
            pending_test = false;
            if d > 0 {
                skip_depth = Some(d);
            }
            continue;
        }
        out.push((n + 1, code.to_string()));
    }
    out
}

#[test]
fn no_layer_uses_a_layer_above_it() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut all = Vec::new();
    files(&src, &mut all);
    let allowed = allowed();
    let mut violations = Vec::new();
    let mut checked = 0;
    for path in &all {
        let rel = path.strip_prefix(&src).unwrap();
        let first = rel.components().next().unwrap().as_os_str().to_string_lossy().to_string();
        let layer = first.trim_end_matches(".rs").to_string();
        if layer == "lib" || layer == "main" {
            continue;
        }
        // A module's tests in a file of their own (`#[cfg(test)] mod tests;`) may use any
        // layer, as the inline `#[cfg(test)]` modules the parser skips may.
        if path.file_name().is_some_and(|f| f == "tests.rs") {
            let parent = std::fs::read_to_string(path.with_file_name("mod.rs")).unwrap_or_default();
            assert!(
                parent.contains("#[cfg(test)]\nmod tests;"),
                "{}: a tests.rs not declared as `#[cfg(test)] mod tests;`",
                rel.display()
            );
            continue;
        }
        let may = allowed.get(layer.as_str()).unwrap_or_else(|| {
            panic!("{} is in no layer: add its folder to this test", rel.display())
        });
        let text = std::fs::read_to_string(path).unwrap();
        for (n, line) in code(&text) {
            for (i, _) in line.match_indices("crate::") {
                let rest = &line[i + "crate::".len()..];
                let name: String =
                    rest.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
                checked += 1;
                if name == layer || !allowed.contains_key(name.as_str()) {
                    continue;
                }
                if !may.contains(&name.as_str()) {
                    violations.push(format!("{}:{n}: {layer} uses crate::{name}", rel.display()));
                }
            }
        }
    }
    assert!(checked > 100, "only {checked} crate paths found: is the parser broken?");
    assert!(violations.is_empty(), "layer violations:\n{}", violations.join("\n"));
}

/// The checker itself: a forbidden path is caught, a test module and a comment are not.
#[test]
fn the_checker_sees_code_and_skips_tests_and_comments() {
    let text = "use crate::world::Simulation;\n// crate::experiments in a comment\n\
                #[cfg(test)]\nmod tests {\n    use crate::experiments::scene::Scene;\n    fn f() {}\n}\n\
                fn g() { crate::gradients::backward(); }\n";
    let lines: Vec<String> = code(text).into_iter().map(|(_, l)| l).collect();
    assert!(lines.iter().any(|l| l.contains("crate::world")));
    assert!(lines.iter().any(|l| l.contains("crate::gradients")));
    assert!(!lines.iter().any(|l| l.contains("crate::experiments")), "{lines:?}");
}
