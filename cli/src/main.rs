//! The diffluid command line: argument handling and printing over the library.

use clap::{Parser, Subcommand};
use diffluid::experiments::optimize::{Checkpoint, Optimization};
use diffluid::experiments::outputs::{
    render_run, write_bench, write_control, write_optimization, RenderRequest, Study,
};
use diffluid::gradients::{gradcheck, GradcheckSettings};
use diffluid::io::recorder::{Frames, RunFolder, RunRecorder, SurfaceFrames};
use diffluid::io::render::View;
use diffluid::math::memory::GridAllocator;
use diffluid::Scene;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
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
    /// Steer bodies over time: optimise the scene's [control] actions (a force and torque on
    /// a dynamic body, a velocity on a `dynamic = false` one, at every step) against its
    /// [loss] on the whole trajectory, with gradients from one backward sweep; with --swarm,
    /// also without gradients (argmin's particle swarm) for the same simulator calls. Writes
    /// control.csv, actions.csv, result.json, control.png and trajectory.png.
    Control(ControlArgs),
    /// Compare adjoint gradients with central finite differences for every body parameter,
    /// with the full gradient and with the paper's approximation, on the scene's own map (its
    /// surface moving unless the scene freezes it; --frozen holds it fixed in both passes).
    /// Exits with status 1 if a parameter fails |adjoint − fd| ≤ atol + rtol·|fd| (at a kink of
    /// the map, where the one-sided differences disagree: unless the adjoint is one of them).
    Gradcheck(GradcheckArgs),
    /// Speed against accuracy: sweeps of resolution and solver tolerance, the stability map
    /// of the monolithic and the weak coupling, thin plates, time per step against liquid
    /// cells, an energy audit, and smoothness over long horizons. Writes CSV tables and PNG
    /// charts.
    Bench(BenchArgs),
    /// Draw a run's frames (a folder `run` wrote with output.surface = true): the liquid's
    /// shaded surface and the bodies, seen from the side or from above, as DIR/render.gif,
    /// or one frame as a PNG with --frame.
    Render(RenderArgs),
}

#[derive(clap::Args)]
struct RenderArgs {
    /// The run's output folder.
    dir: PathBuf,
    /// Draw only the frame of this step, as a PNG.
    #[arg(long)]
    frame: Option<usize>,
    /// The file to write [default: DIR/render.gif, or DIR/render_NNNN.png with --frame].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Width in pixels (the height follows the tank).
    #[arg(long, default_value_t = 800)]
    width: u32,
    /// Seen from the side (x–y) or from above (x–z).
    #[arg(long, value_enum, default_value = "side")]
    view: View,
}

fn render(args: RenderArgs) -> Outcome {
    let request =
        RenderRequest { frame: args.frame, out: args.out, width: args.width, view: args.view };
    let (path, frames) = render_run(&args.dir, &request)?;
    println!("drew {frames} frame{}; wrote {}", if frames == 1 { "" } else { "s" }, path.display());
    Ok(())
}

/// What ends a command: the one line it prints (a library error or a bad argument) and its
/// exit status (1; 130, as a shell reports a process SIGINT ended, for an interrupted run).
struct Failure {
    message: String,
    status: u8,
}

impl Failure {
    fn new(message: String) -> Failure {
        Failure { message, status: 1 }
    }
}

impl From<diffluid::Error> for Failure {
    fn from(e: diffluid::Error) -> Self {
        Failure::new(e.to_string())
    }
}

type Outcome = Result<(), Failure>;

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
    /// Also write the liquid's surface mesh per frame to DIR/surface/ (output.surface = true).
    #[arg(long)]
    surface: bool,
    /// Write into an --out folder that holds files a run does not write (they are kept; an
    /// earlier run's files are cleared in any case).
    #[arg(long)]
    force: bool,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

