//! Bad input in bulk: generated scene files (random keys and values, shapes, meshes, NaN,
//! infinities, huge and tiny numbers, empty tanks, overlapping bodies) must each give either
//! a clean run of a few steps or one error naming the problem: never a panic, and never a
//! message of more than one line.
//!
//! The cases run in process (parse, build, three steps), each on a small tank so none takes
//! long. CI runs `PROPTEST_CASES` cases (default 300); 10⁵ took a minute with 0 panics (75%
//! refused when read, 2% failed in a step, 23% ran:
//! `PROPTEST_CASES=100000 cargo test --release --test robustness fuzz_scenes -- --nocapture`).
//!
//! Names in bulk: generated scene and body names (path separators, `..`, absolute paths
//! into the test's folder, XML markup, NUL and other control characters, any Unicode, empty
//! and overlong ones) are refused in one line or recorded (frame 0, a step, the summary,
//! particles, bodies and ParaView frames) into `out/<scene name>` as `diffluid run` would:
//! never a panic, and never a file outside that folder. `PROPTEST_CASES` sets the count here
//! too (default 100).

use diffluid::Scene;
use proptest::prelude::*;
use proptest::test_runner::{Config, TestRunner};

/// A hostile number (or not a number) as a TOML value.
fn hostile() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("nan".to_string()),
        Just("inf".to_string()),
        Just("-inf".to_string()),
        Just("0.0".to_string()),
        Just("-1.0".to_string()),
        Just("1e300".to_string()),
        Just("-1e300".to_string()),
        Just("1e-300".to_string()),
        Just("1e-9".to_string()),
        (0u64..1000).prop_map(|n| n.to_string()),
        Just("\"text\"".to_string()),
        Just("[1, 2]".to_string()),
    ]
}

/// A number in `lo..hi` most of the time, a hostile one now and then.
fn num(lo: f64, hi: f64) -> impl Strategy<Value = String> {
    prop_oneof![40 => (lo..hi).prop_map(|x| format!("{x:?}")), 1 => hostile()]
}

fn vec3(lo: f64, hi: f64) -> impl Strategy<Value = String> {
    prop_oneof![
        80 => (num(lo, hi), num(lo, hi), num(lo, hi)).prop_map(|(a, b, c)| format!("[{a}, {b}, {c}]")),
        1 => Just("[0.1, 0.2]".to_string()),
        1 => Just("[]".to_string()),
    ]
}

/// A shape table of about a tenth of a metre, now and then one of a kind that is not.
fn shape() -> impl Strategy<Value = String> {
    let good = prop_oneof![
        (vec3(0.0, 0.4), vec3(0.0, 0.4))
            .prop_map(|(a, b)| format!("{{ kind = \"box\", min = {a}, max = {b} }}")),
        vec3(0.0, 0.12).prop_map(|h| format!("{{ kind = \"cuboid\", half_extents = {h} }}")),
        num(0.0, 0.12).prop_map(|r| format!("{{ kind = \"ball\", radius = {r} }}")),
        (num(0.0, 0.1), num(0.0, 0.08)).prop_map(|(h, r)| {
            format!("{{ kind = \"capsule\", half_height = {h}, radius = {r} }}")
        }),
        (num(0.0, 0.1), num(0.0, 0.08)).prop_map(|(h, r)| {
            format!("{{ kind = \"cylinder\", half_height = {h}, radius = {r} }}")
        }),
        prop::collection::vec(vec3(-0.1, 0.1), 3..8)
            .prop_map(|p| format!("{{ kind = \"convex_hull\", points = [{}] }}", p.join(", "))),
        (
            num(0.1, 0.6),
            prop_oneof![
                12 => Just("assets/meshes/cube.obj"),
                1 => Just("no/such.obj"),
                1 => Just("Cargo.toml"),
                1 => Just("assets/meshes"),
            ]
        )
            .prop_map(|(s, p)| format!("{{ kind = \"mesh\", obj = \"{p}\", scale = {s} }}")),
    ];
    let bad = prop_oneof![
        Just("{ kind = \"torus\" }".to_string()),
        Just("{ kind = \"ball\" }".to_string()),
        Just("{ kind = \"ball\", radius = 0.1, extra = 1 }".to_string()),
    ];
    prop_oneof![40 => good, 1 => bad]
}

