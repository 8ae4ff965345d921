//! `diffluid bench --quick`: every table and chart is written, and the stability map says
//! what the physics says: the monolithic coupling is stable for every density ratio at
//! CFL ≤ 1, and the weak (partitioned) coupling blows up for the lightest body (ratio 0.01:
//! its added mass is fifty times its own). The smoothness study's live-surface adjoint
//! agrees with central differences on the surge scene's first steps.
//!
//! The energy audit checks that a rest state stays at rest: still water, and a ball
//! floating at its Archimedes height in it, are equilibria of the continuous problem, so
//! nothing may set the liquid moving (its kinetic energy stays at round-off) and, with no
//! forcing, the total mechanical energy (kinetic plus potential, liquid and ball) may fall
//! through dissipation but never rise above where it started.

use crate::common::EXE;
use std::process::Command;

#[test]
fn quick_bench_writes_its_tables_and_charts_and_maps_stability() {
    let out = std::env::temp_dir().join(format!("diffluid-bench-{}", std::process::id()));
    let status =
        Command::new(EXE).args(["bench", "--quick", "--out"]).arg(&out).status().expect("runs");
    assert!(status.success());
    for f in ["accuracy", "stability", "thin", "cost", "energy"] {
        for ext in ["csv", "png"] {
            let p = out.join(format!("{f}.{ext}"));
            assert!(std::fs::metadata(&p).map(|m| m.len() > 100).unwrap_or(false), "{p:?}");
        }
    }
    // The moving thin bodies: the disk's chart beside the stored figures from before the
    // seal, and in the table a quarter-cell disk falls within 30% of potential flow (issue
    // 36's target; measured 0.785) where it fell 4.5 times too fast before.
    for f in ["moving_thin.csv", "moving_thin.png", "moving_thin_disk.png"] {
        let p = out.join(f);
        assert!(std::fs::metadata(&p).map(|m| m.len() > 100).unwrap_or(false), "{p:?}");
    }
    let table = std::fs::read_to_string(out.join("moving_thin.csv")).unwrap();
    let header: Vec<&str> = table.lines().next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let quarter: Vec<&str> = table
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect::<Vec<_>>())
        .find(|r| r[0] == "0.25")
        .unwrap();
    let now: f64 = quarter[col("fall_over_potential")].parse().unwrap();
    let before: f64 = quarter[col("fall_over_potential_before")].parse().unwrap();
    assert!((now - 1.0).abs() < 0.3, "a quarter-cell disk falls at {now} of potential flow");
    assert!(before > 4.0, "the stored figure from before the seal: {before}");
    let table = std::fs::read_to_string(out.join("stability.csv")).unwrap();
    let rows: Vec<Vec<&str>> = table.lines().skip(1).map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 12, "2 couplings × 3 ratios × 2 CFL numbers");
    for r in &rows {
        let (coupling, ratio, stable) = (r[0], r[1].parse::<f64>().unwrap(), r[3] == "true");
        if coupling == "monolithic" {
            assert!(stable, "monolithic unstable at ratio {ratio}, CFL {}", r[2]);
        } else if ratio == 0.01 {
            assert!(!stable, "weak coupling stable for the lightest body at CFL {}", r[2]);
        }
    }
    for f in [
        "smoothness.csv",
        "smoothness_surge_ball_spread.png",
        "smoothness_surge_ball_adjoint.png",
        "smoothness_gradient.png",
    ] {
        let p = out.join(f);
        assert!(std::fs::metadata(&p).map(|m| m.len() > 100).unwrap_or(false), "{p:?}");
    }
    // The surge scene over 4 and 8 steps is smooth at ε ≤ 1e-4: the live-surface adjoint is
    // its derivative (measured 4e-10 and 8e-10), and cells do change kind every step.
    let table = std::fs::read_to_string(out.join("smoothness.csv")).unwrap();
    let header: Vec<&str> = table.lines().next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    for l in table.lines().skip(1) {
        let r: Vec<&str> = l.split(',').collect();
        let err: f64 = r[col("adjoint_error")].parse().unwrap();
        let kinds: f64 = r[col("kind_changes_per_step")].parse().unwrap();
        assert!(err < 1e-6, "horizon {}: adjoint error {err}", r[col("horizon")]);
        assert!(kinds > 0.0, "no kind changes recorded");
    }
    let _ = std::fs::remove_dir_all(&out);
}

