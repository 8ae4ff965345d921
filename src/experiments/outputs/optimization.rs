//! What an optimisation writes: `diffluid optimize` (a body's initial state: `loss.csv`,
//! `result.json`, the loss and trajectory charts, the optimised run as a GIF, ParaView frames)
//! and `diffluid control` (a schedule of actions: its tables, result and charts).

use crate::error::{Error, Result};
use crate::experiments::optimize::{Optimization, Outcome};
use crate::geometry::body::BodyState;
use crate::io::liquid_mesh::{body_surfaces, liquid_surface};
use crate::io::output::{write_csv, write_json};
use crate::io::plot::{self, Frame, Series, Track};
use crate::io::render::{Picture, View};
use crate::math::{pool, Vec3};
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
    /// With smoothing, L itself (`loss` is then L_σ's estimate); empty without.
    loss_unsmoothed: Option<f64>,
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
                loss_unsmoothed: r.unsmoothed_loss,
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
    sim.set_interior_values(true);
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
    // Two runs that read nothing of each other: side by side when their steps are serial.
    let spread = problem.initial.spread();
    let (optimised, first) =
        pool::beside(spread, || record(&outcome.params, true), || record(start, false));
    let (before, _) = first?;
    let (after, gif) = optimised?;
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
    problem: &crate::experiments::control::ControlProblem,
    outcome: &crate::experiments::control::ControlOutcome,
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