/// A small valid scene, then edits: each replaces a line, adds a table or a key.
fn scene() -> impl Strategy<Value = String> {
    let size = prop_oneof![
        40 => Just("[0.4, 0.4, 0.4]".to_string()),
        1 => Just("[0.0, 0.4, 0.4]".to_string()),
        4 => vec3(0.0, 0.5),
    ];
    let dx =
        prop_oneof![30 => Just("0.1".to_string()), 6 => Just("0.05".to_string()), 1 => hostile()];
    let dt = prop_oneof![30 => num(0.001, 0.05), 1 => hostile()];
    let liquid = prop_oneof![
        40 => Just("shape = { kind = \"box\", min = [0.0, 0.0, 0.0], max = [0.4, 0.2, 0.4] }".to_string()),
        20 => shape().prop_map(|s| format!("shape = {s}\nposition = [0.2, 0.1, 0.2]")),
        1 => Just(String::new()),
    ];
    let body = (
        shape(),
        vec3(0.0, 0.4),
        num(100.0, 3000.0),
        vec3(-1.0, 1.0),
        vec3(-3.0, 3.0),
        any::<bool>(),
    )
        .prop_map(|(s, p, d, v, w, dynamic)| {
            format!(
                "[[body]]\nshape = {s}\nposition = {p}\ndensity = {d}\nvelocity = {v}\n\
                 angular_velocity = {w}\ndynamic = {dynamic}\n"
            )
        });
    let near_body = (num(100.0, 3000.0), any::<bool>()).prop_map(|(d, dynamic)| {
        format!(
            "[[body]]\nshape = {{ kind = \"cuboid\", half_extents = [0.05, 0.05, 0.05] }}\n\
             position = [0.2, 0.25, 0.2]\ndensity = {d}\ndynamic = {dynamic}\n"
        )
    });
    let solver_entry = prop_oneof![
        3 => num(1e-12, 1e-4).prop_map(|v| format!("tolerance = {v}")),
        2 => (1u64..3000).prop_map(|v| format!("max_iterations = {v}")),
        2 => prop_oneof![Just("mic0"), Just("multigrid"), Just("none"), Just("auto")]
            .prop_map(|v| format!("preconditioner = \"{v}\"")),
        2 => (0u64..300).prop_map(|v| format!("extrapolation_layers = {v}")),
        2 => prop_oneof![Just(1u64), Just(8), Just(27), Just(5)]
            .prop_map(|v| format!("particles_per_cell = {v}")),
        2 => num(0.0, 0.6).prop_map(|v| format!("theta_min = {v}")),
        1 => any::<bool>().prop_map(|v| format!("body_ramp = {v}")),
        1 => num(0.0, 1.2).prop_map(|v| format!("surface_blend = {v}")),
        1 => hostile().prop_map(|v| format!("surface_blend = {v}")),
        2 => any::<bool>().prop_map(|v| format!("density_correction = {v}")),
        1 => num(1e-12, 0.5).prop_map(|v| format!("density_tolerance = {v}")),
        1 => hostile().prop_map(|v| format!("density_tolerance = {v}")),
        1 => num(-0.5, 3.0).prop_map(|v| format!("density_gain = {v}")),
        1 => hostile().prop_map(|v| format!("density_gain = {v}")),
        1 => (0u64..6).prop_map(|v| format!("density_passes = {v}")),
        1 => num(-0.2, 1.2).prop_map(|v| format!("density_face_ramp = {v}")),
        1 => hostile().prop_map(|v| format!("density_face_ramp = {v}")),
        2 => any::<bool>().prop_map(|v| format!("sparse_cells = {v}")),
        2 => num(0.0, 0.6).prop_map(|v| format!("sparse_depth = {v}")),
        1 => hostile().prop_map(|v| format!("sparse_depth = {v}")),
        1 => num(0.0, 0.7).prop_map(|v| format!("surface_softness = {v}")),
        1 => hostile().prop_map(|v| format!("surface_softness = {v}")),
        2 => num(0.0, 0.8).prop_map(|v| format!("close_pockets = {v}")),
        1 => hostile().prop_map(|v| format!("close_pockets = {v}")),
        1 => num(0.0, 10.0).prop_map(|v| format!("volume_control = {v}")),
        2 => (0u64..80).prop_map(|v| format!("particle_substeps = {v}")),
        2 => (0u64..40).prop_map(|v| format!("narrow_band = {v}")),
        2 => any::<bool>().prop_map(|v| format!("freeze_surface = {v}")),
        2 => prop_oneof![Just("monolithic"), Just("weak")].prop_map(|v| format!("coupling = \"{v}\"")),
        2 => num(0.0, 4.0).prop_map(|v| format!("cfl = {v}")),
        1 => num(0.0, 100.0).prop_map(|v| format!("memory_limit_gb = {v}")),
        1 => hostile().prop_map(|v| format!("tolerance = {v}")),
        1 => Just("no_such_key = 1".to_string()),
    ];
    let solver = prop::collection::vec(solver_entry, 0..3);
    let contact = prop_oneof![
        3 => Just(String::new()),
        1 => (num(0.0, 1.0), num(0.0, 1.0)).prop_map(|(f, r)| {
            format!("[contact]\nenabled = true\nfriction = {f}\nrestitution = {r}\n")
        }),
    ];
    let gravity = prop_oneof![4 => Just("[0.0, -9.81, 0.0]".to_string()), 1 => vec3(-20.0, 20.0)];
    let density = prop_oneof![6 => Just("1000.0".to_string()), 1 => num(1.0, 5000.0)];
    (
        size,
        dx,
        dt,
        liquid,
        prop::collection::vec(body, 0..3),
        prop::option::of(near_body),
        solver,
        contact,
        gravity,
        density,
    )
        .prop_map(|(size, dx, dt, liquid, bodies, near, solver, contact, gravity, density)| {
            let mut s = format!(
                "name = \"fuzz\"\n[domain]\nsize = {size}\ndx = {dx}\n[time]\ndt = {dt}\nsteps = 3\n\
                 [fluid]\ndensity = {density}\ngravity = {gravity}\n[[liquid]]\n{liquid}\n"
            );
            for b in bodies.iter().chain(near.iter()).chain(near.iter()) {
                s.push_str(b);
            }
            s.push_str(&contact);
            if !solver.is_empty() {
                s.push_str("[solver]\n");
                let mut seen = std::collections::HashSet::new();
                for entry in solver {
                    // A key twice is a TOML error, and not what this test is after.
                    if seen.insert(entry.split(' ').next().unwrap_or("").to_string()) {
                        s.push_str(&entry);
                        s.push('\n');
                    }
                }
            }
            s.push_str("[output]\nparticles = false\n");
            s
        })
}

