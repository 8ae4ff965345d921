//! The diffluid command line: thin over the library.

use clap::{Parser, Subcommand};
use diffluid::io::output::{write_json, write_ply_points};
use diffluid::{Error, Scene, Simulation, StepReport};
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

#[derive(Parser)]
#[command(
    name = "diffluid",
    version,
    about = "Differentiable Eulerian liquid simulation with two-way rigid coupling"
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// Run a scene forward and write particles and a summary.
    Run(RunArgs),
    /// Optimise a body's initial state so it reaches the scene's loss targets; writes
    /// loss.csv, result.json, a checkpoint after every epoch, and pictures.
    Optimize(OptimizeArgs),
    /// Compare adjoint gradients with central finite differences for every body parameter,
    /// with the full gradient and with the paper's approximation. The surface is held fixed
    /// in both passes. Exits with status 1 if a full-gradient relative error exceeds 1e-3.
    Gradcheck(GradcheckArgs),
    /// Speed against accuracy: sweeps of resolution and solver tolerance, the stability map
    /// of the monolithic and the weak coupling, thin plates, and time per step against liquid
    /// cells. Writes CSV tables and PNG charts.
    Bench(BenchArgs),
}

#[derive(clap::Args)]
struct BenchArgs {
    /// Output folder.
    #[arg(long, default_value = "out/bench")]
    out: PathBuf,
    /// Small sweeps (about a minute) instead of the full ones.
    #[arg(long)]
    quick: bool,
}

/// Writes `rows` as a CSV table with a header.
fn write_csv<T: Serialize>(path: &Path, rows: &[T]) -> Result<(), Error> {
    let io = |e: csv::Error| Error::Write {
        path: path.to_path_buf(),
        source: std::io::Error::other(e.to_string()),
    };
    let mut w = csv::Writer::from_writer(Vec::new());
    for r in rows {
        w.serialize(r).map_err(io)?;
    }
    let bytes = w.into_inner().map_err(|e| io(e.into_error().into()))?;
    diffluid::io::output::write_atomic(path, &bytes)
}

