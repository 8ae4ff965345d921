//! What `diffluid optimize` and `diffluid bench` write (features `csv` and `plots`; ParaView
//! frames with `vtk`): the tables, the JSON result and the pictures, so the command line only
//! parses arguments and prints.

use super::bench;
use super::optimize::{Optimization, Outcome};
use crate::error::{Error, Result};
use crate::geometry::body::BodyState;
use crate::io::liquid_mesh::{body_surfaces, liquid_surface};
use crate::io::output::{write_csv, write_json};
use crate::io::plot::{self, Frame, Series, Track};
use crate::io::render::{Picture, View};
use crate::math::Vec3;
use crate::world::Simulation;
use serde::Serialize;
use std::path::Path;

/// One row of `loss.csv`.
#[derive(Serialize)]
struct LossRow {
    epoch: usize,
    evaluations: usize,
    loss: f64,
    grad_norm: f64,
    vx: f64,
    vy: f64,
    vz: f64,
    wx: f64,
    wy: f64,
    wz: f64,
    x: f64,
    y: f64,
    z: f64,
    qw: f64,
    qx: f64,
    qy: f64,
    qz: f64,
}

/// `result.json`.
#[derive(Serialize)]
struct OptimizeResult<'a> {
    scene: &'a str,
    epochs: usize,
    initial_loss: f64,
    final_loss: f64,
    loss_reduction: f64,
    evaluations: usize,
    params: &'a BodyState,
    stopped: Option<&'a str>,
    converged: Option<&'a str>,
    wall_seconds: f64,
}

/// Writes an optimisation's outputs into `out`: `loss.csv`, `result.json`, `loss.png`,
/// `trajectory.png` and `optimized.gif`, and with `vtk` the optimised run's ParaView frames.
pub fn write_optimization(
    problem: &Optimization,
    outcome: &Outcome,
    out: &Path,
    wall_seconds: f64,
    vtk: bool,
) -> Result<()> {
    let rows: Vec<LossRow> = outcome
        .history
        .iter()
        .map(|r| {
            let p = &r.params;
            LossRow {
                epoch: r.epoch,
                evaluations: r.evaluations,
                loss: r.loss,
                grad_norm: r.grad_norm,
                vx: p.v.x,
                vy: p.v.y,
                vz: p.v.z,
                wx: p.w.x,
                wy: p.w.y,
                wz: p.w.z,
                x: p.x.x,
                y: p.x.y,
                z: p.x.z,
                qw: p.q.w,
                qx: p.q.x,
                qy: p.q.y,
                qz: p.q.z,
            }
        })
        .collect();
    write_csv(&out.join("loss.csv"), &rows)?;
    let initial_loss = outcome.history.first().map(|r| r.loss).unwrap_or(f64::NAN);
    write_json(
        &out.join("result.json"),
        &OptimizeResult {
            scene: &problem.scene.name,
            epochs: outcome.history.len(),
            initial_loss,
            final_loss: outcome.final_loss,
            loss_reduction: initial_loss / outcome.final_loss,
            evaluations: outcome.evaluations,
            params: &outcome.params,
            stopped: outcome.stopped.as_deref(),
            converged: outcome.converged.as_deref(),
            wall_seconds,
        },
    )?;
    pictures(problem, &problem.initial_params(), outcome, out)?;
    if vtk {
        vtk_frames(problem, &outcome.params, out)?;
    }
    Ok(())
}

#[cfg(feature = "vtk")]
fn vtk_frames(problem: &Optimization, params: &BodyState, out: &Path) -> Result<()> {
    let mut sim = problem.simulation(params);
    let mut frames = crate::io::vtk::VtkSeries::new(&out.join("vtk"), &problem.scene.name);
    frames.write_frame(&sim, 0)?;
    for n in 1..=problem.scene.time.steps {
        sim.step()?;
        frames.write_frame(&sim, n)?;
    }
    Ok(())
}

#[cfg(not(feature = "vtk"))]
fn vtk_frames(_: &Optimization, _: &BodyState, _: &Path) -> Result<()> {
    Err(crate::error::Error::InvalidSettings {
        key: "vtk".into(),
        message: "diffluid was built without the `vtk` feature".into(),
    })
}

/// A run's body path and animation frames (the last one is the final state).
type Recording = (Vec<Vec3>, Vec<Frame>);