/// How far the cases got: parse errors, build errors, step errors, clean runs.
static REACHED: [std::sync::atomic::AtomicUsize; 4] =
    [const { std::sync::atomic::AtomicUsize::new(0) }; 4];

/// Parses, builds and steps a scene; an error is fine, a panic or a multi-line message is
/// not.
fn check(text: &str) -> Result<(), String> {
    use std::sync::atomic::Ordering::Relaxed;
    let run = std::panic::catch_unwind(|| -> diffluid::Result<()> {
        let stage = |k: usize| REACHED[k].fetch_add(1, Relaxed);
        let scene = Scene::from_toml(text, "<fuzz>").inspect_err(|_| {
            stage(0);
        })?;
        let mut sim = scene.build().inspect_err(|_| {
            stage(1);
        })?;
        for _ in 0..scene.time.steps {
            sim.step().inspect_err(|_| {
                stage(2);
            })?;
        }
        stage(3);
        Ok(())
    });
    match run {
        Err(_) => Err(format!("panicked on:\n{text}")),
        Ok(Err(e)) if e.to_string().contains('\n') => {
            Err(format!("a multi-line error ({e}) on:\n{text}"))
        }
        Ok(_) => Ok(()),
    }
}

#[test]
fn generated_scenes_run_or_give_one_error_line() {
    let cases = std::env::var("PROPTEST_CASES").ok().and_then(|s| s.parse().ok()).unwrap_or(300);
    // The panics are caught: keep their messages off the test output.
    std::panic::set_hook(Box::new(|_| {}));
    let mut runner =
        TestRunner::new(Config { cases, failure_persistence: None, ..Config::default() });
    let result = runner.run(&scene(), |text| {
        check(&text).map_err(TestCaseError::fail)?;
        Ok(())
    });
    let _ = std::panic::take_hook();
    if let Err(e) = result {
        panic!("{e}");
    }
    use std::sync::atomic::Ordering::Relaxed;
    let n = REACHED.each_ref().map(|a| a.load(Relaxed));
    eprintln!(
        "{cases} cases: {} refused when read, {} when built, {} failed in a step, {} ran",
        n[0], n[1], n[2], n[3]
    );
    // Enough cases get past the reading, or the generator tests nothing but the parser.
    assert!(n[1] + n[2] + n[3] >= cases as usize / 10, "{n:?}");
    assert!(n[3] > 0, "no generated scene ran: {n:?}");
}

