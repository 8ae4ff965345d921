//! `diffluid bench`: each study ([`Study`]) run, and its CSV table, charts and summary lines
//! written.

use crate::error::Result;
use crate::experiments::bench;
use crate::io::output::write_csv;
use crate::io::plot::{self, Series};
use std::path::Path;

/// One study of `diffluid bench` (see [`mod@bench`]): [`bench::accuracy`],
/// [`bench::stability`], [`bench::thin_plates`], [`bench::cost`], [`bench::energy`],
/// [`bench::smoothness`], [`bench::smoothed_gradient`] and [`bench::scale`]. (The variants' own docs are the CLI's help,
/// so they name no item.)
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum Study {
    /// Error against wall time.
    Accuracy,
    /// The stability map of the monolithic and the weak coupling.
    Stability,
    /// Thin plates: static leakage and hydrostatics, and moving thin bodies (a falling
    /// disk against potential flow, a paddle pushed through the water).
    Thin,
    /// Time per step against liquid cells.
    Cost,
    /// The mechanical energy of still water, a floating ball at rest, a dropped ball and a
    /// sloshing tank, step by step.
    Energy,
    /// Smoothness over long horizons.
    Smoothness,
    /// The smoothed gradient's bias and noise against the exact one on the surge, from the
    /// runs' gradients and from their losses alone: run only when asked for (`--only
    /// smoothed`; 64 gradients and 64 forward runs of up to 50 steps, about 90 s).
    Smoothed,
    /// Time per step and peak memory against grid size up to 8.4M cells: run only when
    /// asked for (`--only scale`; it takes about a minute and 4 GB).
    Scale,
    /// A game loop's frame time (`advance(1/60)`) against grid size, on one thread and two:
    /// run only when asked for (`--only realtime`; about two minutes).
    Realtime,
}

/// The studies of `diffluid bench` (all six but the scale study, or `only` one), run and written into `out` as
/// CSV tables and PNG charts; `progress` hears each study's name as it starts. Returns a few
/// lines of summary.
pub fn write_bench(
    out: &Path,
    quick: bool,
    only: Option<Study>,
    mut progress: impl FnMut(&str),
) -> Result<Vec<String>> {
    let at = |name: &str| out.join(name);
    let runs = |study: Study| only.is_none_or(|o| o == study);
    let mut lines = Vec::new();
    if runs(Study::Accuracy) {
        write_accuracy(out, quick, &mut progress)?;
    }
    if runs(Study::Stability) {
        lines.extend(write_stability(out, quick, &mut progress)?);
    }
    if runs(Study::Thin) {
        write_thin(out, quick, &mut progress)?;
    }
    if runs(Study::Cost) {
        lines.extend(write_cost(out, quick, &mut progress)?);
    }
    if runs(Study::Energy) {
        lines.extend(write_energy(out, quick, &mut progress)?);
    }
    if only == Some(Study::Scale) {
        lines.extend(write_scale(out, quick, &mut progress)?);
    }
    if only == Some(Study::Realtime) {
        lines.extend(write_realtime(out, quick, &mut progress)?);
    }
    if only == Some(Study::Smoothed) {
        progress("the smoothed gradient on the surge");
        let rows = bench::smoothed_gradient(quick)?;
        write_csv(&at("smoothed_gradient.csv"), &rows)?;
        for r in &rows {
            lines.push(format!(
                "{} steps, σ_v {:.0e}: {} exact {:+.4e} (fd 1e-4 {:+.4e}, 1e-6 {:+.4e}), smoothed from the {} {:+.4e} ± {:.1e}",
                r.horizon, r.sigma, r.param, r.exact, r.fd_1e4, r.fd_1e6, r.estimator, r.smoothed, r.standard_error
            ));
        }
    }
    if runs(Study::Smoothness) {
        progress("smoothness over long horizons");
        let sm = bench::smoothness(quick)?;
        write_csv(&at("smoothness.csv"), &sm)?;
        smoothness_charts(out, &sm)?;
    }
    Ok(lines)
}

fn write_accuracy(out: &Path, quick: bool, progress: &mut impl FnMut(&str)) -> Result<()> {
    let at = |name: &str| out.join(name);
    progress("accuracy against time");
    let acc = bench::accuracy(quick)?;
    write_csv(&at("accuracy.csv"), &acc)?;
    let s = series(acc.iter().map(|r| (r.quantity.clone(), (r.seconds, r.error))));
    plot::line_chart(
        &at("accuracy.png"),
        "error against wall time",
        ("wall time of the run, s", "relative error"),
        (true, true),
        &s,
    )
}

