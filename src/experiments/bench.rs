//! `diffluid bench`: speed against accuracy, stability where methods fail, thin bodies, and
//! what air costs. Each study returns plain rows (written as CSV by the CLI and drawn by
//! `io::plot`); `quick` shrinks every sweep so a test can run them all.
//!
//! Every scene is built here as TOML text, the way a user would write it, and timed in
//! process with the wall clock: a row's `seconds` is the whole run of that configuration.

use crate::error::{Error, Result};
use crate::experiments::scene::Scene;
use crate::geometry::body::Param;
use crate::gradients::{central_difference, value_and_gradient, Coordinate, GradientSettings};
use crate::math::Vec3;
use crate::stages::pressure::Coupling;
use crate::world::Simulation;
use serde::Serialize;
use std::time::Instant;

/// One point of the accuracy-against-time chart.
#[derive(Clone, Debug, Serialize)]
pub struct AccuracyRow {
    /// `archimedes`, `gradient` or `dam_break_front`.
    pub quantity: String,
    /// What was varied (`dx=0.05`, `tol=1e-8`).
    pub setting: String,
    /// Relative error (see each study).
    pub error: f64,
    /// Wall time of the configuration, s.
    pub seconds: f64,
}

/// One cell of the stability map.
#[derive(Clone, Debug, Serialize)]
pub struct StabilityRow {
    /// `monolithic` or `weak`.
    pub coupling: String,
    /// Body density over liquid density.
    pub density_ratio: f64,
    /// |v₀|·Δt/dx of the body's initial velocity.
    pub cfl: f64,
    /// Whether the run stayed within the energy bound (see [`stability`]).
    pub stable: bool,
    /// Largest total kinetic energy over the energy bound (∞ when the run failed).
    pub energy_ratio: f64,
}

/// One plate of the thin-body study.
#[derive(Clone, Debug, Serialize)]
pub struct ThinRow {
    /// Plate thickness in cells.
    pub thickness_cells: f64,
    /// Liquid through a static plate centred on a grid plane of faces, over the liquid that
    /// crosses without it.
    pub leakage: f64,
    /// The same for a plate centred 0.3 cells off that plane.
    pub leakage_off_plane: f64,
    /// |pressure torque| on a submerged tilted plate, over ρ·g·V times its half length
    /// (the exact torque about its centre is zero).
    pub torque_error: f64,
    /// |F_y − ρ·g·V| / ρ·g·V on the same plate.
    pub force_error: f64,
}

/// One point of the cost study.
#[derive(Clone, Debug, Serialize)]
pub struct CostRow {
    /// `air` (liquid fixed, tank taller) or `liquid` (tank fixed, liquid deeper).
    pub series: String,
    /// Air height over liquid depth (`air`) or liquid depth in m (`liquid`).
    pub setting: f64,
    /// Grid cells.
    pub cells: usize,
    /// Liquid cells (pressure unknowns) at the last step.
    pub liquid_cells: usize,
    /// Median wall time of a step, s.
    pub seconds_per_step: f64,
}

/// One grid size of the scale study.
#[derive(Clone, Debug, Serialize)]
pub struct ScaleRow {
    /// Cells along x, y, z.
    pub n: String,
    /// Grid cells.
    pub cells: usize,
    /// Liquid cells at the last forward step.
    pub liquid_cells: usize,
    /// Marker particles at the last forward step.
    pub particles: usize,
    /// Median wall time of a forward step (after the first), s.
    pub forward_seconds_per_step: f64,
    /// Peak resident memory of the forward run, MB (NaN where it cannot be read).
    pub forward_peak_mb: f64,
    /// Wall time of the gradient (surface held fixed: the taped forward and the backward
    /// pass) per step, s.
    pub gradient_seconds_per_step: f64,
    /// The backward pass's time over the taped forward pass's.
    pub backward_over_forward: f64,
    /// Peak resident memory of the gradient, MB.
    pub gradient_peak_mb: f64,
}

/// Resets this process's peak resident memory to what it holds now (Linux; elsewhere
/// nothing), so [`peak_mb`] measures what follows.
fn reset_peak() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

/// This process's peak resident memory since the last [`reset_peak`], MB (NaN where it
/// cannot be read).
fn peak_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            let line = s.lines().find(|l| l.starts_with("VmHWM:"))?.to_string();
            line.split_whitespace().nth(1)?.parse::<f64>().ok()
        })
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// Time per step and peak memory against grid size: `large_tank` (a dam-break column into a
/// pool with a floating box and a floating mesh, particles in a band of 3 cells) at cells of
/// 10, 5, 2.5 and 1.25 cm (32×16×32 to 256×128×256 cells; `quick`: the first two).
/// Forward: `steps` steps, the median after the first. Gradient: the same steps with the
/// surface held fixed (a loss on the box's position). Each peak is the process's resident
/// memory during that run alone (Linux's peak counter reset before it).
pub fn scale(quick: bool) -> Result<Vec<ScaleRow>> {
    let dxs: &[f64] = if quick { &[0.1, 0.05] } else { &[0.1, 0.05, 0.025, 0.0125] };
    let steps = if quick { 2 } else { 4 };
    let mut rows = Vec::new();
    for &dx in dxs {
        let mut scene = Scene::builtin("large_tank")?;
        scene.domain.dx = dx;
        reset_peak();
        let (n, cells, liquid_cells, particles, forward) = {
            let mut sim = scene.build()?;
            let grid = *sim.grid();
            let mut times = Vec::new();
            let mut last = None;
            for _ in 0..steps {
                let t = Instant::now();
                let r = sim.step()?;
                times.push(t.elapsed().as_secs_f64());
                last = Some(r);
            }
            let r = last.expect("at least one step");
            let n = format!("{}x{}x{}", grid.n[0], grid.n[1], grid.n[2]);
            (n, grid.num_cells(), r.liquid_cells, sim.particles.len(), median(times[1..].to_vec()))
        };
        let forward_peak = peak_mb();
        reset_peak();
        let frozen = scene.clone().with_frozen_surface();
        let sim = frozen.build()?;
        let loss = crate::gradients::BodyTargetLoss {
            body: 0,
            position: Some((sim.bodies()[0].x + Vec3::new(0.05, 0.0, 0.0), 1.0)),
            orientation: None,
            velocity: None,
        };
        let run = value_and_gradient(&sim, steps, &loss, &GradientSettings::default())?;
        drop(sim);
        let gradient_peak = peak_mb();
        rows.push(ScaleRow {
            n,
            cells,
            liquid_cells,
            particles,
            forward_seconds_per_step: forward,
            forward_peak_mb: forward_peak,
            gradient_seconds_per_step: (run.forward_seconds + run.backward_seconds) / steps as f64,
            backward_over_forward: run.backward_seconds / run.forward_seconds,
            gradient_peak_mb: gradient_peak,
        });
    }
    Ok(rows)
}