fn bench(args: BenchArgs) -> Result<(), Error> {
    use diffluid::experiments::bench;
    use diffluid::io::plot::{line_chart, stability_chart, Series};
    std::fs::create_dir_all(&args.out)
        .map_err(|e| Error::Write { path: args.out.clone(), source: e })?;
    let out = |name: &str| args.out.join(name);
    let bar = ProgressBar::new(4);
    bar.set_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} {msg} [{elapsed}]")
            .expect("valid template"),
    );
    let series = |pairs: Vec<(String, (f64, f64))>| -> Vec<Series> {
        let mut out: Vec<Series> = Vec::new();
        for (label, p) in pairs {
            match out.iter_mut().find(|s| s.0 == label) {
                Some(s) => s.1.push(p),
                None => out.push((label, vec![p])),
            }
        }
        out
    };

    bar.set_message("accuracy against time");
    let acc = bench::accuracy(args.quick)?;
    write_csv(&out("accuracy.csv"), &acc)?;
    let s = series(acc.iter().map(|r| (r.quantity.clone(), (r.seconds, r.error))).collect());
    line_chart(
        &out("accuracy.png"),
        "error against wall time",
        ("wall time of the run, s", "relative error"),
        (true, true),
        &s,
    )?;
    bar.inc(1);

    bar.set_message("stability map");
    let st = bench::stability(args.quick)?;
    write_csv(&out("stability.csv"), &st)?;
    let panels: Vec<diffluid::io::plot::StabilityPanel> = ["monolithic", "weak"]
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
    stability_chart(&out("stability.png"), &panels)?;
    bar.inc(1);

    bar.set_message("thin plates");
    let thin = bench::thin_plates(args.quick)?;
    write_csv(&out("thin.csv"), &thin)?;
    // Log axis: |value|, floored at 1e-13 (a sealed plate leaks nothing; the particle count
    // behind it can come out a little negative, which thin.csv keeps).
    let floor = |v: f64| v.abs().max(1e-13);
    let s: Vec<Series> = vec![
        ("leakage".into(), thin.iter().map(|r| (r.thickness_cells, floor(r.leakage))).collect()),
        (
            "torque error".into(),
            thin.iter().map(|r| (r.thickness_cells, floor(r.torque_error))).collect(),
        ),
        (
            "force error".into(),
            thin.iter().map(|r| (r.thickness_cells, floor(r.force_error))).collect(),
        ),
    ];
    line_chart(
        &out("thin.png"),
        "thin plates (|value|, floored at 1e-13)",
        ("plate thickness, cells", "relative error"),
        (false, true),
        &s,
    )?;
    bar.inc(1);

    bar.set_message("cost against liquid cells");
    let cost = bench::cost(args.quick)?;
    write_csv(&out("cost.csv"), &cost)?;
    let s = series(
        cost.iter()
            .map(|r| {
                let label =
                    if r.series == "air" { "liquid fixed, air grown" } else { "liquid grown" };
                (label.to_string(), (r.liquid_cells as f64, r.seconds_per_step * 1e3))
            })
            .collect(),
    );
    line_chart(
        &out("cost.png"),
        "time per step against liquid cells",
        ("liquid cells", "ms per step (median)"),
        (false, false),
        &s,
    )?;
    bar.inc(1);
    bar.finish_and_clear();

    let air: Vec<&bench::CostRow> = cost.iter().filter(|r| r.series == "air").collect();
    if air.len() >= 2 {
        println!(
            "doubling the air above the pool: {:+.1}% time per step ({} -> {} cells)",
            100.0 * (air[1].seconds_per_step / air[0].seconds_per_step - 1.0),
            air[0].cells,
            air[1].cells
        );
    }
    let lightest = st.iter().map(|r| r.density_ratio).fold(f64::INFINITY, f64::min);
    for c in ["monolithic", "weak"] {
        let rows: Vec<_> = st.iter().filter(|r| r.coupling == c).collect();
        let stable = rows.iter().filter(|r| r.stable).count();
        let light = rows.iter().filter(|r| r.density_ratio == lightest && r.stable).count();
        println!(
            "{c}: stable in {stable} of {} cells ({light} at density ratio {lightest})",
            rows.len()
        );
    }
    println!("wrote {}", args.out.display());
    Ok(())
}

#[derive(clap::Args, Default)]
struct OptimizeArgs {
    /// Scene file or built-in name with [loss] and [optimize] sections [default: the
    /// embedded block drop].
    scene: Option<PathBuf>,
    /// Output folder [default: out/<scene name>-optimize].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Epochs [default: the scene's optimize.epochs].
    #[arg(long)]
    epochs: Option<usize>,
    /// Continue from DIR/checkpoint.json.
    #[arg(long)]
    resume: bool,
    /// Also write ParaView frames of the optimised forward run to DIR/vtk/.
    #[arg(long)]
    vtk: bool,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

#[derive(Serialize)]
struct OptimizeResult<'a> {
    scene: &'a str,
    epochs: usize,
    initial_loss: f64,
    final_loss: f64,
    loss_reduction: f64,
    evaluations: usize,
    params: &'a diffluid::experiments::optimize::BodyParams,
    stopped: Option<&'a str>,
    converged: Option<&'a str>,
    wall_seconds: f64,
}