/// `diffluid bench --only scale --quick`: the scale study's table and charts, for the two
/// smallest grids, with memory growing with the cells (8× the cells: measured 4.2× the memory
/// of a forward run; its time, 4.2× when the machine is idle, is the study's to report).
#[test]
fn quick_scale_study_writes_its_table_and_charts() {
    let out = std::env::temp_dir().join(format!("diffluid-scale-{}", std::process::id()));
    let status = Command::new(EXE)
        .args(["bench", "--only", "scale", "--quick", "--out"])
        .arg(&out)
        .status()
        .expect("runs");
    assert!(status.success());
    for f in ["scale.csv", "scale_time.png", "scale_memory.png"] {
        let p = out.join(f);
        assert!(std::fs::metadata(&p).map(|m| m.len() > 100).unwrap_or(false), "{p:?}");
    }
    let table = std::fs::read_to_string(out.join("scale.csv")).unwrap();
    let header: Vec<&str> = table.lines().next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let rows: Vec<Vec<f64>> = table
        .lines()
        .skip(1)
        .map(|l| l.split(',').skip(1).map(|x| x.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 2);
    let at = |r: usize, name: &str| rows[r][col(name) - 1];
    assert_eq!((at(0, "cells"), at(1, "cells")), (16384.0, 131072.0));
    // Memory only: a time per step is a benchmark's to measure, not a test's to assert (a
    // loaded machine made the smaller grid as slow as the larger one).
    for name in ["forward_peak_mb", "gradient_peak_mb"] {
        assert!(at(1, name) > 2.0 * at(0, name), "{name}: {} then {}", at(0, name), at(1, name));
    }
    let _ = std::fs::remove_dir_all(&out);
}

/// `diffluid bench --only smoothed --quick`: the smoothed gradient on the surge at 6 steps
/// (σ_v 1e-2, 4 runs) beside the exact adjoint, for x₀ and v_x. Over 6 steps the map is
/// smooth at that scale, so the estimate lies within 10% plus four standard errors of the
/// exact gradient (a sign or frame error would put it far outside).
#[test]
fn quick_smoothed_gradient_study_agrees_where_the_map_is_smooth() {
    let out = std::env::temp_dir().join(format!("diffluid-smoothed-{}", std::process::id()));
    let status = Command::new(EXE)
        .args(["bench", "--only", "smoothed", "--quick", "--out"])
        .arg(&out)
        .status()
        .expect("runs");
    assert!(status.success());
    let table = std::fs::read_to_string(out.join("smoothed_gradient.csv")).unwrap();
    let header: Vec<&str> = table.lines().next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let rows: Vec<Vec<&str>> = table.lines().skip(1).map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 2, "x[0] and v[0] at one horizon and one σ");
    for r in &rows {
        let num = |name: &str| r[col(name)].parse::<f64>().unwrap();
        let (exact, smoothed, se) = (num("exact"), num("smoothed"), num("standard_error"));
        eprintln!("{}: exact {exact:+.5e} smoothed {smoothed:+.5e} ± {se:.1e}", r[col("param")]);
        assert!(exact.is_finite() && se.is_finite() && se >= 0.0);
        assert!(
            (smoothed - exact).abs() <= 0.1 * exact.abs() + 4.0 * se,
            "{}: {smoothed} ± {se} against {exact}",
            r[col("param")]
        );
    }
    let _ = std::fs::remove_dir_all(&out);
}

/// The quick energy audit (0.5 s of each scene): still water and the ball floating at rest
/// stay still, their liquid's kinetic energy under 1e-9 J (measured about 1e-17 J) and
/// their total energy never more than 1e-6 J above its start (measured 1e-11 J). The
/// dropped ball and the sloshing tank are only run here: every step leaves a finite row.
#[test]
fn quick_energy_audit_keeps_rest_states_at_rest() {
    use diffluid::experiments::bench::{energy, ENERGY_SCENES};
    let rows = energy(true).unwrap();
    for name in ENERGY_SCENES {
        let scene: Vec<_> = rows.iter().filter(|r| r.scene == name).collect();
        assert_eq!(scene.len(), 51, "{name}: the initial state and 50 steps");
        for (n, r) in scene.iter().enumerate() {
            assert_eq!(r.step, n, "{name}");
            let parts = [r.liquid_kinetic, r.liquid_potential, r.body_kinetic, r.body_potential];
            assert!(parts.iter().chain([&r.total_change]).all(|x| x.is_finite()), "{name} {n}");
        }
    }
    for name in ["still_water", "ball_at_rest"] {
        let scene = rows.iter().filter(|r| r.scene == name);
        let kinetic = scene.clone().map(|r| r.liquid_kinetic).fold(0.0, f64::max);
        let gain = scene.map(|r| r.total_change).fold(0.0, f64::max);
        eprintln!("{name}: liquid kinetic energy at most {kinetic:.3e} J, gain {gain:.3e} J");
        assert!(kinetic < 1e-9, "{name}: the liquid gained {kinetic:e} J of kinetic energy");
        assert!(gain < 1e-6, "{name}: the total energy rose {gain:e} J above its start");
    }
}