/// The liquid's surface (at `samples` per cell) and the bodies' of `sim` now, captioned.
fn frame(sim: &Simulation, samples: usize, label: String) -> Frame {
    Frame { liquid: liquid_surface(sim, samples), bodies: body_surfaces(sim), label }
}

/// loss.png, trajectory.png (the body's path before and after, over the liquid's shaded
/// surface at the end of the optimised run) and optimized.gif (the optimised run).
fn pictures(
    problem: &Optimization,
    start: &BodyState,
    outcome: &Outcome,
    out: &Path,
) -> Result<()> {
    let loss: Vec<f64> = outcome.history.iter().map(|r| r.loss).collect();
    let norms: Vec<f64> = outcome.history.iter().map(|r| r.grad_norm).collect();
    if !loss.is_empty() {
        plot::loss_plot(&out.join("loss.png"), &loss, &norms)?;
    }
    let steps = problem.scene.time.steps;
    let body = problem.body;
    let name = &problem.scene.name;
    let record = |p: &BodyState, frames: bool| -> Result<Recording> {
        let mut sim = problem.simulation(p);
        // The pictures read the bodies and the particles, none of the reports' measures.
        sim.set_report_measures(false);
        let mut path = vec![sim.bodies()[body].x];
        let mut gif = Vec::new();
        let every = (steps / 25).max(1);
        for n in 0..=steps {
            if n > 0 {
                sim.step()?;
                path.push(sim.bodies()[body].x);
            }
            if frames && (n % every == 0 || n == steps) {
                let samples = problem.scene.output.surface_samples;
                gif.push(frame(&sim, samples, format!("{name} optimised, step {n}")));
            }
        }
        Ok((path, gif))
    };
    let (before, _) = record(start, false)?;
    let (after, gif) = record(&outcome.params, true)?;
    let target = problem.loss.position.map(|(t, _)| t);
    let domain = problem.initial.grid().size();
    let last = gif.last().expect("the final frame");
    let picture = Picture { domain, liquid: &last.liquid, bodies: &last.bodies };
    plot::trajectory_plot(
        &out.join("trajectory.png"),
        domain,
        &[
            Track { label: "before".into(), points: before },
            Track { label: "after".into(), points: after },
        ],
        target,
        Some((&format!("liquid and body after, step {steps}"), &picture)),
    )?;
    plot::animation_gif(&out.join("optimized.gif"), domain, &gif, View::Side, (640, 320), 80)
}

/// The narrowest and the widest picture [`render_run`] draws, pixels a side (a frame is held
/// in memory at 3 bytes a pixel: 4096 x 4096 is 50 MB).
pub const MIN_PICTURE_SIDE: u32 = 64;
/// See [`MIN_PICTURE_SIDE`].
pub const MAX_PICTURE_SIDE: u32 = 4096;

/// What [`render_run`] draws.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RenderRequest {
    /// One frame (by step) as a PNG, instead of every frame as a GIF.
    pub frame: Option<usize>,
    /// The file to write [default: DIR/render.gif, or DIR/render_NNNN.png for one frame].
    pub out: Option<std::path::PathBuf>,
    /// The picture's width in pixels; the height follows the tank's extent in the view.
    pub width: u32,
    /// Seen from the side (x–y) or from above (x–z).
    pub view: View,
}