#[derive(clap::Args)]
struct ControlArgs {
    /// Scene file or built-in name with [control] and [loss] sections.
    scene: PathBuf,
    /// Output folder [default: out/<scene name>-control].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Epochs [default: the scene's control.epochs].
    #[arg(long)]
    epochs: Option<usize>,
    /// Also solve it without gradients: argmin's particle swarm for as many simulator calls as
    /// the gradient run made.
    #[arg(long)]
    swarm: bool,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

fn control(args: ControlArgs) -> Outcome {
    use diffluid::experiments::control::{optimise, particle_swarm, ControlProblem};
    let scene = load_scene(Some(&args.scene))?;
    let out =
        args.out.unwrap_or_else(|| PathBuf::from("out").join(format!("{}-control", scene.name)));
    let problem = ControlProblem::new(scene)?;
    let epochs = match args.epochs {
        Some(0) => return Err(Failure::new("--epochs must be at least 1".into())),
        Some(n) => n,
        None => problem.epochs,
    };
    let _lock = RunFolder::lock(&out)?;
    let start = Instant::now();
    let bar = bar(epochs + 1, args.quiet, "{msg} [{bar:30}] epoch {pos}/{len} ({elapsed} < {eta})");
    let outcome = optimise(&problem, epochs, |r| {
        bar.set_message(format!("loss {:.4e} |g| {:.3e}", r.loss, r.grad_norm));
        bar.inc(1);
    })?;
    bar.finish_and_clear();
    let calls = outcome.history.last().map_or(0, |r| r.calls);
    let swarm = if args.swarm { Some(particle_swarm(&problem, calls)?) } else { None };
    write_control(&problem, &outcome, swarm.as_deref(), &out, start.elapsed().as_secs_f64())?;
    if let Some(reason) = &outcome.stopped {
        return Err(Failure::new(format!("control stopped at {reason}; wrote {}", out.display())));
    }
    let initial = outcome.history.first().map_or(f64::NAN, |r| r.loss);
    println!(
        "{}: {epochs} epochs ({calls} simulator calls), loss {initial:.4e} -> {:.4e} ({:.0}x){} in {:.1} s; wrote {}",
        problem.scene.name,
        outcome.best.1,
        initial / outcome.best.1,
        swarm
            .as_ref()
            .and_then(|s| s.last())
            .map(|s| format!("; particle swarm {:.4e} after {} calls", s.1, s.0))
            .unwrap_or_default(),
        start.elapsed().as_secs_f64(),
        out.display()
    );
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

#[derive(clap::Args)]
struct GradcheckArgs {
    /// Scene file or built-in name (it needs a [loss] section) [default: gradcheck_box].
    scene: Option<PathBuf>,
    /// Finite-difference step.
    #[arg(long, default_value_t = 1e-6)]
    eps: f64,
    /// Relative tolerance.
    #[arg(long, default_value_t = 1e-3)]
    rtol: f64,
    /// Absolute tolerance.
    #[arg(long, default_value_t = 1e-9)]
    atol: f64,
    /// Hold the liquid surface fixed in the forward and backward passes (the paper's frozen
    /// surface, an exact gradient of that map).
    #[arg(long)]
    frozen: bool,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
    /// With a [control] section: how many action entries to check (spread evenly over the
    /// actions, bodies and entries; all of them if there are fewer).
    #[arg(long, default_value_t = 12)]
    actions: usize,
}

#[derive(clap::Args)]
struct BenchArgs {
    /// Output folder.
    #[arg(long, default_value = "out/bench")]
    out: PathBuf,
    /// Small sweeps (a few seconds) instead of the full ones.
    #[arg(long)]
    quick: bool,
    /// Run only this study.
    #[arg(long, value_enum)]
    only: Option<Study>,
}

/// A scene from a path, a built-in name, or the embedded default.
fn load_scene(arg: Option<&Path>) -> Result<Scene, diffluid::Error> {
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

fn bar(len: usize, quiet: bool, template: &str) -> ProgressBar {
    let bar = if quiet { ProgressBar::hidden() } else { ProgressBar::new(len as u64) };
    bar.set_style(
        ProgressStyle::with_template(template).expect("valid template").progress_chars("=> "),
    );
    bar
}

/// What Ctrl-C (SIGINT) or SIGTERM does while a [`Listening`] guard lives: it sets the flag,
/// so a run stops after the step in progress and writes what it has; a second one ends the
/// process at once. Without one (the other commands, or `optimize` after `run` in the default
/// job) it ends the process at once, as if no handler were installed. Exit status 130.
struct Listening(Arc<AtomicBool>);

/// Whether a [`Listening`] guard lives.
static LISTENING: AtomicBool = AtomicBool::new(false);

impl Listening {
    /// Installs the handler (once) and starts listening.
    fn start() -> Listening {
        static FLAG: std::sync::OnceLock<Arc<AtomicBool>> = std::sync::OnceLock::new();
        let flag = FLAG
            .get_or_init(|| {
                let flag = Arc::new(AtomicBool::new(false));
                let set = flag.clone();
                let installed = ctrlc::set_handler(move || {
                    if !LISTENING.load(Ordering::SeqCst) || set.swap(true, Ordering::SeqCst) {
                        std::process::exit(130);
                    }
                });
                if let Err(e) = installed {
                    eprintln!("warning: Ctrl-C will end the run without its summary: {e}");
                }
                flag
            })
            .clone();
        flag.store(false, Ordering::SeqCst);
        LISTENING.store(true, Ordering::SeqCst);
        Listening(flag)
    }

    /// Whether Ctrl-C came.
    fn heard(&self) -> bool {
        self.0.load(Ordering::SeqCst)
    }
}

impl Drop for Listening {
    fn drop(&mut self) {
        LISTENING.store(false, Ordering::SeqCst);
    }
}

fn run(args: RunArgs) -> Outcome {
    run_to(args, &mut Console::Terminal, true)
}

/// [`run`], its lines to `console`, its progress bar shown if `bar_shown` (and not quiet).
fn run_to(args: RunArgs, console: &mut Console, bar_shown: bool) -> Outcome {
    let mut scene = load_scene(args.scene.as_deref())?;
    match args.steps {
        Some(0) => return Err(Failure::new("--steps must be at least 1".into())),
        Some(n) => scene.time.steps = n,
        None => {}
    }
    let out = args.out.unwrap_or_else(|| PathBuf::from("out").join(&scene.name));
    let mut sim = scene.build()?;
    // The run ends at the first error: no step is tried again, and a fifth of the peak
    // stays free.
    sim.set_rollback(false);
    // VTK frames and surface meshes read φ_L's values deep in the liquid.
    if args.vtk || args.surface || scene.output.surface {
        sim.set_interior_values(true);
    }
    if !args.quiet {
        console.err(format!("model: {}", sim.model()));
    }
    for w in sim.warnings() {
        console.err(format!("warning: {w}"));
    }
    let frames = Frames {
        every: scene.output.every,
        particles: scene.output.particles,
        vtk: args.vtk,
        surface: (scene.output.surface || args.surface).then_some(SurfaceFrames {
            samples: scene.output.surface_samples,
            format: scene.output.surface_format,
        }),
    };
    let folder = RunFolder::claim(&out, args.force)?;
    let interrupt = Listening::start();
    let mut rec = RunRecorder::new(folder, &scene.name, frames, &sim)?;
    let bar = bar(
        scene.time.steps,
        args.quiet || !bar_shown,
        "{spinner} {msg} [{bar:30}] step {pos}/{len} ({elapsed} < {eta})",
    );
    bar.set_message(scene.name.clone());
    let mut stopped = None;
    for _ in 0..scene.time.steps {
        if interrupt.heard() {
            let done = sim.steps_taken();
            stopped = Some(Failure {
                message: format!(
                    "interrupted after step {done} of {}; wrote the {done} finished steps to {}",
                    scene.time.steps,
                    out.display()
                ),
                status: 130,
            });
            break;
        }
        match sim.step() {
            Ok(r) => {
                for w in &r.warnings {
                    bar.suspend(|| console.err(format!("warning: {w}")));
                }
                bar.set_message(format!("{} cg {:>3} it", scene.name, r.cg_iterations));
                rec.record(&sim, r)?;
                bar.inc(1);
            }
            Err(e) => {
                stopped = Some(e.into());
                break;
            }
        }
    }
    bar.finish_and_clear();
    let total = rec.finish(stopped.as_ref().map(|f| f.message.as_str()))?;
    if let Some(failure) = stopped {
        return Err(failure);
    }
    let last = rec.reports().last().expect("at least one step");
    console.out(format!(
        "{}: {} steps in {total:.3} s ({} particles, {} liquid cells); final volume {:.4} m³ \
         (start {:.4}), max speed {:.3} m/s; wrote {}",
        scene.name,
        scene.time.steps,
        sim.particles().len(),
        last.liquid_cells,
        last.liquid_volume,
        rec.initial_volume(),
        last.max_speed,
        out.display()
    ));
    Ok(())
}

fn optimize(args: OptimizeArgs) -> Outcome {
    optimize_to(args, &mut Console::Terminal)
}

/// [`optimize`], its lines to `console`.
fn optimize_to(args: OptimizeArgs, console: &mut Console) -> Outcome {
    let mut scene = load_scene(args.scene.as_deref())?;
    match (args.epochs, scene.optimize.as_mut()) {
        (Some(0), _) => return Err(Failure::new("--epochs must be at least 1".into())),
        (Some(n), Some(o)) => o.epochs = n,
        _ => {}
    }
    let out =
        args.out.unwrap_or_else(|| PathBuf::from("out").join(format!("{}-optimize", scene.name)));
    let ck_path = out.join("checkpoint.json");
    let resume = if args.resume { Some(Checkpoint::load(&ck_path)?) } else { None };
    let problem = Optimization::new(scene)?;
    if let Some(done) = resume.as_ref().map(|c| c.next_epoch).filter(|&n| n >= problem.epochs) {
        let asked = match args.epochs {
            Some(n) => format!("--epochs {n} counts every epoch, those before it too"),
            None => format!("optimize.epochs is {}", problem.epochs),
        };
        return Err(Failure::new(format!(
            "the checkpoint has run {done} epochs already and {asked}: give --epochs more than \
             {done} to go on"
        )));
    }
    let _lock = RunFolder::lock(&out)?;
    let start = Instant::now();
    let bar =
        bar(problem.epochs, args.quiet, "{msg} [{bar:30}] epoch {pos}/{len} ({elapsed} < {eta})");
    bar.set_position(resume.as_ref().map(|c| c.next_epoch).unwrap_or(0) as u64);
    let outcome = problem.run(Some(&ck_path), resume, |r| {
        bar.set_message(format!(
            "loss {:.4e} |g| {:.3e} ({} evaluations)",
            r.loss, r.grad_norm, r.evaluations
        ));
        bar.inc(1);
    })?;
    bar.finish_and_clear();
    write_optimization(&problem, &outcome, &out, start.elapsed().as_secs_f64(), args.vtk)?;
    if let Some(reason) = &outcome.stopped {
        return Err(Failure::new(format!("optimisation stopped at {reason}")));
    }
    if let Some(reason) = &outcome.converged {
        console.out(format!("L-BFGS converged at {reason}"));
    }
    let initial = outcome.history.first().map(|r| r.loss).unwrap_or(f64::NAN);
    console.out(format!(
        "{}: {} epochs ({} evaluations), loss {initial:.4e} -> {:.4e} ({:.0}x) in {:.1} s; v0 = {:?}; wrote {}",
        problem.scene.name,
        outcome.history.len(),
        outcome.evaluations,
        outcome.final_loss,
        initial / outcome.final_loss,
        start.elapsed().as_secs_f64(),
        outcome.params.v.to_array(),
        out.display()
    ));
    Ok(())
}

fn gradcheck_cmd(args: GradcheckArgs) -> Outcome {
    let mut scene = match args.scene.as_deref() {
        None => Scene::builtin("gradcheck_box")?,
        Some(p) => load_scene(Some(p))?,
    };
    if args.frozen {
        scene = scene.with_frozen_surface();
    }
    let surface = if scene.solver.freeze_surface { "surface held fixed" } else { "surface moving" };
    for (name, x) in [("--eps", args.eps), ("--rtol", args.rtol), ("--atol", args.atol)] {
        if !(x.is_finite() && x >= 0.0) || (name == "--eps" && x == 0.0) {
            return Err(Failure::new(format!("{name} must be a positive number, got {x}")));
        }
    }
    let loss = scene.loss().ok_or_else(|| diffluid::Error::InvalidScene {
        origin: scene.name.clone(),
        message: "gradcheck needs a [loss] section naming a body and its targets".into(),
    })?;
    let sim = scene.build()?;
    let settings = GradcheckSettings {
        eps: args.eps,
        rtol: args.rtol,
        atol: args.atol,
        compare_paper: scene.control.is_none(),
        options: diffluid::gradients::GradientOptions {
            through_contact: scene.through_contact(),
            ..Default::default()
        },
    };
    let report = match (scene.schedule(&sim), scene.trajectory_loss()) {
        (Some(schedule), Some(terms)) => diffluid::gradients::gradcheck_controlled(
            &sim,
            &schedule?,
            &terms,
            &settings,
            args.actions,
        )?,
        _ => gradcheck(&sim, scene.time.steps, &loss, &settings)?,
    };
    if args.json {
        let mut json = report.to_json();
        json["scene"] = scene.name.clone().into();
        println!("{}", serde_json::to_string_pretty(&json).expect("serialisable"));
    } else {
        println!(
            "{}: loss {:.6e} after {} steps ({surface}); forward {:.3} s, backward {:.3} s, tape {} kB/step",
            scene.name,
            report.loss,
            report.steps,
            report.forward_seconds,
            report.backward_seconds,
            report.tape_bytes_per_step / 1024
        );
        print!("{report}");
    }
    if !report.passed() {
        let kinks = report.params.iter().filter(|r| r.kink && !r.pass).count();
        let at_kinks = if kinks > 0 {
            format!("; {kinks} of the failing parameters sit at a kink of the map (see above)")
        } else {
            String::new()
        };
        return Err(Failure::new(format!(
            "gradient check failed: worst relative error {:.2e} (criterion |adjoint − fd| ≤ {:e} + {:e}·|fd|){at_kinks}",
            report.worst_rel_error(),
            args.atol,
            args.rtol
        )));
    }
    Ok(())
}

fn bench(args: BenchArgs) -> Outcome {
    let bar = bar(
        if args.only.is_some() { 1 } else { 6 },
        false,
        "{bar:30} {pos}/{len} {msg} [{elapsed}]",
    );
    let lines = write_bench(&args.out, args.quick, args.only, |study| {
        if bar.position() > 0 || !bar.message().is_empty() {
            bar.inc(1);
        }
        bar.set_message(study.to_string());
    })?;
    bar.finish_and_clear();
    println!("{}\nwrote {}", lines.join("\n"), args.out.display());
    Ok(())
}

/// glibc's malloc, tuned for a few large arrays made again every step, the largest on huge
/// pages (see [`GridAllocator`]).
#[global_allocator]
static ALLOCATOR: GridAllocator = GridAllocator;

/// Where a command's lines go: the terminal at once, or kept to be printed later in order.
enum Console {
    Terminal,
    Kept(Vec<(bool, String)>),
}

impl Console {
    /// A line for standard output.
    fn out(&mut self, line: String) {
        match self {
            Console::Terminal => println!("{line}"),
            Console::Kept(lines) => lines.push((true, line)),
        }
    }

    /// A line for standard error.
    fn err(&mut self, line: String) {
        match self {
            Console::Terminal => eprintln!("{line}"),
            Console::Kept(lines) => lines.push((false, line)),
        }
    }

    /// Prints the lines kept, in order.
    fn print(self) {
        if let Console::Kept(lines) = self {
            let mut terminal = Console::Terminal;
            for (out, line) in lines {
                if out {
                    terminal.out(line)
                } else {
                    terminal.err(line)
                }
            }
        }
    }
}

/// The main job: the embedded block drop forward (`run`), and its optimisation (`optimize`).
/// Neither reads the other's results, and each steps on one thread (the grid is small), so
/// the run goes on a thread of its own while the optimisation runs here. Their lines come
/// out as if one ran after the other: the run's first, kept until both are done (its
/// progress bar not drawn). A failed or interrupted run ends the process at once, as it
/// ended the job before the optimisation started.
fn main_job() -> Outcome {
    // Its own one-thread pool: the run's serial steps would otherwise queue behind the
    // optimisation's on the library's one (`math::pool`).
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .thread_name(|_| "diffluid-run".into())
        .build()
        .ok();
    std::thread::scope(|s| {
        let forward = s.spawn(|| {
            let run = || {
                let mut console = Console::Kept(Vec::new());
                (run_to(RunArgs::default(), &mut console, false), console)
            };
            let (outcome, console) = match &pool {
                Some(pool) => pool.install(run),
                None => run(),
            };
            if let Err(Failure { message, status }) = outcome {
                console.print();
                eprintln!("error: {message}");
                std::process::exit(status.into());
            }
            console
        });
        let mut console = Console::Kept(Vec::new());
        let optimised = optimize_to(OptimizeArgs::default(), &mut console);
        forward.join().expect("the run returned or ended the process").print();
        console.print();
        optimised
    })
}

fn main() -> ExitCode {
    // Before rayon starts its threads.
    GridAllocator::tune();
    let result = match Cli::parse().command {
        Some(Command::Run(args)) => run(args),
        Some(Command::Gradcheck(args)) => gradcheck_cmd(args),
        Some(Command::Optimize(args)) => optimize(args),
        Some(Command::Control(args)) => control(args),
        Some(Command::Bench(args)) => bench(args),
        Some(Command::Render(args)) => render(args),
        None => main_job(),
    };
    if let Err(Failure { message, status }) = result {
        eprintln!("error: {message}");
        return ExitCode::from(status);
    }
    ExitCode::SUCCESS
}