fn optimize(args: OptimizeArgs) -> Result<(), Error> {
    use diffluid::experiments::optimize::{Checkpoint, Optimization};
    let mut scene = load_scene(args.scene.as_deref())?;
    if let Some(n) = args.epochs {
        if n == 0 {
            return Err(Error::Usage("--epochs must be at least 1".into()));
        }
        if let Some(o) = scene.optimize.as_mut() {
            o.epochs = n;
        }
    }
    let out =
        args.out.unwrap_or_else(|| PathBuf::from("out").join(format!("{}-optimize", scene.name)));
    let ck_path = out.join("checkpoint.json");
    let resume = if args.resume { Some(Checkpoint::load(&ck_path)?) } else { None };
    let problem = Optimization::new(scene)?;
    let start = Instant::now();
    let done = resume.as_ref().map(|c| c.next_epoch).unwrap_or(0);
    let bar =
        if args.quiet { ProgressBar::hidden() } else { ProgressBar::new(problem.epochs as u64) };
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:30}] epoch {pos}/{len} ({elapsed} < {eta})")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_position(done as u64);
    let outcome = problem.run(Some(&ck_path), resume, |r| {
        bar.set_message(format!(
            "loss {:.4e} |g| {:.3e} ({} evaluations)",
            r.loss, r.grad_norm, r.evaluations
        ));
        bar.inc(1);
    })?;
    bar.finish_and_clear();
    let mut csv =
        String::from("epoch,evaluations,loss,grad_norm,vx,vy,vz,wx,wy,wz,x,y,z,qw,qx,qy,qz\n");
    for r in &outcome.history {
        let p = &r.params;
        csv.push_str(&format!(
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
            r.epoch,
            r.evaluations,
            r.loss,
            r.grad_norm,
            p.v[0],
            p.v[1],
            p.v[2],
            p.w[0],
            p.w[1],
            p.w[2],
            p.x[0],
            p.x[1],
            p.x[2],
            p.q[0],
            p.q[1],
            p.q[2],
            p.q[3]
        ));
    }
    diffluid::io::output::write_atomic(&out.join("loss.csv"), csv.as_bytes())?;
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
            wall_seconds: start.elapsed().as_secs_f64(),
        },
    )?;
    pictures(&problem, &problem.initial_params(), &outcome, &out)?;
    if args.vtk {
        let mut sim = problem.simulation(&outcome.params);
        let mut frames = diffluid::io::vtk::VtkSeries::new(&out.join("vtk"));
        frames.write_frame(&sim, 0)?;
        for n in 1..=problem.scene.time.steps {
            sim.step()?;
            frames.write_frame(&sim, n)?;
        }
    }
    if let Some(reason) = &outcome.stopped {
        return Err(Error::Usage(format!("optimisation stopped at {reason}")));
    }
    if let Some(reason) = &outcome.converged {
        println!("L-BFGS converged at {reason}");
    }
    println!(
        "{}: {} epochs ({} evaluations), loss {:.4e} -> {:.4e} ({:.0}x) in {:.1} s; v0 = {:?}; wrote {}",
        problem.scene.name,
        outcome.history.len(),
        outcome.evaluations,
        initial_loss,
        outcome.final_loss,
        initial_loss / outcome.final_loss,
        start.elapsed().as_secs_f64(),
        outcome.params.v,
        out.display()
    );
    Ok(())
}

/// A run's body path, liquid snapshots and animation frames.
type Recording = (
    Vec<diffluid::math::Vec3>,
    Vec<(String, Vec<diffluid::math::Vec3>)>,
    Vec<diffluid::io::plot::Frame>,
);