/// Draws a run's frames (a folder `diffluid run` wrote with `output.surface = true`): the
/// liquid's surface from `surface/NNNN.ply` (or `.obj`) and every body from
/// `bodies/<name>_NNNN.ply`, seen from the side or from above, as an animated GIF or one PNG. Returns the
/// file written and the number of frames drawn.
pub fn render_run(dir: &Path, request: &RenderRequest) -> Result<(std::path::PathBuf, usize)> {
    let fail = |path: &Path, message: String| Error::Read { path: path.to_path_buf(), message };
    let bad = |key: &str, message: String| Error::InvalidSettings { key: key.into(), message };
    if !(MIN_PICTURE_SIDE..=MAX_PICTURE_SIDE).contains(&request.width) {
        return Err(bad(
            "width",
            format!(
                "must be {MIN_PICTURE_SIDE} to {MAX_PICTURE_SIDE} pixels, got {}",
                request.width
            ),
        ));
    }
    let out = match (&request.out, request.frame) {
        (Some(p), _) => p.clone(),
        (None, Some(n)) => dir.join(format!("render_{n:04}.png")),
        (None, None) => dir.join("render.gif"),
    };
    let (what, ext) = match request.frame {
        Some(_) => ("one frame is drawn as a PNG", "png"),
        None => ("the frames are drawn as a GIF", "gif"),
    };
    let given = out.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    if given.as_deref() != Some(ext) {
        return Err(bad(
            "out",
            format!("{what}: give a path ending in .{ext}, got {}", out.display()),
        ));
    }
    let summary_path = dir.join("summary.json");
    let RunSummary { name, domain, dt } = RunSummary::read(&summary_path)?;
    // The surface frames by step.
    let surface = dir.join("surface");
    let mut frames: Vec<(usize, std::path::PathBuf)> = std::fs::read_dir(&surface)
        .map_err(|e| {
            fail(&surface, format!("{e}: the run wrote no surface (set output.surface = true)"))
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter_map(|p| {
            let ext = p.extension()?.to_str()?;
            let n = p.file_stem()?.to_str()?.parse().ok()?;
            (ext == "ply" || ext == "obj").then_some((n, p))
        })
        .collect();
    frames.sort();
    if let Some(n) = request.frame {
        frames.retain(|(m, _)| *m == n);
        if frames.is_empty() {
            return Err(fail(&surface, format!("no surface frame for step {n}")));
        }
    }
    if frames.is_empty() {
        return Err(fail(&surface, "no surface frames (NNNN.ply or NNNN.obj)".into()));
    }
    // A summary can describe a tank of any shape: its picture must still fit in memory.
    picture_height(domain, request.view, request.width.max(64))?;
    let body_files: Vec<std::path::PathBuf> = std::fs::read_dir(dir.join("bodies"))
        .map(|d| d.filter_map(|e| e.ok().map(|e| e.path())).collect())
        .unwrap_or_default();
    let mut drawn = Vec::with_capacity(frames.len());
    for (n, path) in &frames {
        let suffix = format!("_{n:04}.ply");
        let mut bodies = Vec::new();
        for b in body_files.iter().filter(|p| {
            p.file_name().and_then(|f| f.to_str()).is_some_and(|f| f.ends_with(&suffix))
        }) {
            bodies.push(crate::io::output::read_mesh(b)?);
        }
        drawn.push(Frame {
            liquid: crate::io::output::read_mesh(path)?,
            bodies,
            label: format!("{name}, step {n}, t = {:.2} s", *n as f64 * dt),
        });
    }
    let width = request.width;
    // The plot's margins and caption take about 60 pixels around the tank's side.
    let up = request.view.extent(domain).1;
    let height = ((width as f64 - 45.0) * up / domain.x + 60.0).round();
    if !(height >= MIN_PICTURE_SIDE as f64 && height <= MAX_PICTURE_SIDE as f64) {
        return Err(bad(
            "width",
            format!(
                "the picture would be {width} x {height} pixels (the tank is {:.3} x {up:.3} m \
                 in this view): each side must be {MIN_PICTURE_SIDE} to {MAX_PICTURE_SIDE}",
                domain.x
            ),
        ));
    }
    let height = height as u32;
    match request.frame {
        Some(_) => plot::frame_png(&out, domain, &drawn[0], request.view, (width, height))?,
        None => {
            // Real time when the frames allow it, between 20 ms and 0.2 s a frame.
            let step = frames.get(1).map_or(1, |f| f.0 - frames[0].0).max(1);
            let delay = (1e3 * dt * step as f64).clamp(20.0, 200.0) as u32;
            plot::animation_gif(&out, domain, &drawn, request.view, (width, height), delay)?
        }
    }
    Ok((out, drawn.len()))
}

/// The tallest picture `render` draws, in pixels: a tank much taller than wide (or deep, from
/// above) would otherwise ask for a picture of any size.
pub const MAX_PICTURE_HEIGHT: u32 = 8192;

/// What `render` reads of a run's `summary.json`: the scene's name, the tank's extent and
/// the step.
struct RunSummary {
    name: String,
    domain: Vec3,
    dt: f64,
}

impl RunSummary {
    /// Reads and checks `summary.json`: three whole positive cell counts, a positive dx and dt,
    /// a finite tank.
    fn read(path: &Path) -> Result<RunSummary> {
        let fail = |message: String| Error::Read { path: path.to_path_buf(), message };
        let text = crate::math::input::read_text(path)
            .map_err(|e| fail(format!("{e} (not a folder `diffluid run` wrote?)")))?;
        let summary: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| fail(e.to_string()))?;
        let grid: Option<Vec<u64>> = summary["grid"]
            .as_array()
            .and_then(|a| a.iter().map(serde_json::Value::as_u64).collect());
        let (Some(dx), Some(dt), Some(grid)) =
            (summary["dx"].as_f64(), summary["dt"].as_f64(), grid)
        else {
            return Err(fail("no grid, dx and dt".into()));
        };
        let [nx, ny, nz] = grid[..] else {
            return Err(fail(format!("grid {grid:?}: three cell counts expected")));
        };
        if grid.contains(&0) {
            return Err(fail(format!("grid {grid:?}: every axis needs at least one cell")));
        }
        if !(dx.is_finite() && dx > 0.0 && dt.is_finite() && dt > 0.0) {
            return Err(fail(format!("dx {dx} and dt {dt} must be positive")));
        }
        let domain = Vec3::new(nx as f64, ny as f64, nz as f64) * dx;
        if !domain.is_finite() {
            return Err(fail(format!("a tank of {grid:?} cells of {dx} m is not finite")));
        }
        let name = summary["scene"].as_str().unwrap_or("run").to_string();
        Ok(RunSummary { name, domain, dt })
    }
}

/// The height of a picture `width` pixels wide of a tank of extent `domain` seen from
/// `view`: the tank's aspect in the view, and about 60 pixels for the plot's margins and
/// caption. At most [`MAX_PICTURE_HEIGHT`].
fn picture_height(domain: Vec3, view: View, width: u32) -> Result<u32> {
    let (right, up) = view.extent(domain);
    let height = ((width as f64 - 45.0) * up / right + 60.0).round();
    if height.is_nan() || height > MAX_PICTURE_HEIGHT as f64 {
        return Err(Error::InvalidSettings {
            key: "render".into(),
            message: format!(
                "the tank is {:.0} times taller than wide in this view: a picture {width} \
                 pixels wide would be {height} high (at most {MAX_PICTURE_HEIGHT}); give a \
                 smaller --width or the other --view",
                up / right
            ),
        });
    }
    Ok(height as u32)
}

/// The smoothness study's two charts: the spread of the central differences over ε
/// (`smoothness_spread.png`) and the adjoint's error against the smallest ε
/// (`smoothness_adjoint.png`), per settings and parameter, against the horizon.
pub fn smoothness_charts(out: &Path, rows: &[bench::SmoothnessRow]) -> Result<()> {
    let h = |r: &bench::SmoothnessRow| r.horizon as f64;
    let spread = series(
        rows.iter().map(|r| (format!("{} {}", r.settings, r.param), (h(r), r.spread.max(1e-12)))),
    );
    plot::line_chart(
        &out.join("smoothness_spread.png"),
        "surge: spread of the central differences over eps = 1e-3 ... 1e-6",
        ("horizon, steps", "(max - min) / |fd(1e-6)|"),
        (false, true),
        &spread,
    )?;
    let adjoint = series(
        rows.iter()
            .map(|r| (format!("{} {}", r.settings, r.param), (h(r), r.adjoint_error.max(1e-12)))),
    );
    plot::line_chart(
        &out.join("smoothness_adjoint.png"),
        "surge: live-surface adjoint against fd(1e-6)",
        ("horizon, steps", "relative error (floored at 1e-12)"),
        (false, true),
        &adjoint,
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
    /// The smoothed gradient's bias and noise against the exact one on the surge: run only
    /// when asked for (`--only smoothed`; 64 gradients of up to 50 steps).
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
                "{} steps, σ_v {:.0e}: {} exact {:+.4e} (fd 1e-4 {:+.4e}, 1e-6 {:+.4e}), smoothed {:+.4e} ± {:.1e}",
                r.horizon, r.sigma, r.param, r.exact, r.fd_1e4, r.fd_1e6, r.smoothed, r.standard_error
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

/// One action of `diffluid control`'s best schedule, as `actions.csv` writes it.
#[derive(Serialize)]
struct ActionRow<'a> {
    action: usize,
    first_step: usize,
    body: &'a str,
    a0: f64,
    a1: f64,
    a2: f64,
    a3: f64,
    a4: f64,
    a5: f64,
}

/// What `result.json` of `diffluid control` holds.
#[derive(Serialize)]
struct ControlResult<'a> {
    scene: &'a str,
    epochs: usize,
    calls: usize,
    initial_loss: f64,
    best_loss: f64,
    loss_reduction: f64,
    /// The particle swarm's best loss after as many calls, if it ran.
    particle_swarm_loss: Option<f64>,
    /// The calls the gradient run took to reach the swarm's final loss, if it did.
    calls_to_match_swarm: Option<usize>,
    /// Why the gradient run stopped early, if it did.
    stopped: Option<&'a str>,
    wall_seconds: f64,
}

/// `diffluid control`'s files: `control.csv` (every epoch), `actions.csv` (the best
/// actions), `result.json`, `control.png` (the best loss against simulator calls, and the
/// particle swarm's when it ran) and `trajectory.png` (the bodies' paths under the starting
/// and the best actions, over the liquid at the start).
pub fn write_control(
    problem: &super::control::ControlProblem,
    outcome: &super::control::ControlOutcome,
    swarm: Option<&[(usize, f64)]>,
    out: &Path,
    wall_seconds: f64,
) -> Result<()> {
    std::fs::create_dir_all(out)
        .map_err(|source| Error::Write { path: out.to_path_buf(), source })?;
    write_csv(&out.join("control.csv"), &outcome.history)?;
    let names: Vec<String> = problem.sim.bodies().iter().map(|b| b.name.clone()).collect();
    let spa = problem.schedule.steps_per_action;
    let rows: Vec<ActionRow> = outcome
        .best
        .0
        .iter()
        .enumerate()
        .flat_map(|(k, row)| {
            let names = &names;
            row.iter().zip(&problem.schedule.bodies).map(move |(a, &(i, _))| ActionRow {
                action: k,
                first_step: k * spa,
                body: &names[i],
                a0: a[0],
                a1: a[1],
                a2: a[2],
                a3: a[3],
                a4: a[4],
                a5: a[5],
            })
        })
        .collect();
    write_csv(&out.join("actions.csv"), &rows)?;
    let mut best = f64::INFINITY;
    let gradient: Vec<(f64, f64)> = outcome
        .history
        .iter()
        .map(|r| {
            best = best.min(r.loss);
            (r.calls as f64, best)
        })
        .collect();
    let mut series: Vec<Series> = vec![("gradients (the adjoint)".into(), gradient.clone())];
    if let Some(s) = swarm {
        series.push((
            "particle swarm (argmin, no gradients)".into(),
            s.iter().map(|&(c, l)| (c as f64, l)).collect(),
        ));
    }
    plot::line_chart(
        &out.join("control.png"),
        &format!("{}: best loss against simulator calls", problem.scene.name),
        ("simulator calls (a gradient counts two)", "best loss"),
        (false, true),
        &series,
    )?;
    let swarm_final = swarm.and_then(|s| s.last()).map(|s| s.1);
    let calls_to_match = swarm_final
        .and_then(|target| gradient.iter().find(|(_, l)| *l <= target).map(|(c, _)| *c as usize));
    let initial = outcome.history.first().map_or(f64::NAN, |r| r.loss);
    write_json(
        &out.join("result.json"),
        &ControlResult {
            scene: &problem.scene.name,
            epochs: outcome.history.len().saturating_sub(1),
            calls: outcome.history.last().map_or(0, |r| r.calls),
            initial_loss: initial,
            best_loss: outcome.best.1,
            loss_reduction: initial / outcome.best.1,
            particle_swarm_loss: swarm_final,
            calls_to_match_swarm: calls_to_match,
            stopped: outcome.stopped.as_deref(),
            wall_seconds,
        },
    )?;
    let track = |label: String, states: &[Vec<BodyState>], i: usize| Track {
        label,
        points: states.iter().map(|s| s[i].x).collect(),
    };
    let mut tracks = Vec::new();
    for (i, name) in names.iter().enumerate() {
        tracks.push(track(format!("{name}, starting actions"), &outcome.start_states, i));
        tracks.push(track(format!("{name}, optimised"), &outcome.states, i));
    }
    let target = problem.loss.target.and_then(|t| t.position);
    let shot = frame(&problem.sim, problem.scene.output.surface_samples, String::new());
    let picture =
        Picture { domain: problem.sim.grid().size(), liquid: &shot.liquid, bodies: &shot.bodies };
    plot::trajectory_plot(
        &out.join("trajectory.png"),
        problem.sim.grid().size(),
        &tracks,
        target.map(|t| t.0),
        Some(("liquid and bodies at the start", &picture)),
    )
}