/// The stability map, and a line per coupling saying where it is stable.
fn write_stability(
    out: &Path,
    quick: bool,
    progress: &mut impl FnMut(&str),
) -> Result<Vec<String>> {
    let at = |name: &str| out.join(name);
    progress("stability map");
    let st = bench::stability(quick)?;
    write_csv(&at("stability.csv"), &st)?;
    let panels: Vec<plot::StabilityPanel> = ["monolithic", "weak"]
        .iter()
        .map(|c| {
            let cells = st
                .iter()
                .filter(|r| r.coupling == *c)
                .map(|r| (r.density_ratio, r.cfl, r.stable))
                .collect();
            (c.to_string(), cells)
        })
        .collect();
    plot::stability_chart(&at("stability.png"), &panels)?;
    let mut lines = Vec::new();
    let lightest = st.iter().map(|r| r.density_ratio).fold(f64::INFINITY, f64::min);
    for c in ["monolithic", "weak"] {
        let rows: Vec<_> = st.iter().filter(|r| r.coupling == c).collect();
        let stable = rows.iter().filter(|r| r.stable).count();
        let light = rows.iter().filter(|r| r.density_ratio == lightest && r.stable).count();
        lines.push(format!(
            "{c}: stable in {stable} of {} cells ({light} at density ratio {lightest})",
            rows.len()
        ));
    }
    Ok(lines)
}

fn write_thin(out: &Path, quick: bool, progress: &mut impl FnMut(&str)) -> Result<()> {
    let at = |name: &str| out.join(name);
    progress("thin plates");
    let thin = bench::thin_plates(quick)?;
    write_csv(&at("thin.csv"), &thin)?;
    // Log axis: |value|, floored at 1e-7 (a sealed plate leaks nothing; the particle count
    // behind it can come out a little negative, which thin.csv keeps).
    let floor = |v: f64| v.abs().max(1e-7);
    let s: Vec<Series> = vec![
        (
            "leakage, on a face plane".into(),
            thin.iter().map(|r| (r.thickness_cells, floor(r.leakage))).collect(),
        ),
        (
            "leakage, 0.3 cells off it".into(),
            thin.iter().map(|r| (r.thickness_cells, floor(r.leakage_off_plane))).collect(),
        ),
        (
            "torque error".into(),
            thin.iter().map(|r| (r.thickness_cells, floor(r.torque_error))).collect(),
        ),
        (
            "force error".into(),
            thin.iter().map(|r| (r.thickness_cells, floor(r.force_error))).collect(),
        ),
    ];
    plot::line_chart(
        &at("thin.png"),
        "thin plates (|value|, floored at 1e-7)",
        ("plate thickness, cells", "relative error"),
        (false, true),
        &s,
    )?;
    progress("moving thin bodies");
    let moving = bench::moving_thin(quick)?;
    write_csv(&at("moving_thin.csv"), &moving)?;
    let line = |f: fn(&bench::MovingThinRow) -> f64| -> Vec<(f64, f64)> {
        moving.iter().map(|r| (r.thickness_cells, f(r))).collect()
    };
    // The disk on a log axis: before the seal it fell up to nine times too fast.
    let s = vec![
        ("now".into(), line(|r| r.fall_over_potential)),
        ("before the seal (stored, assets/bench)".into(), bench::disk_fall_before()),
        ("potential flow".into(), vec![(0.125, 1.0), (2.0, 1.0)]),
    ];
    plot::line_chart(
        &at("moving_thin_disk.png"),
        "a thin disk falling flat: acceleration / potential flow",
        ("disk thickness, cells", "ratio"),
        (true, true),
        &s,
    )?;
    let s = vec![
        ("paddle: impulse / a two-cell paddle's".into(), line(|r| r.momentum_over_thick)),
        ("paddle: leakage".into(), line(|r| r.leakage)),
    ];
    plot::line_chart(
        &at("moving_thin.png"),
        "a thin paddle pushed through the water",
        ("paddle thickness, cells", "ratio"),
        (false, false),
        &s,
    )
}