/// loss.png, trajectory.png (the body's path before and after, over the liquid at a few
/// frames) and optimized.gif (the optimised run).
fn pictures(
    problem: &diffluid::experiments::optimize::Optimization,
    start: &diffluid::experiments::optimize::BodyParams,
    outcome: &diffluid::experiments::optimize::Outcome,
    out: &Path,
) -> Result<(), Error> {
    use diffluid::io::plot::{animation_gif, loss_plot, trajectory_plot, Frame, Track};
    let loss: Vec<f64> = outcome.history.iter().map(|r| r.loss).collect();
    let norms: Vec<f64> = outcome.history.iter().map(|r| r.grad_norm).collect();
    if !loss.is_empty() {
        loss_plot(&out.join("loss.png"), &loss, &norms)?;
    }
    let steps = problem.scene.time.steps;
    let body = problem.body;
    let (verts, _) = diffluid::geometry::mesh::surface_mesh(&problem.initial.bodies[body].shape);
    let record = |p: &diffluid::experiments::optimize::BodyParams,
                  frames: bool|
     -> Result<Recording, Error> {
        let mut sim = problem.simulation(p);
        let mut path = vec![sim.bodies[body].x];
        let mut snaps = Vec::new();
        let mut gif = Vec::new();
        let every = (steps / 25).max(1);
        for n in 0..=steps {
            if n > 0 {
                sim.step()?;
                path.push(sim.bodies[body].x);
            }
            if frames && (n == 0 || n == steps / 2 || n == steps) {
                snaps.push((format!("liquid, step {n}"), sim.particles.clone()));
            }
            if frames && n % every == 0 {
                let pose = sim.bodies[body].pose();
                gif.push(Frame {
                    // Every other particle is plenty for a 2D picture, and halves what the
                    // frames hold in memory until the GIF is written.
                    particles: sim.particles.iter().step_by(2).copied().collect(),
                    bodies: vec![verts.iter().map(|v| pose.transform_point(*v)).collect()],
                    label: format!("{} optimised, step {n}", problem.scene.name),
                });
            }
        }
        Ok((path, snaps, gif))
    };
    let (before, _, _) = record(start, false)?;
    let (after, snaps, gif) = record(&outcome.params, true)?;
    let target = problem.loss.position.map(|(t, _)| t);
    let domain = problem.initial.grid().size();
    trajectory_plot(
        &out.join("trajectory.png"),
        domain,
        &[
            Track { label: "before".into(), points: before },
            Track { label: "after".into(), points: after },
        ],
        target,
        &snaps,
    )?;
    animation_gif(&out.join("optimized.gif"), domain, &gif, 80)
}

#[derive(clap::Args)]
struct GradcheckArgs {
    /// Scene file or built-in name (it needs a [loss] section) [default: gradcheck_box].
    scene: Option<PathBuf>,
    /// Finite-difference step.
    #[arg(long, default_value_t = 1e-6)]
    eps: f64,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct GradRow {
    name: String,
    adjoint: f64,
    fd: f64,
    rel_error: f64,
}

#[derive(Serialize)]
struct GradReport {
    scene: String,
    eps: f64,
    loss: f64,
    steps: usize,
    forward_seconds: f64,
    backward_seconds: f64,
    tape_bytes_per_step: usize,
    params: Vec<GradRow>,
    paper: Vec<GradRow>,
}

fn gradcheck(args: GradcheckArgs) -> Result<(), Error> {
    use diffluid::gradients::{
        central_difference, value_and_gradient, BodyParam, BodyTargetLoss, GradientMode,
    };
    let mut scene = match args.scene.as_deref() {
        None => Scene::builtin("gradcheck_box")?,
        Some(p) => load_scene(Some(p))?,
    };
    if !(args.eps.is_finite() && args.eps > 0.0) {
        return Err(Error::Usage(format!("--eps must be a positive number, got {}", args.eps)));
    }
    let invalid = |m: &str| Error::InvalidScene { origin: scene.name.clone(), message: m.into() };
    let loss = BodyTargetLoss::from_scene(&scene)
        .ok_or_else(|| invalid("gradcheck needs a [loss] section naming a body and its targets"))?;
    if scene.contact.enabled {
        return Err(invalid(
            "gradcheck needs [contact] enabled = false (no gradients through contact)",
        ));
    }
    scene.solver.freeze_surface = true;
    let steps = scene.time.steps;
    let sim = Simulation::new(scene.clone())?;
    let full = value_and_gradient(&sim, steps, &loss, GradientMode::Full, None)?;
    let paper = value_and_gradient(&sim, steps, &loss, GradientMode::Paper, None)?;
    let mut rows = Vec::new();
    let mut paper_rows = Vec::new();
    for (b, body) in sim.bodies.iter().enumerate().filter(|(_, b)| b.dynamic) {
        for p in BodyParam::all() {
            let fd = central_difference(&sim, steps, &loss, b, p, args.eps)?;
            let rel = |ad: f64| (ad - fd).abs() / fd.abs().max(1e-12);
            let name = format!("{}.{}", body.name, p.name());
            let ad = p.of(&full.gradient.bodies[b]);
            let pa = p.of(&paper.gradient.bodies[b]);
            rows.push(GradRow { name: name.clone(), adjoint: ad, fd, rel_error: rel(ad) });
            paper_rows.push(GradRow { name, adjoint: pa, fd, rel_error: rel(pa) });
        }
    }
    let report = GradReport {
        scene: scene.name.clone(),
        eps: args.eps,
        loss: full.loss,
        steps,
        forward_seconds: full.forward_seconds,
        backward_seconds: full.backward_seconds,
        tape_bytes_per_step: full.tape_bytes_per_step,
        params: rows,
        paper: paper_rows,
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report).expect("serialisable"));
    } else {
        println!(
            "{}: loss {:.6e} after {} steps (surface held fixed); forward {:.3} s, backward {:.3} s, tape {} kB/step",
            report.scene,
            report.loss,
            steps,
            report.forward_seconds,
            report.backward_seconds,
            report.tape_bytes_per_step / 1024
        );
        println!(
            "{:<12} {:>16} {:>16} {:>10} {:>16} {:>10}",
            "param", "adjoint", "central diff", "rel err", "paper approx", "rel err"
        );
        for (r, p) in report.params.iter().zip(&report.paper) {
            println!(
                "{:<12} {:>16.8e} {:>16.8e} {:>10.2e} {:>16.8e} {:>10.2e}",
                r.name, r.adjoint, r.fd, r.rel_error, p.adjoint, p.rel_error
            );
        }
    }
    let worst = report.params.iter().map(|r| r.rel_error).fold(0.0, f64::max);
    if worst > 1e-3 {
        return Err(Error::Usage(format!(
            "gradient check failed: worst relative error {worst:.2e} > 1e-3"
        )));
    }
    Ok(())
}

