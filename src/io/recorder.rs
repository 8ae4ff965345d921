//! What `diffluid run` writes (feature `csv`): per frame the marker particles (PLY) and each
//! body's surface (PLY), optionally ParaView frames (feature `vtk`); at the end `bodies.csv`
//! (one row per step and body) and `summary.json` (the run and every step's report). A run
//! that fails part-way still leaves the summary and body tracks of every step before it.

use crate::error::Result;
use crate::geometry::mesh::placed_surface;
use crate::io::output::{write_csv, write_json, write_ply_mesh, write_ply_points, MeshFormat};
use crate::world::{Simulation, StepReport};
use serde::Serialize;
use std::path::{Path, PathBuf};

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
    steps: &'a [StepReport],
}

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
    out: PathBuf,
    name: String,
    frames: Frames,
    #[cfg(feature = "vtk")]
    vtk: Option<crate::io::vtk::VtkSeries>,
    rows: Vec<BodyRow>,
    reports: Vec<StepReport>,
    initial_volume: f64,
}

impl RunRecorder {
    /// A recorder of the run `name` into `out`; writes frame 0 of `sim`.
    pub fn new(out: &Path, name: &str, frames: Frames, sim: &Simulation) -> Result<RunRecorder> {
        if frames.surface.is_some() && !cfg!(feature = "surface") {
            return Err(crate::error::Error::InvalidSettings {
                key: "output.surface".into(),
                message: crate::io::output::SURFACE_FEATURE_MISSING.into(),
            });
        }
        let mut r = RunRecorder {
            out: out.to_path_buf(),
            name: name.into(),
            frames,
            #[cfg(feature = "vtk")]
            vtk: frames.vtk.then(|| crate::io::vtk::VtkSeries::new(&out.join("vtk"), name)),
            rows: Vec::new(),
            reports: Vec::new(),
            initial_volume: sim.liquid_volume(),
        };
        r.frame(sim, 0)?;
        Ok(r)
    }

    fn frame(&mut self, sim: &Simulation, n: usize) -> Result<()> {
        for b in sim.bodies() {
            let q = b.q;
            self.rows.push(BodyRow {
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
            });
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
            s.format.write(
                &self.out.join("surface").join(file),
                &mesh.vertices,
                &mesh.triangles,
            )?;
            #[cfg(feature = "vtk")]
            if let Some(v) = self.vtk.as_mut() {
                v.write_surface(sim.time(), n, &mesh.vertices, &mesh.triangles)?;
            }
        }
        if self.frames.particles {
            write_ply_points(
                &self.out.join("particles").join(format!("{n:04}.ply")),
                &sim.particles,
            )?;
        }
        for b in sim.bodies() {
            let mesh = placed_surface(&b.shape, &b.pose());
            write_ply_mesh(
                &self.out.join("bodies").join(format!("{}_{n:04}.ply", b.name)),
                &mesh.vertices,
                &mesh.triangles,
            )?;
        }
        Ok(())
    }

    /// Records the step `report` that brought `sim` to its state.
    pub fn record(&mut self, sim: &Simulation, report: StepReport) -> Result<()> {
        self.frame(sim, report.step)?;
        self.reports.push(report);
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

    /// Writes `bodies.csv` (when there are bodies) and `summary.json`, with the stepping
    /// loop's wall time `total_seconds`.
    pub fn finish(&self, sim: &Simulation, total_seconds: f64) -> Result<()> {
        if !sim.bodies().is_empty() {
            write_csv(&self.out.join("bodies.csv"), &self.rows)?;
        }
        let grid = *sim.grid();
        write_json(
            &self.out.join("summary.json"),
            &Summary {
                scene: &self.name,
                grid: grid.n,
                dx: grid.dx,
                dt: sim.dt(),
                particles: sim.particles.len(),
                initial_liquid_volume: self.initial_volume,
                total_seconds,
                steps: &self.reports,
            },
        )
    }
}
