//! What `diffluid run` writes (feature `csv`) into its [`RunFolder`]: per frame the marker
//! particles (PLY) and each body's surface (PLY), optionally ParaView frames (feature
//! `vtk`); `bodies.csv` (one row per step and body), appended and flushed as each step ends;
//! and `summary.json` (the run and every step's report), written at the start, again every
//! few seconds while the run goes, and at its end with how it ended. A run that fails, is
//! interrupted or is killed part-way leaves the frames and body rows of every step it
//! finished, and a summary of them (of all of them unless it was killed).

use crate::error::{Error, Result};
use crate::geometry::mesh::placed_surface;
pub use crate::io::folder::RunFolder;
use crate::io::output::{
    check_body_names, write_json, write_ply_mesh, write_ply_points, MeshFormat,
};
use crate::world::{Simulation, StepReport};
use serde::Serialize;
use std::path::Path;
use std::time::{Duration, Instant};

/// One row of `bodies.csv`: a body's state at the end of a step (row 0: the initial state).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BodyRow {
    /// Step, from 0.
    pub step: usize,
    /// Simulated time, s.
    pub time: f64,
    /// Body name.
    pub body: String,
    /// Centre of mass.
    pub x: f64,
    /// Centre of mass.
    pub y: f64,
    /// Centre of mass.
    pub z: f64,
    /// Orientation of the shape frame.
    pub qw: f64,
    /// Orientation.
    pub qx: f64,
    /// Orientation.
    pub qy: f64,
    /// Orientation.
    pub qz: f64,
    /// Linear velocity.
    pub vx: f64,
    /// Linear velocity.
    pub vy: f64,
    /// Linear velocity.
    pub vz: f64,
    /// Angular velocity (world).
    pub wx: f64,
    /// Angular velocity.
    pub wy: f64,
    /// Angular velocity.
    pub wz: f64,
}

/// `summary.json`.
#[derive(Serialize)]
struct Summary<'a> {
    scene: &'a str,
    grid: [usize; 3],
    dx: f64,
    dt: f64,
    particles: usize,
    initial_liquid_volume: f64,
    total_seconds: f64,
    /// `running` (the run goes on, or was killed), `complete` or `stopped`.
    status: &'static str,
    /// Why the run stopped before its last step (a failed step, an interrupt).
    #[serde(skip_serializing_if = "Option::is_none")]
    stopped: Option<&'a str>,
    steps: &'a [StepReport],
}

/// The shortest time between two writes of `summary.json` while a run goes; longer when a
/// write takes more than a twentieth of it (a long run's summary grows with its steps).
const SUMMARY_EVERY: Duration = Duration::from_secs(2);

/// Which frames a run writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Frames {
    /// Every this many steps (frame 0 is the initial state).
    pub every: usize,
    /// The marker particles as PLY.
    pub particles: bool,
    /// ParaView frames under `vtk/` (needs the `vtk` feature).
    pub vtk: bool,
    /// The liquid's surface mesh under `surface/` (and in the ParaView frames), when the
    /// `surface` feature is on; without it, asking for one is an error.
    pub surface: Option<SurfaceFrames>,
}

/// How a run writes the liquid's surface.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SurfaceFrames {
    /// Distance samples per cell along each axis (see `liquid_mesh::liquid_surface`).
    pub samples: usize,
    /// The file format.
    pub format: MeshFormat,
}

/// Records a run into a folder.
pub struct RunRecorder {
    folder: RunFolder,
    name: String,
    frames: Frames,
    #[cfg(feature = "vtk")]
    vtk: Option<crate::io::vtk::VtkSeries>,
    /// `bodies.csv`, made with the first body's row.
    rows: Option<csv::Writer<std::fs::File>>,
    reports: Vec<StepReport>,
    initial_volume: f64,
    grid: crate::geometry::grid::Grid,
    dt: f64,
    particles: usize,
    started: Instant,
    /// When `summary.json` was last written, and how long that took.
    summary_written: (Instant, Duration),
}

impl RunRecorder {
    /// A recorder of the run `name` into `folder` (see [`RunFolder::claim`]); writes frame 0
    /// of `sim` and a summary of no steps.
    pub fn new(
        folder: RunFolder,
        name: &str,
        frames: Frames,
        sim: &Simulation,
    ) -> Result<RunRecorder> {
        if frames.surface.is_some() && !cfg!(feature = "surface") {
            return Err(crate::error::Error::InvalidSettings {
                key: "output.surface".into(),
                message: crate::io::output::SURFACE_FEATURE_MISSING.into(),
            });
        }
        let out = folder.path().to_path_buf();
        let now = Instant::now();
        let mut r = RunRecorder {
            folder,
            name: name.into(),
            frames,
            #[cfg(feature = "vtk")]
            vtk: frames.vtk.then(|| crate::io::vtk::VtkSeries::new(&out.join("vtk"), name)),
            rows: None,
            reports: Vec::new(),
            initial_volume: sim.liquid_volume(),
            grid: *sim.grid(),
            dt: sim.dt(),
            particles: sim.particles.len(),
            started: now,
            summary_written: (now, Duration::ZERO),
        };
        r.frame(sim, 0)?;
        r.write_summary(None)?;
        r.started = Instant::now();
        Ok(r)
    }

