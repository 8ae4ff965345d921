//! The diffluid command line: thin over the library.

use clap::{Parser, Subcommand};
use diffluid::output::{write_json, write_ply_points};
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
            if diffluid::scene::BUILTIN_SCENES.iter().any(|(n, _)| *n == name) {
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
    let frame = |sim: &Simulation, n: usize| -> Result<(), Error> {
        if write_particles && n % every == 0 {
            write_ply_points(&out.join("particles").join(format!("{n:04}.ply")), &sim.particles)?;
        }
        if n % every == 0 {
            for b in &sim.bodies {
                let (verts, tris) = diffluid::mesh::surface_mesh(&b.shape);
                let pose = b.pose();
                let world: Vec<_> = verts.iter().map(|v| pose.transform_point(*v)).collect();
                let path = out.join("bodies").join(format!("{}_{n:04}.ply", b.name));
                diffluid::output::write_ply_mesh(&path, &world, &tris)?;
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
        diffluid::output::write_atomic(&out.join("bodies.csv"), csv.as_bytes())?;
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
        None => run(RunArgs::default()),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