/// A name as a TOML basic string.
#[cfg(feature = "csv")] // the run recorder
fn toml_str(s: &str) -> String {
    let mut out = String::from("\"");
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if c.is_control() => out.push_str(&format!("\\U{:08X}", c as u32)),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

/// A hostile name: mostly file-like, often with what would leave a folder or break XML.
#[cfg(feature = "csv")] // the run recorder
fn name(sandbox: &str) -> impl Strategy<Value = String> {
    let escapes = vec![
        "..".to_string(),
        "../x".into(),
        "../../../x".into(),
        "a/b".into(),
        "a\\b".into(),
        "./a".into(),
        ".hidden".into(),
        "a&b<c>\"d'".into(),
        "nul\u{0}x".into(),
        "line\nbreak".into(),
        "C:x".into(),
        String::new(),
        format!("{sandbox}/abs/x"),
        format!("{sandbox}/abs"),
    ];
    prop_oneof![
        6 => "[A-Za-z0-9_][A-Za-z0-9_.-]{0,12}",
        3 => prop::sample::select(escapes),
        2 => "[A-Za-z0-9_./\\\\&<>\"' \\x00-\\x1f-]{0,12}",
        2 => any::<String>().prop_map(|s| s.chars().take(20).collect()),
        1 => "[a-zé]{60,70}",
        1 => ("[a-z]{1,4}", "[a-z]{1,4}").prop_map(|(a, b)| format!("{a}/../../{b}")),
    ]
}

/// Every file under `dir`.
#[cfg(feature = "csv")] // the run recorder
fn files_under(dir: &std::path::Path, out: &mut Vec<std::path::PathBuf>) {
    for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let p = e.path();
        if p.is_dir() {
            files_under(&p, out);
        } else {
            out.push(p);
        }
    }
}

/// How the name cases ended: refused when read, refused by the recorder, recorded.
#[cfg(feature = "csv")] // the run recorder
static NAMED: [std::sync::atomic::AtomicUsize; 3] =
    [const { std::sync::atomic::AtomicUsize::new(0) }; 3];

