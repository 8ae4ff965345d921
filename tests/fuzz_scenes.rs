//! Bad input in bulk: generated scene files (random keys and values, shapes, meshes, NaN,
//! infinities, huge and tiny numbers, empty tanks, overlapping bodies) must each give either
//! a clean run of a few steps or one error naming the problem: never a panic, and never a
//! message of more than one line.
//!
//! The cases run in process (parse, build, three steps), each on a small tank so none takes
//! long. CI runs `PROPTEST_CASES` cases (default 300); 10⁵ took a minute with 0 panics (75%
//! refused when read, 2% failed in a step, 23% ran:
//! `PROPTEST_CASES=100000 cargo test --release --test fuzz_scenes -- --nocapture`).

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
        2 => any::<bool>().prop_map(|v| format!("density_correction = {v}")),
        1 => num(1e-12, 0.5).prop_map(|v| format!("density_tolerance = {v}")),
        1 => hostile().prop_map(|v| format!("density_tolerance = {v}")),
        2 => any::<bool>().prop_map(|v| format!("sparse_cells = {v}")),
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