/// The scale study: its table, a chart of time per step and one of peak memory against
/// cells, and a line per size.
fn write_scale(out: &Path, quick: bool, progress: &mut impl FnMut(&str)) -> Result<Vec<String>> {
    let at = |name: &str| out.join(name);
    progress("time and memory against grid size");
    let rows = bench::scale(quick)?;
    write_csv(&at("scale.csv"), &rows)?;
    let pick = |f: fn(&bench::ScaleRow) -> f64, label: &str| {
        (label.to_string(), rows.iter().map(|r| (r.cells as f64, f(r))).collect::<Vec<_>>())
    };
    let time = vec![
        pick(|r| r.forward_seconds_per_step, "forward"),
        pick(|r| r.gradient_seconds_per_step, "gradient (surface held fixed)"),
    ];
    plot::line_chart(
        &at("scale_time.png"),
        "time per step against grid cells (large_tank)",
        ("grid cells", "s per step (median)"),
        (true, true),
        &time,
    )?;
    let memory = vec![
        pick(|r| r.forward_peak_mb, "forward"),
        pick(|r| r.gradient_peak_mb, "gradient (surface held fixed)"),
    ];
    plot::line_chart(
        &at("scale_memory.png"),
        "peak memory against grid cells (large_tank)",
        ("grid cells", "peak resident memory, MB"),
        (true, true),
        &memory,
    )?;
    Ok(rows
        .iter()
        .map(|r| {
            format!(
                "{}: {:.3} s a step, {:.0} MB; gradient {:.3} s a step, {:.0} MB",
                r.n,
                r.forward_seconds_per_step,
                r.forward_peak_mb,
                r.gradient_seconds_per_step,
                r.gradient_peak_mb
            )
        })
        .collect())
}

/// The real-time study: its table, a chart of the frame time against cells beside the
/// frame budgets of 30 and 60 frames a second, and a line per size and thread count.
fn write_realtime(out: &Path, quick: bool, progress: &mut impl FnMut(&str)) -> Result<Vec<String>> {
    let at = |name: &str| out.join(name);
    progress("a game loop's frame time against grid size");
    let rows = bench::realtime(quick)?;
    write_csv(&at("realtime.csv"), &rows)?;
    let mode = |m: &str| {
        let points = rows.iter().filter(|r| r.mode == m);
        (m.to_string(), points.map(|r| (r.cells as f64, 1e3 * r.frame_seconds)).collect::<Vec<_>>())
    };
    let (lo, hi) = (rows[0].cells as f64, rows[rows.len() - 1].cells as f64);
    let budget = |fps: f64| (format!("{fps:.0} frames/s"), vec![(lo, 1e3 / fps), (hi, 1e3 / fps)]);
    plot::line_chart(
        &at("realtime.png"),
        "a pool with three floating bodies, advance(1/60) a frame",
        ("grid cells", "ms a frame (median)"),
        (true, true),
        &[
            mode("1 thread"),
            mode("2 threads"),
            mode("2 threads, parallel"),
            budget(30.0),
            budget(60.0),
        ],
    )?;
    Ok(rows
        .iter()
        .map(|r| {
            format!(
                "{} ({}): {:.1} ms a frame, {:.1} frames/s, {:.2} steps a frame",
                r.n,
                r.mode,
                1e3 * r.frame_seconds,
                r.frames_per_second,
                r.steps_per_frame
            )
        })
        .collect())
}

/// The cost study, and a line saying what doubling the air costs.
fn write_cost(out: &Path, quick: bool, progress: &mut impl FnMut(&str)) -> Result<Vec<String>> {
    let at = |name: &str| out.join(name);
    progress("cost against liquid cells");
    let cost = bench::cost(quick)?;
    write_csv(&at("cost.csv"), &cost)?;
    let s = series(cost.iter().map(|r| {
        let label = if r.series == "air" { "liquid fixed, air grown" } else { "liquid grown" };
        (label.to_string(), (r.liquid_cells as f64, r.seconds_per_step * 1e3))
    }));
    plot::line_chart(
        &at("cost.png"),
        "time per step against liquid cells",
        ("liquid cells", "ms per step (median)"),
        (false, false),
        &s,
    )?;

    let mut lines = Vec::new();
    let air: Vec<&bench::CostRow> = cost.iter().filter(|r| r.series == "air").collect();
    if air.len() >= 2 {
        lines.push(format!(
            "doubling the air above the pool: {:+.1}% time per step ({} -> {} cells)",
            100.0 * (air[1].seconds_per_step / air[0].seconds_per_step - 1.0),
            air[0].cells,
            air[1].cells
        ));
    }
    Ok(lines)
}