    /// The output folder.
    pub fn out(&self) -> &Path {
        self.folder.path()
    }

    fn frame(&mut self, sim: &Simulation, n: usize) -> Result<()> {
        check_body_names(sim.bodies().iter().map(|b| b.name.as_str()))?;
        let out = self.folder.path().to_path_buf();
        for b in sim.bodies() {
            let q = b.q;
            let row = BodyRow {
                step: n,
                time: sim.time(),
                body: b.name.clone(),
                x: b.x.x,
                y: b.x.y,
                z: b.x.z,
                qw: q.w,
                qx: q.x,
                qy: q.y,
                qz: q.z,
                vx: b.v.x,
                vy: b.v.y,
                vz: b.v.z,
                wx: b.w.x,
                wy: b.w.y,
                wz: b.w.z,
            };
            let path = out.join("bodies.csv");
            let fail = |e: csv::Error| Error::Write {
                path: path.clone(),
                source: std::io::Error::other(e.to_string()),
            };
            let rows = match &mut self.rows {
                Some(w) => w,
                None => {
                    let file = std::fs::File::create(&path)
                        .map_err(|source| Error::Write { path: path.clone(), source })?;
                    self.rows.insert(csv::Writer::from_writer(file))
                }
            };
            rows.serialize(row).map_err(fail)?;
        }
        if let Some(w) = &mut self.rows {
            w.flush().map_err(|source| Error::Write { path: out.join("bodies.csv"), source })?;
        }
        if n % self.frames.every != 0 {
            return Ok(());
        }
        #[cfg(feature = "vtk")]
        if let Some(v) = self.vtk.as_mut() {
            v.write_frame(sim, n)?;
        }
        #[cfg(feature = "surface")]
        if let Some(s) = self.frames.surface {
            let mesh = crate::io::liquid_mesh::liquid_surface(sim, s.samples);
            let file = format!("{n:04}.{}", s.format.extension());
            s.format.write(&out.join("surface").join(file), &mesh.vertices, &mesh.triangles)?;
            #[cfg(feature = "vtk")]
            if let Some(v) = self.vtk.as_mut() {
                v.write_surface(sim.time(), n, &mesh.vertices, &mesh.triangles)?;
            }
        }
        if self.frames.particles {
            write_ply_points(&out.join("particles").join(format!("{n:04}.ply")), &sim.particles)?;
        }
        for b in sim.bodies() {
            let mesh = placed_surface(&b.shape, &b.pose());
            write_ply_mesh(
                &out.join("bodies").join(format!("{}_{n:04}.ply", b.name)),
                &mesh.vertices,
                &mesh.triangles,
            )?;
        }
        Ok(())
    }

    /// Records the step `report` that brought `sim` to its state: its frame, its body rows,
    /// and now and then the summary.
    pub fn record(&mut self, sim: &Simulation, report: StepReport) -> Result<()> {
        self.frame(sim, report.step)?;
        self.reports.push(report);
        self.particles = sim.particles.len();
        let (at, took) = self.summary_written;
        if at.elapsed() >= SUMMARY_EVERY.max(20 * took) {
            self.write_summary(None)?;
        }
        Ok(())
    }

    /// The reports so far.
    pub fn reports(&self) -> &[StepReport] {
        &self.reports
    }

    /// The liquid volume at the start, m³.
    pub fn initial_volume(&self) -> f64 {
        self.initial_volume
    }

    /// Writes `summary.json` with every step recorded: `stopped` says why the run ended
    /// before its last step (a failed step, an interrupt), None that it is complete. Returns
    /// the wall time of the stepping loop so far, s.
    pub fn finish(&mut self, stopped: Option<&str>) -> Result<f64> {
        self.write_summary(Some(stopped))
    }

    /// `summary.json`: `end` None while the run goes, `Some(stopped)` at its end. Returns the
    /// `total_seconds` it holds.
    fn write_summary(&mut self, end: Option<Option<&str>>) -> Result<f64> {
        let clock = Instant::now();
        let total_seconds = self.started.elapsed().as_secs_f64();
        let (status, stopped) = match end {
            None => ("running", None),
            Some(None) => ("complete", None),
            Some(Some(why)) => ("stopped", Some(why)),
        };
        write_json(
            &self.folder.path().join("summary.json"),
            &Summary {
                scene: &self.name,
                grid: self.grid.n,
                dx: self.grid.dx,
                dt: self.dt,
                particles: self.particles,
                initial_liquid_volume: self.initial_volume,
                total_seconds,
                status,
                stopped,
                steps: &self.reports,
            },
        )?;
        self.summary_written = (Instant::now(), clock.elapsed());
        Ok(total_seconds)
    }
}