#[derive(clap::Args, Default)]
struct RunArgs {
    /// Scene file (TOML), or the name of a built-in scene; the embedded default if omitted.
    scene: Option<PathBuf>,
    /// Output folder [default: out/<scene name>].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Number of steps [default: the scene's time.steps].
    #[arg(long)]
    steps: Option<usize>,
    /// Also write ParaView frames (every output.every steps) to DIR/vtk/.
    #[arg(long)]
    vtk: bool,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

/// Loads a scene from a path, a built-in name, or the embedded default.
fn load_scene(arg: Option<&Path>) -> Result<Scene, Error> {
    match arg {
        None => Ok(Scene::embedded_default()),
        Some(p) if !p.exists() && p.extension().is_none() => {
            let name = p.to_string_lossy();
            if diffluid::experiments::scene::BUILTIN_SCENES.iter().any(|(n, _)| *n == name) {
                Scene::builtin(&name)
            } else {
                Scene::from_file(p)
            }
        }
        Some(p) => Scene::from_file(p),
    }
}

#[derive(Serialize)]
struct Summary<'a> {
    scene: &'a str,
    grid: [usize; 3],
    dx: f64,
    dt: f64,
    particles: usize,
    initial_liquid_volume: f64,
    total_seconds: f64,
    steps: &'a [StepReport],
}