/// The energy audit: `energy.csv`, `energy.png`, and a line per scene with the largest gain
/// of the total energy over its start, the change at the end, and the largest kinetic energy
/// of the liquid.
fn write_energy(out: &Path, quick: bool, progress: &mut impl FnMut(&str)) -> Result<Vec<String>> {
    let at = |name: &str| out.join(name);
    progress("energy audit");
    let rows = bench::energy(quick)?;
    write_csv(&at("energy.csv"), &rows)?;
    let mut curves = Vec::new();
    let mut lines = Vec::new();
    for name in bench::ENERGY_SCENES {
        let scene: Vec<&bench::EnergyRow> = rows.iter().filter(|r| r.scene == name).collect();
        let Some(last) = scene.last() else { continue };
        let pick = |f: fn(&bench::EnergyRow) -> f64| -> Vec<(f64, f64)> {
            scene.iter().map(|r| (r.time, f(r))).collect()
        };
        curves.push(plot::EnergyCurves {
            label: name.replace('_', " "),
            change: pick(|r| r.total_change),
            liquid_kinetic: pick(|r| r.liquid_kinetic),
            body_kinetic: pick(|r| r.body_kinetic),
        });
        let gain = scene.iter().map(|r| r.total_change).fold(0.0, f64::max);
        let kinetic = scene.iter().map(|r| r.liquid_kinetic).fold(0.0, f64::max);
        lines.push(format!(
            "{name}: total energy at most {gain:+.3e} J over its start, {:+.3e} J at {:.2} s; \
             liquid kinetic energy at most {kinetic:.3e} J",
            last.total_change, last.time
        ));
    }
    plot::energy_chart(&at("energy.png"), &curves)?;
    Ok(lines)
}

/// The smoothness study's charts against the horizon: per scene, the spread of the central
/// differences over ε (`smoothness_<scene>_spread.png`) and the adjoint's error against the
/// smallest ε (`smoothness_<scene>_adjoint.png`), per settings and parameter; and the
/// gradient norm |∂L/∂v₀| per scene and settings (`smoothness_gradient.png`).
pub fn smoothness_charts(out: &Path, rows: &[bench::SmoothnessRow]) -> Result<()> {
    let h = |r: &bench::SmoothnessRow| r.horizon as f64;
    let mut scenes: Vec<&str> = Vec::new();
    for r in rows {
        if !scenes.contains(&r.scene.as_str()) {
            scenes.push(&r.scene);
        }
    }
    for scene in scenes {
        let of = || rows.iter().filter(move |r| r.scene == scene);
        let label = |r: &bench::SmoothnessRow| format!("{} {}", r.settings, r.param);
        let spread = series(of().map(|r| (label(r), (h(r), r.spread.max(1e-12)))));
        plot::line_chart(
            &out.join(format!("smoothness_{scene}_spread.png")),
            &format!("{scene}: |fd(1e-4) - fd(1e-6)| / |fd(1e-6)|"),
            ("horizon, steps", "spread of the central differences"),
            (false, true),
            &spread,
        )?;
        let adjoint = series(of().map(|r| (label(r), (h(r), r.adjoint_error.max(1e-12)))));
        plot::line_chart(
            &out.join(format!("smoothness_{scene}_adjoint.png")),
            &format!("{scene}: live-surface adjoint against fd(1e-6)"),
            ("horizon, steps", "relative error (floored at 1e-12)"),
            (false, true),
            &adjoint,
        )?;
    }
    // One point per (scene, settings, horizon): every parameter's row holds the same norm.
    let first = |r: &bench::SmoothnessRow| {
        rows.iter().find(|q| q.scene == r.scene).is_some_and(|q| q.param == r.param)
    };
    let norm = series(
        rows.iter()
            .filter(|r| first(r))
            .map(|r| (format!("{} {}", r.scene, r.settings), (h(r), r.grad_norm_v.max(1e-12)))),
    );
    plot::line_chart(
        &out.join("smoothness_gradient.png"),
        "gradient norm |dL/dv0| against the horizon",
        ("horizon, steps", "|dL/dv0|"),
        (false, true),
        &norm,
    )
}

/// Points grouped into one series per label, in the order the labels first appear.
fn series(pairs: impl IntoIterator<Item = (String, (f64, f64))>) -> Vec<Series> {
    let mut out: Vec<Series> = Vec::new();
    for (label, p) in pairs {
        match out.iter_mut().find(|s| s.0 == label) {
            Some(s) => s.1.push(p),
            None => out.push((label, vec![p])),
        }
    }
    out
}