/// Reads a scene with these names and records a step of it into `work/out/<scene name>`
/// under `case`; a panic, a message of more than one line or a file outside `work/out` fails.
#[cfg(feature = "csv")] // the run recorder
fn record_named(case: &std::path::Path, scene_name: &str, bodies: &[String]) -> Result<(), String> {
    use diffluid::io::recorder::{Frames, RunFolder, RunRecorder};
    use std::sync::atomic::Ordering::Relaxed;
    let mut text = format!(
        "name = {}\n[domain]\nsize = [0.4, 0.4, 0.4]\ndx = 0.1\n[time]\ndt = 0.01\nsteps = 1\n\
         [fluid]\ndensity = 1000.0\ngravity = [0.0, -9.81, 0.0]\n[[liquid]]\n\
         shape = {{ kind = \"box\", min = [0.0, 0.0, 0.0], max = [0.4, 0.2, 0.4] }}\n",
        toml_str(scene_name)
    );
    for (i, b) in bodies.iter().enumerate() {
        text.push_str(&format!(
            "[[body]]\nname = {}\nshape = {{ kind = \"ball\", radius = 0.04 }}\ndensity = 500.0\n\
             position = [{}, 0.3, 0.2]\n",
            toml_str(b),
            0.1 + 0.2 * i as f64
        ));
    }
    std::fs::remove_dir_all(case).ok();
    let work = case.join("work");
    std::fs::create_dir_all(&work).unwrap();
    let run = std::panic::catch_unwind(|| -> diffluid::Result<()> {
        let scene = Scene::from_toml(&text, "<fuzz>").inspect_err(|_| {
            NAMED[0].fetch_add(1, Relaxed);
        })?;
        let mut sim = scene.build()?;
        // Where `diffluid run` writes without --out.
        let out = work.join("out").join(&scene.name);
        let frames = Frames { every: 1, particles: true, vtk: true, surface: None };
        let mut rec = RunRecorder::new(RunFolder::claim(&out, false)?, &scene.name, frames, &sim)
            .inspect_err(|_| {
            NAMED[1].fetch_add(1, Relaxed);
        })?;
        let report = sim.step()?;
        rec.record(&sim, report)?;
        rec.finish(None)?;
        NAMED[2].fetch_add(1, Relaxed);
        Ok(())
    });
    let root = case.parent().unwrap();
    let mut written = Vec::new();
    files_under(root, &mut written);
    if let Some(outside) = written.iter().find(|p| !p.starts_with(work.join("out"))) {
        return Err(format!("{} written outside the output folder by:\n{text}", outside.display()));
    }
    match run {
        Err(_) => Err(format!("panicked on:\n{text}")),
        Ok(Err(e)) if e.to_string().contains('\n') => {
            Err(format!("a multi-line error ({e}) on:\n{text}"))
        }
        Ok(_) => Ok(()),
    }
}

#[cfg(feature = "csv")] // the run recorder
#[test]
fn generated_names_never_write_outside_the_output_folder() {
    let cases = std::env::var("PROPTEST_CASES").ok().and_then(|s| s.parse().ok()).unwrap_or(100);
    let sandbox = std::env::temp_dir().join(format!("diffluid-fuzz-names-{}", std::process::id()));
    std::fs::create_dir_all(&sandbox).unwrap();
    let root = sandbox.to_str().unwrap().to_string();
    let case = sandbox.join("case");
    std::panic::set_hook(Box::new(|_| {}));
    let mut runner =
        TestRunner::new(Config { cases, failure_persistence: None, ..Config::default() });
    let names = (name(&root), prop::collection::vec(name(&root), 0..3));
    let result = runner.run(&names, |(scene_name, bodies)| {
        record_named(&case, &scene_name, &bodies).map_err(TestCaseError::fail)?;
        Ok(())
    });
    let _ = std::panic::take_hook();
    std::fs::remove_dir_all(&sandbox).ok();
    if let Err(e) = result {
        panic!("{e}");
    }
    use std::sync::atomic::Ordering::Relaxed;
    let n = NAMED.each_ref().map(|a| a.load(Relaxed));
    eprintln!(
        "{cases} name cases: {} refused when read, {} by the recorder, {} recorded",
        n[0], n[1], n[2]
    );
    assert!(n[2] > 0 && n[0] > 0, "{n:?}");
}