/// One grid size and thread count of the real-time study.
#[derive(Clone, Debug, Serialize)]
pub struct RealtimeRow {
    /// Cells along x, y, z.
    pub n: String,
    /// Grid cells.
    pub cells: usize,
    /// `1 thread`, `2 threads` (the default spread) or `2 threads, parallel` (every loop
    /// split, small grids too).
    pub mode: String,
    /// Marker particles at the end.
    pub particles: usize,
    /// Median wall time of a frame (`advance(1/60)`, after the first ten), s.
    pub frame_seconds: f64,
    /// Frames a second at that median.
    pub frames_per_second: f64,
    /// Steps a frame took, on average.
    pub steps_per_frame: f64,
}

/// The pool of `examples/realtime_pool.rs` (3.2 × 1.6 × 3.2 m, 0.7 m of water, a crate, a
/// ball and a log) at `cells` cells across, default settings.
pub fn game_pool(cells: usize) -> Result<Scene> {
    let bodies = r#"[[body]]
name = "crate"
shape = { kind = "cuboid", half_extents = [0.2, 0.15, 0.2] }
density = 400.0
position = [0.8, 0.72, 0.9]
[[body]]
name = "ball"
shape = { kind = "ball", radius = 0.2 }
density = 600.0
position = [1.7, 0.72, 2.1]
[[body]]
name = "log"
shape = { kind = "capsule", half_height = 0.3, radius = 0.1 }
density = 700.0
position = [2.3, 0.7, 1.1]
axis_angle = { axis = [0, 0, 1], degrees = 90 }"#;
    let text = tank([3.2, 1.6, 3.2], 3.2 / cells as f64, 1.0 / 60.0, 1, 0.7, bodies);
    Scene::from_toml(&text, "<game pool>")
}