fn run(args: RunArgs) -> Result<(), Error> {
    let mut scene = load_scene(args.scene.as_deref())?;
    if let Some(n) = args.steps {
        if n == 0 {
            return Err(Error::Usage("--steps must be at least 1".into()));
        }
        scene.time.steps = n;
    }
    let out = args.out.unwrap_or_else(|| PathBuf::from("out").join(&scene.name));
    let steps = scene.time.steps;
    let every = scene.output.every;
    let write_particles = scene.output.particles;
    let mut sim = Simulation::new(scene)?;
    let initial_volume = sim.liquid_volume();
    let mut vtk = args.vtk.then(|| diffluid::io::vtk::VtkSeries::new(&out.join("vtk")));
    let mut frame = |sim: &Simulation, n: usize| -> Result<(), Error> {
        if let (Some(v), true) = (vtk.as_mut(), n % every == 0) {
            v.write_frame(sim, n)?;
        }
        if write_particles && n % every == 0 {
            write_ply_points(&out.join("particles").join(format!("{n:04}.ply")), &sim.particles)?;
        }
        if n % every == 0 {
            for b in &sim.bodies {
                let (verts, tris) = diffluid::geometry::mesh::surface_mesh(&b.shape);
                let pose = b.pose();
                let world: Vec<_> = verts.iter().map(|v| pose.transform_point(*v)).collect();
                let path = out.join("bodies").join(format!("{}_{n:04}.ply", b.name));
                diffluid::io::output::write_ply_mesh(&path, &world, &tris)?;
            }
        }
        Ok(())
    };
    frame(&sim, 0)?;
    let mut csv = String::from("step,time,body,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz\n");
    let mut body_rows = |sim: &Simulation, step: usize| {
        for b in &sim.bodies {
            let (x, q, v, w) = (b.x, b.q, b.v, b.w);
            csv.push_str(&format!(
                "{step},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
                step as f64 * sim.scene().time.dt,
                b.name,
                x.x,
                x.y,
                x.z,
                q.w,
                q.x,
                q.y,
                q.z,
                v.x,
                v.y,
                v.z,
                w.x,
                w.y,
                w.z
            ));
        }
    };
    body_rows(&sim, 0);
    let bar = if args.quiet { ProgressBar::hidden() } else { ProgressBar::new(steps as u64) };
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} {msg} [{bar:30}] step {pos}/{len} ({elapsed} < {eta})",
        )
        .expect("valid template")
        .progress_chars("=> "),
    );
    bar.set_message(sim.scene().name.clone());
    let start = Instant::now();
    let mut reports = Vec::with_capacity(steps);
    let mut failure = None;
    for _ in 0..steps {
        // A failed step still leaves the summary and body tracks of every step before it.
        let r = match sim.step() {
            Ok(r) => r,
            Err(e) => {
                failure = Some(e);
                break;
            }
        };
        frame(&sim, r.step)?;
        body_rows(&sim, r.step);
        bar.set_message(format!("{} cg {:>3} it", sim.scene().name, r.cg_iterations));
        bar.inc(1);
        reports.push(r);
    }
    let total = start.elapsed().as_secs_f64();
    bar.finish_and_clear();
    if !sim.bodies.is_empty() {
        diffluid::io::output::write_atomic(&out.join("bodies.csv"), csv.as_bytes())?;
    }
    let grid = *sim.grid();
    write_json(
        &out.join("summary.json"),
        &Summary {
            scene: &sim.scene().name,
            grid: grid.n,
            dx: grid.dx,
            dt: sim.scene().time.dt,
            particles: sim.particles.len(),
            initial_liquid_volume: initial_volume,
            total_seconds: total,
            steps: &reports,
        },
    )?;
    if let Some(e) = failure {
        return Err(e);
    }
    let last = reports.last().expect("at least one step");
    println!(
        "{}: {} steps in {:.3} s ({} particles, {} liquid cells); final volume {:.4} m³ (start {:.4}), \
         max speed {:.3} m/s; wrote {}",
        sim.scene().name,
        steps,
        total,
        sim.particles.len(),
        last.liquid_cells,
        last.liquid_volume,
        initial_volume,
        last.max_speed,
        out.display()
    );
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Some(Command::Run(args)) => run(args),
        Some(Command::Gradcheck(args)) => gradcheck(args),
        Some(Command::Optimize(args)) => optimize(args),
        Some(Command::Bench(args)) => bench(args),
        // The main job: the embedded block drop forward, then its optimisation.
        None => run(RunArgs::default()).and_then(|()| optimize(OptimizeArgs::default())),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