/// A game loop's frame time against grid size: [`game_pool`] at 32, 48, 64 and 96 cells
/// across (`quick`: 32 and 48), advanced 1/60 s a frame with the report's measures off (as in
/// the example), on one thread, on two as the defaults spread the step
/// ([`crate::math::pool::Spread`]: one thread below [`crate::math::pool::SERIAL_BELOW`]
/// cells), and on two with every loop parallel (`spin_workers = false`), which measures where
/// the serial path pays.
pub fn realtime(quick: bool) -> Result<Vec<RealtimeRow>> {
    let sizes: &[usize] = if quick { &[32, 48] } else { &[32, 48, 64, 96] };
    let frames = if quick { 20 } else { 120 };
    let mut rows = Vec::new();
    for &cells in sizes {
        for (threads, mode) in [(1, "1 thread"), (2, "2 threads"), (2, "2 threads, parallel")] {
            let pool =
                rayon::ThreadPoolBuilder::new().num_threads(threads).build().map_err(|e| {
                    Error::InvalidSettings {
                        key: "bench".into(),
                        message: format!("a pool of {threads} threads could not start: {e}"),
                    }
                })?;
            let row = pool.install(|| -> Result<RealtimeRow> {
                let mut scene = game_pool(cells)?;
                if mode.ends_with("parallel") {
                    scene.solver.spin_workers = Some(false);
                }
                let mut sim = scene.build()?;
                // As the example: a game loop reads none of the report's measures.
                sim.set_report_measures(false);
                let (mut times, mut steps) = (Vec::new(), 0);
                for _ in 0..frames {
                    let t = Instant::now();
                    steps += sim.advance(1.0 / 60.0)?.len();
                    times.push(t.elapsed().as_secs_f64());
                }
                let grid = *sim.grid();
                let frame = median(times[frames.min(10)..].to_vec());
                Ok(RealtimeRow {
                    n: format!("{}x{}x{}", grid.n[0], grid.n[1], grid.n[2]),
                    cells: grid.num_cells(),
                    mode: mode.into(),
                    particles: sim.particles.len(),
                    frame_seconds: frame,
                    frames_per_second: 1.0 / frame,
                    steps_per_frame: steps as f64 / frames as f64,
                })
            })?;
            rows.push(row);
        }
    }
    Ok(rows)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn clock<T>(f: impl FnOnce() -> Result<T>) -> Result<(T, f64)> {
    let t = Instant::now();
    let out = f()?;
    Ok((out, t.elapsed().as_secs_f64()))
}

/// A cube tank of side `size` at cell size `dx`, still water `depth` deep, and `bodies`
/// (TOML `[[body]]` tables) and other tables appended as they are.
fn tank(size: [f64; 3], dx: f64, dt: f64, steps: usize, depth: f64, extra: &str) -> String {
    format!(
        r#"
name = "bench"
[domain]
size = [{}, {}, {}]
dx = {dx}
[time]
dt = {dt}
steps = {steps}
[fluid]
density = 1000.0
gravity = [0.0, -9.81, 0.0]
[[liquid]]
shape = {{ kind = "box", min = [0.0, 0.0, 0.0], max = [{}, {depth}, {}] }}
[output]
particles = false
{extra}
"#,
        size[0], size[1], size[2], size[0], size[2]
    )
}

/// Accuracy against time, three ways:
///
/// - `archimedes`: a flat box (0.4 × 0.2 × 0.4 m, density ratio 0.5) placed at its exact
///   draft in still water, off the grid's planes; the first step's pressure force F_y against its weight m·g gives
///   the draft error the discretisation makes, ΔF/(ρ·g·A) over the draft 0.1 m, for dx from
///   0.1 to 0.025 m (2 to 8 cells across its height);
/// - `gradient`: the adjoint dL/dv_x of `gradcheck_box` at CG tolerances 1e-4 … 1e-10
///   against a central difference taken at 1e-12;
/// - `dam_break_front`: the dam break's front (the smallest x a particle reaches) after
///   0.5 s, at dx 0.25, 0.125 and 0.0625, against the finest run.
pub fn accuracy(quick: bool) -> Result<Vec<AccuracyRow>> {
    let mut rows = Vec::new();
    let dxs: &[f64] = if quick { &[0.1, 0.05] } else { &[0.1, 0.05, 0.04, 0.025] };
    for &dx in dxs {
        let body = r#"[[body]]
shape = { kind = "cuboid", half_extents = [0.2, 0.1, 0.2] }
density = 500.0
position = [0.413, 0.437, 0.391]
[solver]
density_correction = false
tolerance = 1e-10"#;
        // Off the grid on purpose: aligned with the cells, the volume-consistent fractions
        // make the force exact to round-off at every resolution.
        let text = tank([0.8, 0.8, 0.8], dx, 0.005, 1, 0.437, body);
        let ((force, weight), seconds) = clock(|| {
            let mut sim = Scene::from_toml(&text, "<bench>")?.build()?;
            let report = sim.step()?;
            Ok((report.bodies[0].force[1], sim.bodies()[0].mass * 9.81))
        })?;
        let area = 0.4 * 0.4;
        let draft_error = (force - weight).abs() / (1000.0 * 9.81 * area) / 0.1;
        rows.push(AccuracyRow {
            quantity: "archimedes".into(),
            setting: format!("dx={dx}"),
            error: draft_error,
            seconds,
        });
    }

    let scene = Scene::builtin("gradcheck_box")?.with_frozen_surface();
    let steps = scene.time.steps;
    let loss = scene.loss().expect("gradcheck_box has a loss");
    let mut tight = scene.clone();
    tight.solver.tolerance = 1e-12;
    let reference = {
        let sim = tight.build()?;
        central_difference(&sim, steps, &loss, 0, Coordinate { param: Param::V, axis: 0 }, 1e-6)?
    };
    let tols: &[f64] = if quick { &[1e-4, 1e-8] } else { &[1e-4, 1e-6, 1e-8, 1e-10] };
    for &tol in tols {
        let mut s = scene.clone();
        s.solver.tolerance = tol;
        let sim = s.build()?;
        let (run, seconds) =
            clock(|| value_and_gradient(&sim, steps, &loss, &GradientSettings::default()))?;
        let ad = Coordinate { param: Param::V, axis: 0 }.of(&run.gradient.bodies[0]);
        rows.push(AccuracyRow {
            quantity: "gradient".into(),
            setting: format!("tol={tol:e}"),
            error: (ad - reference).abs() / reference.abs().max(1e-300),
            seconds,
        });
    }

    // Cell sizes that divide the 4 × 1.5 × 2 m tank.
    let dxs: &[f64] = if quick { &[0.25, 0.125] } else { &[0.25, 0.125, 0.0625] };
    let mut fronts = Vec::new();
    for &dx in dxs {
        let mut scene = Scene::builtin("dam_break")?;
        scene.domain.dx = dx;
        scene.time.dt = 0.025;
        scene.time.steps = 20;
        scene.output.particles = false;
        let (front, seconds) = clock(|| {
            let mut sim = scene.build()?;
            for _ in 0..20 {
                sim.step()?;
            }
            Ok(sim.particles.iter().map(|p| p.x).fold(f64::INFINITY, f64::min))
        })?;
        fronts.push((dx, front, seconds));
    }
    let finest = fronts.last().expect("at least one resolution").1;
    let travel = 3.6 - finest;
    for (dx, front, seconds) in &fronts[..fronts.len() - 1] {
        rows.push(AccuracyRow {
            quantity: "dam_break_front".into(),
            setting: format!("dx={dx}"),
            error: (front - finest).abs() / travel,
            seconds: *seconds,
        });
    }
    Ok(rows)
}

/// The stability map: a 0.2 m cube in a closed 0.6 m tank full of water (dx 0.05 m; no free
/// surface, so only the coupling is on trial: an explicit free surface has a time-step limit
/// of its own), launched sideways at 1 m/s with Δt set for the CFL number |v₀|·Δt/dx, run
/// for 30 steps with contact on, with the monolithic and the weak coupling. Neither the density
/// projection nor volume control: the tank is full and closed, so a divergence source has
/// nowhere to send the liquid (with volume control on, every run blew up).
///
/// A run is stable when it finishes and the total kinetic energy (liquid plus body) never
/// exceeds twice what the scene can supply: the initial kinetic energy plus the potential
/// energy the body can release by rising or sinking the whole tank height, |m − ρV|·g·H.
/// An instability grows by orders of magnitude within a few steps, far past that bound.
pub fn stability(quick: bool) -> Result<Vec<StabilityRow>> {
    let ratios: &[f64] =
        if quick { &[0.01, 1.0, 10.0] } else { &[0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0] };
    let cfls: &[f64] = if quick { &[0.5, 1.0] } else { &[0.5, 1.0, 2.0, 4.0, 8.0] };
    let (dx, v0, steps, size) = (0.05, 1.0, 30, 0.6);
    let mut rows = Vec::new();
    for &coupling in &[Coupling::Monolithic, Coupling::Weak] {
        for &ratio in ratios {
            for &cfl in cfls {
                let dt = cfl * dx / v0;
                let body = format!(
                    r#"[[body]]
shape = {{ kind = "cuboid", half_extents = [0.1, 0.1, 0.1] }}
density = {}
position = [0.3, 0.25, 0.3]
velocity = [{v0}, 0.0, 0.0]
[contact]
enabled = true
[solver]
density_correction = false
volume_control = 0"#,
                    1000.0 * ratio
                );
                let mut scene =
                    Scene::from_toml(&tank([size; 3], dx, dt, steps, size, &body), "<bench>")?;
                scene.solver.coupling = coupling;
                let volume = 0.2f64.powi(3);
                let mass = 1000.0 * ratio * volume;
                let bound =
                    2.0 * (0.5 * mass * v0 * v0 + (mass - 1000.0 * volume).abs() * 9.81 * size);
                let mut sim = scene.build()?;
                let mut worst: f64 = 0.0;
                for _ in 0..steps {
                    match sim.step() {
                        Ok(r) => {
                            let b = &sim.bodies()[0];
                            let e = r.kinetic_energy
                                + 0.5 * b.mass * b.v.length_squared()
                                + 0.5 * b.w.dot(b.world_inertia() * b.w);
                            worst = worst.max(if e.is_finite() { e } else { f64::INFINITY });
                        }
                        Err(_) => {
                            worst = f64::INFINITY;
                            break;
                        }
                    }
                    if worst > 1e3 * bound {
                        break;
                    }
                }
                rows.push(StabilityRow {
                    coupling: format!("{coupling:?}").to_lowercase(),
                    density_ratio: ratio,
                    cfl,
                    stable: worst <= bound,
                    energy_ratio: worst / bound,
                });
            }
        }
    }
    Ok(rows)
}

/// Thin bodies, plates 0.125 to 2 cells thick (dx 0.05 m):
///
/// - leakage ([`plate_leakage`]): a static plate across the whole tank, on a grid plane of
///   x-faces (x = 0.5 m) and 0.3 cells off it, where a plate thinner than half a cell can
///   fall between the distance samples;
/// - torque and force ([`plate_hydrostatics`]): the same plate as a neutrally buoyant body,
///   tilted 30° about z.
pub fn thin_plates(quick: bool) -> Result<Vec<ThinRow>> {
    let thicknesses: &[f64] = if quick { &[0.25, 2.0] } else { &[0.125, 0.25, 0.5, 1.0, 1.5, 2.0] };
    let mut rows = Vec::new();
    for &t in thicknesses {
        let (force_error, torque_error) = plate_hydrostatics(t, [0.0, 0.0, 1.0], 30.0)?;
        rows.push(ThinRow {
            thickness_cells: t,
            leakage: plate_leakage(t, [0.5, 0.3, 0.15], 0.0)?,
            leakage_off_plane: plate_leakage(t, [0.5 + 0.3 * THIN_DX, 0.3, 0.15], 0.0)?,
            torque_error,
            force_error,
        });
    }
    Ok(rows)
}

/// The cell size of the thin-plate scenes, m.
pub const THIN_DX: f64 = 0.05;

/// Leakage of a static plate `cells` thick (1.2 × 0.6 m, of cells of [`THIN_DX`]) centred at
/// `centre`, turned `degrees` about z, across a 1.0 × 0.6 × 0.3 m tank that holds 0.5 m of
/// water left of x = 0.45 against 0.1 m right of x = 0.55: after 0.3 s, the liquid (marker
/// particles) past the plate's far face, less what started there, over the same with no
/// plate at all.
pub fn plate_leakage(cells: f64, centre: [f64; 3], degrees: f64) -> Result<f64> {
    let t = cells * THIN_DX;
    let a = degrees.to_radians();
    let n = Vec3::new(a.cos(), a.sin(), 0.0);
    let far_face = n.dot(Vec3::from_array(centre)) + t / 2.0;
    let crossed = |obstacle: &str| -> Result<f64> {
        let text = format!(
            r#"
name = "leak"
[domain]
size = [1.0, 0.6, 0.3]
dx = {THIN_DX}
[time]
dt = 0.01
steps = 30
[fluid]
density = 1000.0
gravity = [0.0, -9.81, 0.0]
[[liquid]]
shape = {{ kind = "box", min = [0.0, 0.0, 0.0], max = [0.45, 0.5, 0.3] }}
[[liquid]]
shape = {{ kind = "box", min = [0.55, 0.0, 0.0], max = [1.0, 0.1, 0.3] }}
{obstacle}
[output]
particles = false
"#
        );
        let mut sim = Scene::from_toml(&text, "<bench>")?.build()?;
        let count =
            |s: &Simulation| s.particles.iter().filter(|p| n.dot(**p) > far_face).count() as f64;
        let before = count(&sim);
        for _ in 0..30 {
            sim.step()?;
        }
        Ok(count(&sim) - before)
    };
    let plate = format!(
        r#"[[obstacle]]
shape = {{ kind = "cuboid", half_extents = [{}, 0.6, 0.3] }}
position = {centre:?}
axis_angle = {{ axis = [0.0, 0.0, 1.0], degrees = {degrees} }}"#,
        t / 2.0
    );
    Ok(crossed(&plate)? / crossed("")?)
}

/// Hydrostatic errors of a neutrally buoyant plate `cells` thick (0.4 × 0.3 m, of cells of
/// [`THIN_DX`]), turned `degrees` about `axis` and submerged in still water off the grid's
/// planes (centred at (0.513, 0.307, 0.291) m; centred on them, a mirror symmetry makes a
/// thick plate's errors round-off): the first solve's force error |F_y − ρ·g·V| / ρ·g·V and
/// its torque about the plate's centre (exactly zero) over ρ·g·V times the half length.
pub fn plate_hydrostatics(cells: f64, axis: [f64; 3], degrees: f64) -> Result<(f64, f64)> {
    let t = cells * THIN_DX;
    let body = format!(
        r#"[[body]]
shape = {{ kind = "cuboid", half_extents = [0.2, {}, 0.15] }}
density = 1000.0
position = [0.513, 0.307, 0.291]
axis_angle = {{ axis = {axis:?}, degrees = {degrees} }}
[solver]
density_correction = false
tolerance = 1e-10"#,
        t / 2.0
    );
    let text = tank([1.0, 0.7, 0.6], THIN_DX, 0.005, 1, 0.6, &body);
    let mut sim = Scene::from_toml(&text, "<bench>")?.build()?;
    let r = sim.step()?;
    let buoyancy = 1000.0 * 9.81 * 0.4 * 0.3 * t;
    let torque = Vec3::from_array(r.bodies[0].torque).length();
    Ok(((r.bodies[0].force[1] - buoyancy).abs() / buoyancy, torque / (buoyancy * 0.2)))
}

/// Time per step against liquid cells: a 0.5 m pool in a 1 m × 1 m tank (dx 0.05 m) with
/// 1, 2 and 4 times its depth of air above it (liquid fixed, air grown), and pools 0.25 to 1 m deep in a
/// 1.2 m tall tank (liquid grown). Median of 20 steps after 5 warm-up steps, marker
/// particles and all.
pub fn cost(quick: bool) -> Result<Vec<CostRow>> {
    let dx = 0.05;
    let steps = if quick { 6 } else { 25 };
    let run = |height: f64, depth: f64| -> Result<(usize, usize, f64)> {
        let text = tank([1.0, height, 1.0], dx, 0.01, steps, depth, "");
        let mut sim = Scene::from_toml(&text, "<bench>")?.build()?;
        let mut times = Vec::new();
        let mut cells = 0;
        for n in 0..steps {
            let t = Instant::now();
            let r = sim.step()?;
            if n >= steps / 5 {
                times.push(t.elapsed().as_secs_f64());
            }
            cells = r.liquid_cells;
        }
        Ok((sim.grid().num_cells(), cells, median(times)))
    };
    let mut rows = Vec::new();
    let air: &[f64] = if quick { &[1.0, 2.0] } else { &[1.0, 2.0, 4.0] };
    for &k in air {
        let (cells, liquid_cells, s) = run(0.5 * (1.0 + k), 0.5)?;
        rows.push(CostRow {
            series: "air".into(),
            setting: k,
            cells,
            liquid_cells,
            seconds_per_step: s,
        });
    }
    let depths: &[f64] = if quick { &[0.25, 0.5] } else { &[0.25, 0.5, 0.75, 1.0] };
    for &d in depths {
        let (cells, liquid_cells, s) = run(1.2, d)?;
        rows.push(CostRow {
            series: "liquid".into(),
            setting: d,
            cells,
            liquid_cells,
            seconds_per_step: s,
        });
    }
    Ok(rows)
}

/// One (scene, settings, horizon, parameter) point of the smoothness study.
#[derive(Clone, Debug, Serialize)]
pub struct SmoothnessRow {
    /// The built-in scene (`surge_ball` or `dam_break_ball`).
    pub scene: String,
    /// Which settings (see [`smoothness`]).
    pub settings: String,
    /// Steps from the initial state to the loss.
    pub horizon: usize,
    /// The ball's initial-state coordinate (`x[0]`, `v[0]`, `v[1]`).
    pub param: String,
    /// Central differences at ε = 1e-3, 1e-4, 1e-5, 1e-6 (NaN where not run).
    pub fd_1e3: f64,
    /// At 1e-4.
    pub fd_1e4: f64,
    /// At 1e-5.
    pub fd_1e5: f64,
    /// At 1e-6.
    pub fd_1e6: f64,
    /// (max − min)/|fd at 1e-6| over the differences taken: 0 for a map smooth at the
    /// scale of the largest ε.
    pub spread: f64,
    /// The live-surface adjoint.
    pub adjoint: f64,
    /// |adjoint − fd at 1e-6| / |fd at 1e-6|.
    pub adjoint_error: f64,
    /// |∂L/∂v₀| from the adjoint (the gradient norm's growth with the horizon).
    pub grad_norm_v: f64,
    /// Cells that changed kind (liquid ↔ not) per step, on average up to the horizon.
    pub kind_changes_per_step: f64,
}

/// Smoothness of the forward map over long horizons: the central differences of the loss in
/// the ball's initial state at several ε (their spread: a smooth map gives one derivative at
/// every ε), the live-surface adjoint's error against the smallest ε, the gradient norm
/// |∂L/∂v₀|, and how many cells change kind per step (each change is a jump of the map that
/// no derivative sees).
///
/// The full study: horizons of 25, 50, 100 and 200 steps, ε = 1e-4 and 1e-6, the ball's
/// initial v_x and v_y, on two scenes: the surge (`surge_ball`: a floating ball hit by a
/// dam-break surge, dx 0.05, dt 0.02) and the dam break with a ball (`dam_break_ball`,
/// dx 0.1, dt 0.05; its contact is on, and its gradient goes through rapier's contact
/// step, as its `[optimize]` section asks). Four settings: the defaults (since 6 December
/// 2026 the smooth ones: the liquid–air faces blended, φ_L ramped into the bodies, air
/// pockets closed, no sparse-cell rule, θ clamped at 1e-5); `volume control` (no density
/// projection, the volume kept by the smooth divergence source instead); `smoothed` (also
/// a fixed 4 particle sub-steps); and `yes/no rules` (the defaults before: no blend, no
/// ramp, pockets open, the sparse-cell rule, θ clamped at 0.01). The quick study: the surge
/// at 4 and 8 steps, x₀, ε = 1e-4 and 1e-6, the defaults.
pub fn smoothness(quick: bool) -> Result<Vec<SmoothnessRow>> {
    use crate::geometry::body::Param;
    let epss = [1e-4, 1e-6];
    let horizons: &[usize] = if quick { &[4, 8] } else { &[25, 50, 100, 200] };
    let params: &[Coordinate] = if quick {
        &[Coordinate { param: Param::X, axis: 0 }]
    } else {
        &[Coordinate { param: Param::V, axis: 0 }, Coordinate { param: Param::V, axis: 1 }]
    };
    let scenes: &[&str] = if quick { &["surge_ball"] } else { &["surge_ball", "dam_break_ball"] };
    let variants: &[&str] = if quick {
        &["default"]
    } else {
        &["default", "volume control", "smoothed", "yes/no rules"]
    };
    let mut rows = Vec::new();
    for &name in scenes {
        for &variant in variants {
            let mut scene = Scene::builtin(name)?;
            match variant {
                "default" => {}
                "volume control" => {
                    scene.solver.density_correction = false;
                    scene.solver.volume_control = Some(4.0);
                }
                "smoothed" => {
                    scene.solver.density_correction = false;
                    scene.solver.volume_control = Some(4.0);
                    scene.solver.sparse_cells = false;
                    scene.solver.particle_substeps = 4;
                }
                "yes/no rules" => scene.solver.use_yes_no_surface_rules(),
                other => unreachable!("no settings {other}"),
            }
            rows.extend(smoothness_of(&scene, variant, horizons, &epss, params)?);
        }
    }
    Ok(rows)
}

/// The rows of [`smoothness`] for one scene under one settings.
fn smoothness_of(
    scene: &Scene,
    variant: &str,
    horizons: &[usize],
    epss: &[f64],
    params: &[Coordinate],
) -> Result<Vec<SmoothnessRow>> {
    use crate::gradients::{value_and_gradient, GradientOptions, GradientSettings, Loss};
    let max = *horizons.last().expect("a horizon");
    let loss = scene.loss().expect("the scene has a loss");
    let through_contact = scene.through_contact();
    let settings: GradientSettings =
        GradientOptions { through_contact, ..Default::default() }.into();
    let sim = scene.build()?;
    // Kind changes along the unperturbed run.
    let mut changes = Vec::with_capacity(max);
    let mut s = sim.clone();
    let liquid =
        |s: &Simulation| -> Vec<bool> { s.liquid_phi().iter().map(|p| *p < 0.0).collect() };
    s.step()?;
    let mut last = liquid(&s);
    for _ in 1..max {
        s.step()?;
        let now = liquid(&s);
        changes.push(now.iter().zip(&last).filter(|(a, b)| a != b).count() as f64);
        last = now;
    }
    // The losses at every horizon of one run per (parameter, ±ε).
    let run = |c: Coordinate, h: f64| -> Result<Vec<f64>> {
        let mut s = sim.clone();
        let b = &mut s.bodies_mut()[0];
        let st = c.param.perturbed(&b.state(), c.axis, h);
        b.set_state(&st);
        let mut out = Vec::new();
        for n in 1..=max {
            s.step()?;
            if horizons.contains(&n) {
                out.push(loss.value(&s));
            }
        }
        Ok(out)
    };
    let adjoints: Vec<_> = horizons
        .iter()
        .map(|&h| value_and_gradient(&sim, h, &loss, &settings))
        .collect::<Result<_>>()?;
    let mut rows = Vec::new();
    for &c in params {
        let mut fds = Vec::new();
        for &eps in epss {
            let (p, m) = (run(c, eps)?, run(c, -eps)?);
            fds.push((
                eps,
                p.iter().zip(&m).map(|(a, b)| (a - b) / (2.0 * eps)).collect::<Vec<_>>(),
            ));
        }
        for (k, &h) in horizons.iter().enumerate() {
            let at = |e: f64| fds.iter().find(|(x, _)| *x == e).map_or(f64::NAN, |(_, v)| v[k]);
            let vals: Vec<f64> = fds.iter().map(|(_, v)| v[k]).collect();
            let fine = at(1e-6);
            let spread = (vals.iter().copied().fold(f64::MIN, f64::max)
                - vals.iter().copied().fold(f64::MAX, f64::min))
                / fine.abs();
            let g = &adjoints[k].gradient.bodies[0];
            let adjoint = c.of(g);
            rows.push(SmoothnessRow {
                scene: scene.name.clone(),
                settings: variant.into(),
                horizon: h,
                param: c.name(),
                fd_1e3: at(1e-3),
                fd_1e4: at(1e-4),
                fd_1e5: at(1e-5),
                fd_1e6: fine,
                spread,
                adjoint,
                adjoint_error: (adjoint - fine).abs() / fine.abs(),
                grad_norm_v: g.v.length(),
                kind_changes_per_step: changes[..h - 1].iter().sum::<f64>() / (h - 1) as f64,
            });
        }
    }
    Ok(rows)
}

/// One (horizon, σ, parameter) point of the smoothed-gradient study.
#[derive(Clone, Debug, Serialize)]
pub struct SmoothedRow {
    /// Steps.
    pub horizon: usize,
    /// σ of the velocity, m/s (the position's is a tenth of it in m).
    pub sigma: f64,
    /// Runs (antithetic pairs × 2).
    pub samples: usize,
    /// What the estimate is taken from: `gradients` (the mean of the runs' exact gradients)
    /// or `values` (the runs' losses alone, see [`crate::gradients::SmoothingEstimator`]).
    pub estimator: String,
    /// Which coordinate.
    pub param: String,
    /// The exact (live-surface) adjoint at the unperturbed state.
    pub exact: f64,
    /// Central differences of L at ε = 1e-4 and 1e-6.
    pub fd_1e4: f64,
    /// At ε = 1e-6.
    pub fd_1e6: f64,
    /// The smoothed gradient's estimate.
    pub smoothed: f64,
    /// Its standard error.
    pub standard_error: f64,
    /// smoothed − exact, relative to |exact|: the smoothing's bias (with the estimate's noise).
    pub bias: f64,
    /// Wall time of the smoothed estimate, s.
    pub seconds: f64,
}

/// The smoothed gradient ([`crate::gradients::smooth`]) against the exact one on the surge
/// (`surge_ball`): at 25 and 50 steps, σ_v = 1e-3 and 1e-2 m/s (σ_x a tenth of it, in m),
/// 16 runs each, from the runs' exact gradients and from their losses alone, the estimate of
/// ∂L/∂x₀ and ∂L/∂v_y with its standard error beside the exact adjoint and the central
/// differences at 1e-4 and 1e-6 (where the map jumps, those two disagree and the exact
/// gradient is one smooth piece's slope). The quick study: 6 steps, σ_v = 1e-2, 4 runs, from
/// the gradients, ∂L/∂x₀ and ∂L/∂v_x.
pub fn smoothed_gradient(quick: bool) -> Result<Vec<SmoothedRow>> {
    use crate::geometry::body::Param;
    use crate::gradients::{
        central_difference, value_and_gradient, value_and_smoothed_gradient, GradientSettings,
        Smoothing, SmoothingEstimator, SmoothingScale,
    };
    let horizons: &[usize] = if quick { &[6] } else { &[25, 50] };
    let sigmas: &[f64] = if quick { &[1e-2] } else { &[1e-3, 1e-2] };
    let samples = if quick { 4 } else { 16 };
    let estimators: &[SmoothingEstimator] =
        if quick { &[SmoothingEstimator::Gradients] } else { &SmoothingEstimator::ALL };
    // The quick study's v_x: at 6 steps v_y's gradient is small and curved at the scale of
    // σ_v with the blended surface (docs/gradients.md, "The smooth defaults").
    let v_axis = if quick { 0 } else { 1 };
    let params =
        [Coordinate { param: Param::X, axis: 0 }, Coordinate { param: Param::V, axis: v_axis }];
    let scene = Scene::builtin("surge_ball")?;
    let loss = scene.loss().expect("surge_ball has a loss");
    let sim = scene.build()?;
    let settings = GradientSettings::default();
    let mut rows = Vec::new();
    for &h in horizons {
        let exact = value_and_gradient(&sim, h, &loss, &settings)?.gradient.bodies[0];
        let fd = |c: Coordinate, e: f64| central_difference(&sim, h, &loss, 0, c, e);
        let fds: Vec<(f64, f64)> =
            params.iter().map(|&c| Ok((fd(c, 1e-4)?, fd(c, 1e-6)?))).collect::<Result<_>>()?;
        for (&sigma, &estimator) in
            sigmas.iter().flat_map(|s| estimators.iter().map(move |e| (s, e)))
        {
            let scale = SmoothingScale { v: sigma, w: 0.0, x: 0.1 * sigma, q: 0.0 };
            let smoothing = Smoothing { estimator, ..Smoothing::new(samples, scale, 1) };
            let run = value_and_smoothed_gradient(&sim, h, &loss, &settings, &smoothing)?;
            for (&c, &(fd_1e4, fd_1e6)) in params.iter().zip(&fds) {
                let (ex, sm) = (c.of(&exact), c.of(&run.gradient.bodies[0]));
                rows.push(SmoothedRow {
                    horizon: h,
                    sigma,
                    samples,
                    estimator: estimator.name().into(),
                    param: c.name(),
                    exact: ex,
                    fd_1e4,
                    fd_1e6,
                    smoothed: sm,
                    standard_error: c.of(&run.standard_error[0]),
                    bias: (sm - ex) / ex.abs(),
                    seconds: run.seconds,
                });
            }
        }
    }
    Ok(rows)
}

/// One step of one scene of the energy audit.
#[derive(Clone, Debug, Serialize)]
pub struct EnergyRow {
    /// Which scene (one of [`ENERGY_SCENES`]).
    pub scene: String,
    /// Steps taken (0: the initial state, before the first step).
    pub step: usize,
    /// Simulated time, s.
    pub time: f64,
    /// The liquid's kinetic energy, J (see [`crate::world::Energy`]).
    pub liquid_kinetic: f64,
    /// The liquid's potential energy −m·g·x (zero at the origin), J.
    pub liquid_potential: f64,
    /// The bodies' kinetic energy, translation and rotation, J.
    pub body_kinetic: f64,
    /// The bodies' potential energy, J.
    pub body_potential: f64,
    /// The total less the total of the initial state (step 0), J: a closed system without
    /// forcing may lose energy (advection dissipates) but never gain it.
    pub total_change: f64,
}

/// The energy audit's scenes, in the order [`energy`] runs them.
pub const ENERGY_SCENES: [&str; 4] = ["still_water", "ball_at_rest", "ball_dropped", "sloshing"];

/// The scene file of one of [`ENERGY_SCENES`], `steps` steps of 0.01 s, default solver
/// settings.
fn energy_scene(name: &str, steps: usize) -> String {
    let ball = |y: f64| {
        format!(
            r#"[[body]]
name = "ball"
shape = {{ kind = "ball", radius = 0.12 }}
density = 500.0
position = [0.413, {y}, 0.387]"#
        )
    };
    match name {
        "still_water" => tank([0.8, 0.6, 0.8], 0.04, 0.01, steps, 0.32, ""),
        "ball_at_rest" => tank([0.8, 0.6, 0.8], 0.04, 0.01, steps, 0.32, &ball(0.32)),
        "ball_dropped" => tank([0.8, 0.6, 0.8], 0.04, 0.01, steps, 0.32, &ball(0.37)),
        "sloshing" => format!(
            r#"
name = "sloshing"
[domain]
size = [0.8, 0.6, 0.4]
dx = 0.04
[time]
dt = 0.01
steps = {steps}
[fluid]
density = 1000.0
gravity = [0.0, -9.81, 0.0]
[[liquid]]
shape = {{ kind = "convex_hull", points = [
    [0.0, 0.0, 0.0], [0.8, 0.0, 0.0], [0.0, 0.0, 0.4], [0.8, 0.0, 0.4],
    [0.0, 0.25, 0.0], [0.0, 0.25, 0.4], [0.8, 0.35, 0.0], [0.8, 0.35, 0.4],
] }}
[output]
particles = false
"#
        ),
        _ => unreachable!("not an energy scene: {name}"),
    }
}

/// The energy audit: the mechanical energy of the liquid and the bodies
/// ([`Simulation::energy`]) step by step over 3 s (Δt = 0.01 s; `quick`: 0.5 s) of four
/// scenes with the default solver settings, none of them forced, so none should gain energy:
///
/// - `still_water`: a 0.8 × 0.6 × 0.8 m tank (dx 0.04 m), water 0.32 m deep, a rest state;
/// - `ball_at_rest`: the same with a ball of radius 0.12 m and density 500 at its
///   Archimedes height (centre on the surface, at (0.413, 0.32, 0.387) m), a rest state too;
/// - `ball_dropped`: the same ball released 5 cm higher, which bobs and makes waves;
/// - `sloshing`: a 0.8 × 0.6 × 0.4 m tank (dx 0.04 m) whose water surface starts tilted,
///   0.25 m deep at x = 0 to 0.35 m at x = 0.8, and sloshes.
///
/// A row per scene and step, step 0 the initial state; each total is compared with its own
/// scene's initial one (potential energy is zero at the origin).
pub fn energy(quick: bool) -> Result<Vec<EnergyRow>> {
    let dt = 0.01;
    let steps = if quick { 50 } else { 300 };
    let mut rows = Vec::with_capacity(ENERGY_SCENES.len() * (steps + 1));
    for name in ENERGY_SCENES {
        let mut sim = Scene::from_toml(&energy_scene(name, steps), "<bench>")?.build()?;
        let start = sim.energy();
        let row = |step: usize, e: &crate::world::Energy| EnergyRow {
            scene: name.into(),
            step,
            time: step as f64 * dt,
            liquid_kinetic: e.liquid_kinetic,
            liquid_potential: e.liquid_potential,
            body_kinetic: e.body_kinetic,
            body_potential: e.body_potential,
            total_change: e.total() - start.total(),
        };
        rows.push(row(0, &start));
        for n in 1..=steps {
            let r = sim.step()?;
            rows.push(row(n, &r.energy));
        }
    }
    Ok(rows)
}

/// One thickness of the moving-thin-body study ([`moving_thin`]).
#[derive(Clone, Debug, Serialize)]
pub struct MovingThinRow {
    /// Body thickness in cells.
    pub thickness_cells: f64,
    /// The falling disk's acceleration over the potential-flow value ([`disk_fall`]).
    pub fall_over_potential: f64,
    /// The same before moving thin bodies were sealed ([`disk_fall_before`]), where stored.
    pub fall_over_potential_before: Option<f64>,
    /// Liquid through a paddle moved at constant speed, over the liquid its outline swept
    /// ([`paddle_through`]).
    pub leakage: f64,
    /// The liquid's x-momentum after the paddle's push, over a two-cell paddle's.
    pub momentum_over_thick: f64,
}

/// A disk (radius 0.2 m, `cells` thick on cells of [`THIN_DX`], density 3000) released flat
/// at rest in the middle of a 1.4 m cube of still water 1.3 m deep: its downward
/// acceleration over the first 5 steps of 2 ms (it moves about a hundredth of a cell), and
/// the potential-flow value for a thin disk, (m − ρV)·g / (m + 8/3·ρ·R³) (added mass of a
/// disk broadside, Lamb §108). Returns (measured, potential flow).
pub fn disk_fall(cells: f64) -> Result<(f64, f64)> {
    let t = cells * THIN_DX;
    let (radius, density, steps, dt) = (0.2, 3000.0, 5, 0.002);
    let body = format!(
        r#"[[body]]
name = "disk"
shape = {{ kind = "cylinder", half_height = {}, radius = {radius} }}
density = {density}
position = [0.7013, 0.6527, 0.6991]"#,
        t / 2.0
    );
    let text = tank([1.4, 1.4, 1.4], THIN_DX, dt, steps, 1.3, &body);
    let mut sim = Scene::from_toml(&text, "<bench>")?.build()?;
    for _ in 0..steps {
        sim.step()?;
    }
    let measured = -sim.bodies()[0].v.y / (steps as f64 * dt);
    let (rho, g) = (1000.0, 9.81);
    let volume = std::f64::consts::PI * radius * radius * t;
    let mass = density * volume;
    let added = 8.0 / 3.0 * rho * radius.powi(3);
    Ok((measured, (mass - rho * volume) * g / (mass + added)))
}

/// The falling disk's acceleration over potential flow before moving thin bodies were sealed
/// (issue 36), by thickness in cells: (thickness, ratio) from `assets/bench/disk_fall_before.csv`,
/// measured with the code of that time on the scene of [`disk_fall`] (the file's README says
/// how).
pub fn disk_fall_before() -> Vec<(f64, f64)> {
    const TABLE: &str = include_str!("../../assets/bench/disk_fall_before.csv");
    TABLE
        .lines()
        .skip(1)
        .filter_map(|l| {
            let mut cols = l.split(',').map(|c| c.trim().parse::<f64>());
            Some((cols.next()?.ok()?, cols.next()?.ok()?))
        })
        .collect()
}

/// How far (m) a neutrally buoyant plate `cells` thick (0.4 × 0.3 m, of cells of
/// [`THIN_DX`]), tilted 17° about (0.3, 1, 0.2) and submerged at rest in still water off the
/// grid's planes, moves in 0.5 s (100 steps of 5 ms): it should stay put.
pub fn plate_drift(cells: f64) -> Result<f64> {
    let t = cells * THIN_DX;
    let body = format!(
        r#"[[body]]
shape = {{ kind = "cuboid", half_extents = [0.2, {}, 0.15] }}
density = 1000.0
position = [0.513, 0.307, 0.291]
axis_angle = {{ axis = [0.3, 1.0, 0.2], degrees = 17.0 }}"#,
        t / 2.0
    );
    let text = tank([1.0, 0.7, 0.6], THIN_DX, 0.005, 100, 0.6, &body);
    let mut sim = Scene::from_toml(&text, "<bench>")?.build()?;
    let x0 = sim.bodies()[0].x;
    for _ in 0..100 {
        sim.step()?;
    }
    Ok((sim.bodies()[0].x - x0).length())
}

/// A kinematic paddle (a plate 0.3 × 0.3 m, `cells` thick on cells of [`THIN_DX`], its
/// normal along x) moved along +x at 0.25 m/s for 100 steps of 10 ms through a 1.2 × 0.6 ×
/// 0.6 m tank of water 0.4 m deep, fully submerged. Returns (leakage, momentum): the marker
/// particles that cross the paddle's plane within its outline shrunk by a cell (the liquid
/// flows around the edges, not through the middle), over the particles the outline swept;
/// and the momentum the paddle gives the liquid in its first 10 steps (its start), kg·m/s:
/// −Σ Δt·F_x of the pressure force F on it ([`Simulation::fluid_force`]).
pub fn paddle_through(cells: f64) -> Result<(f64, f64)> {
    let t = cells * THIN_DX;
    let (speed, dt, steps) = (0.25, 0.01, 100);
    let (half, centre) = (0.15, [0.3013, 0.2027, 0.2991]);
    let body = format!(
        r#"[[body]]
name = "paddle"
shape = {{ kind = "cuboid", half_extents = [{}, {half}, {half}] }}
density = 1000.0
dynamic = false
velocity = [{speed}, 0.0, 0.0]
position = {centre:?}
# The leakage follows each particle by its index: no band trading them.
[solver]
narrow_band = 0"#,
        t / 2.0
    );
    let text = tank([1.2, 0.6, 0.6], THIN_DX, dt, steps, 0.4, &body);
    let mut sim = Scene::from_toml(&text, "<bench>")?.build()?;
    let inner = half - THIN_DX;
    let mut crossed = 0usize;
    let mut momentum = 0.0;
    for step in 0..steps {
        let x0 = sim.bodies()[0].x;
        let before = sim.particles.clone();
        sim.step()?;
        let x1 = sim.bodies()[0].x;
        if sim.particles.len() == before.len() {
            crossed += before
                .iter()
                .zip(&sim.particles)
                .filter(|(a, b)| {
                    let inside =
                        |p: &Vec3, c: Vec3| (p.y - c.y).abs() < inner && (p.z - c.z).abs() < inner;
                    (a.x - x0.x).signum() != (b.x - x1.x).signum() && inside(a, x0) && inside(b, x1)
                })
                .count();
        }
        if step < 10 {
            momentum -= dt * sim.fluid_force(sim.handles()[0]).map_or(0.0, |f| f.0.x);
        }
    }
    let per_cell = sim.settings().solver.particles_per_cell as f64;
    let swept = (2.0 * inner).powi(2) * speed * dt * steps as f64 / THIN_DX.powi(3) * per_cell;
    Ok((crossed as f64 / swept, momentum))
}

/// Moving thin bodies, 0.125 to 2 cells thick: the falling disk against potential flow
/// ([`disk_fall`]; beside it the stored figure from before the seal, [`disk_fall_before`]), and a paddle pushed through the water ([`paddle_through`]): the liquid
/// through it, and the momentum it gives the liquid over a two-cell paddle's.
pub fn moving_thin(quick: bool) -> Result<Vec<MovingThinRow>> {
    let thicknesses: &[f64] = if quick { &[0.25, 2.0] } else { &[0.125, 0.25, 0.5, 1.0, 2.0] };
    let (_, thick) = paddle_through(2.0)?;
    let before = disk_fall_before();
    let mut rows = Vec::new();
    for &t in thicknesses {
        let (a, pf) = disk_fall(t)?;
        let (leakage, momentum) = paddle_through(t)?;
        rows.push(MovingThinRow {
            thickness_cells: t,
            fall_over_potential: a / pf,
            fall_over_potential_before: before
                .iter()
                .find(|(c, _)| (c - t).abs() < 1e-9)
                .map(|&(_, r)| r),
            leakage,
            momentum_over_thick: momentum / thick,
        });
    }
    Ok(rows)
}
