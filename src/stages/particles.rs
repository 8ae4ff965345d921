//! The marker particles' stages, written once for both directions:
//! [`AdvectParticles`](super::Stage::AdvectParticles) (through the step's start velocity,
//! then pushed out of the bodies) and [`Density`](super::Stage::Density) (the density
//! projection, then pushed out again). The backward pass replays them from the record with
//! the same [`ParticleStage`], then runs their adjoints.

use crate::error::{Error, Result, Solve};
use crate::geometry::body::RigidBody;
use crate::geometry::fractions::{DualFaces, NodeSdf};
use crate::geometry::grid::{Grid, Mac};
use crate::geometry::weights::FaceWeights;
use crate::math::Twist;
use crate::math::Vec3;
use crate::stages::band::BandChange;
use crate::stages::density::{self, DensityInputs, DensityProjection, DensityStats, Displacement};
use crate::stages::surface::{self, Pockets};

/// What the particle stages leave for the backward pass: the positions they started from
/// and after advection, the sub-steps and the density projection's potential; the rest (the
/// push out of the bodies, the density system, the displacement, the positions after it) is
/// replayed ([`ParticleStage::replay`]).
#[derive(Clone, Debug)]
pub struct ParticleRecord {
    /// Positions at the start of the step.
    pub start: Vec<Vec3>,
    /// Sub-steps of the advection.
    pub substeps: usize,
    /// Positions after advection, before the push out of the bodies (which the backward
    /// pass replays: it is cheap, and its adjoint reads the positions before it).
    pub moved: Vec<Vec3>,
    /// The density projection's potential q of each pass that found a cell over full (none
    /// when it is off).
    pub density: Vec<Vec<f64>>,
    /// Per cell, the particle (at the end of the step) whose distance the step's φ_L is
    /// (`NONE` where φ does not move with a particle).
    pub nearest: Vec<u32>,
    /// The cells the closing of air pockets changed in the step's φ_L (empty when it is
    /// off).
    pub pockets: Pockets,
    /// What the narrow band's update before the advection did to the particle list
    /// (`start` is the list after it); None without a band.
    pub change: Option<BandChange>,
    /// The narrow band's deep cells that the step's density projection and φ_L read (the
    /// rest of the band, its deposit, is a function of them).
    pub deep: Option<Vec<bool>>,
}

/// The particle stages of one step: what they read.
pub struct ParticleStage<'a> {
    /// The grid.
    pub grid: &'a Grid,
    /// The step's Δt.
    pub dt: f64,
    /// The advecting field: the fluid velocity at the start of the step.
    pub u: &'a Mac,
    /// The bodies at the start of the step (the push-outs').
    pub bodies: &'a [RigidBody],
    /// The static solids' signed distance at the nodes (advection keeps out of them).
    pub node_sdf: &'a NodeSdf,
    /// How far out of a body a particle is pushed.
    pub margin: f64,
    /// The density projection's inputs (None when it is off).
    pub density: Option<DensityInputs<'a>>,
    /// The step's number.
    pub step: usize,
}

/// A recorded run's next density projection pass: its potential (None for a pass that found
/// no cell over full, which ended the passes) and iterations.
pub type NextPass<'a> = dyn FnMut() -> Result<(Option<Vec<f64>>, usize)> + 'a;

/// Where the density projection's potentials come from.
pub enum Potential<'a> {
    /// Solved.
    Solve,
    /// A recorded run's potentials and iterations, handed out pass by pass, for its re-run
    /// (a checkpointed segment).
    Recorded(&'a mut NextPass<'a>),
    /// The step's recorded potentials (one per pass that acted), in the backward pass's
    /// replay: each pass's system is built with its adjoint's inputs and kept.
    Replay(Vec<Vec<f64>>),
}

/// One density projection pass as the backward pass's replay keeps it: the system, its
/// potential, its displacement and the positions it was built from.
pub struct KeptPass {
    /// The pass's system.
    pub proj: DensityProjection,
    /// Its recorded potential.
    pub q: Vec<f64>,
    /// Its displacement.
    pub disp: Displacement,
    /// The positions it was built from and moved.
    pub before: Vec<Vec3>,
}

/// What [`ParticleStage::settle`] did.
#[derive(Default)]
pub struct Settled {
    /// The projection's statistics (the first pass's excess, every pass's iterations).
    pub stats: DensityStats,
    /// Each pass's potential and iterations, in order (None for a pass that found no
    /// over-full cell, which ends them; empty when the projection is off or replayed).
    pub passes: Vec<(Option<Vec<f64>>, usize)>,
    /// In a replay: each pass that acted, and the positions after the last (before the
    /// second push-out).
    pub kept: Option<(Vec<KeptPass>, Vec<Vec3>)>,
}

impl Settled {
    /// Up to `passes` passes of `pass` on `particles`, each on the positions the last left,
    /// until one finds no cell over full; what they did is added to `self`.
    fn run_passes(
        &mut self,
        particles: &mut [Vec3],
        passes: usize,
        mut pass: impl FnMut(&mut [Vec3]) -> Result<(DensityStats, Option<Vec<f64>>)>,
    ) -> Result<()> {
        for _ in 0..passes {
            let (stats, q) = pass(particles)?;
            if self.passes.is_empty() {
                self.stats.excess_volume = stats.excess_volume;
            }
            self.stats.cg_iterations += stats.cg_iterations;
            let acted = q.is_some();
            self.passes.push((q, stats.cg_iterations));
            if !acted {
                break;
            }
        }
        Ok(())
    }

    /// The potentials of the passes that acted, for the step's record.
    pub fn into_potentials(self) -> Vec<Vec<f64>> {
        self.passes.into_iter().filter_map(|(q, _)| q).collect()
    }
}

/// The particle stages replayed from a record: the positions each part started from.
pub struct Replayed {
    /// After advection and the first push-out (the density projection's input).
    pub advected: Vec<Vec3>,
    /// After the whole stage (φ_L's input).
    pub end: Vec<Vec3>,
    /// The density projection as it acted.
    pub settled: Settled,
}

impl ParticleStage<'_> {
    /// The advection's sub-steps: `asked` (0 for as many as the field needs), at least as
    /// many as it needs.
    pub fn substeps(&self, asked: usize) -> usize {
        let needed = surface::advect_substeps(self.u, self.grid, self.dt);
        match asked {
            0 => needed,
            n => n.max(needed),
        }
    }

    /// [`AdvectParticles`](super::Stage::AdvectParticles): the particles through the start
    /// velocity in `substeps`, then pushed out of the bodies. Returns the positions before
    /// the push when `keep` (the record's `moved`).
    pub fn advect(&self, particles: &mut [Vec3], substeps: usize, keep: bool) -> Option<Vec<Vec3>> {
        surface::advect_substepped(particles, self.u, self.grid, self.dt, substeps, self.node_sdf);
        let moved = keep.then(|| particles.to_vec());
        self.push(particles);
        moved
    }

    /// [`Density`](super::Stage::Density): the density projection's passes (`g.passes`,
    /// each on the positions the last left; a pass that finds no over-full cell ends them),
    /// their potentials from `potential`, then the push out of the bodies again (nothing
    /// when it is off).
    pub fn settle(&self, particles: &mut [Vec3], potential: Potential<'_>) -> Result<Settled> {
        let Some(g) = &self.density else { return Ok(Settled::default()) };
        let step = self.step;
        let mut settled = Settled::default();
        match potential {
            Potential::Solve => {
                settled.run_passes(particles, g.passes, |p| density::correct(p, g, step))?;
            }
            Potential::Recorded(next) => {
                settled.run_passes(particles, g.passes, |p| {
                    density::correct_replayed(p, g, next()?, step)
                })?;
            }
            Potential::Replay(qs) => {
                let mut kept = Vec::with_capacity(qs.len());
                for q in qs {
                    let Some(proj) = DensityProjection::build(particles, g) else {
                        return Err(crate::error::GradientError::NotDeterministic {
                            step,
                            what: "found no cell over full where its forward pass did".into(),
                        }
                        .into());
                    };
                    let before = particles.to_vec();
                    let disp = proj.displacement(&q, g);
                    proj.displace_by(particles, &disp, g);
                    kept.push(KeptPass { proj, q, disp, before });
                }
                if !kept.is_empty() {
                    settled.kept = Some((kept, particles.to_vec()));
                }
            }
        }
        self.push(particles);
        Ok(settled)
    }

    /// The particle stages of `rec`'s step replayed from its record.
    pub fn replay(&self, rec: &ParticleRecord) -> Result<Replayed> {
        let mut advected = rec.moved.clone();
        self.push(&mut advected);
        let mut end = advected.clone();
        let settled = self.settle(&mut end, Potential::Replay(rec.density.clone()))?;
        Ok(Replayed { advected, end, settled })
    }

    /// Adjoint of [`ParticleStage::settle`] (its replay `replayed`): ∂L/∂(positions after) in
    /// `pbar` becomes ∂L/∂(positions before); the bodies' ∂L/∂[δx; δθ] through the push-out
    /// and the density system's weights (given each body's dual fractions, `dual_faces`,
    /// with the static weights `statics`) is added to `pose`. Gives the replay's system
    /// back.
    pub fn settle_adjoint(
        &self,
        replayed: Replayed,
        pbar: &mut [Vec3],
        pose: &mut [Twist],
        dual_faces: &[DualFaces],
        statics: &FaceWeights,
    ) -> Result<()> {
        let Some(g) = &self.density else { return Ok(()) };
        let fd = surface::jacobian_step(self.grid);
        let Some((kept, displaced)) = replayed.settled.kept else {
            // No projection: the second push-out from the advected positions.
            let push = surface::push_out_of_bodies_adjoint(
                &replayed.advected,
                pbar,
                self.bodies,
                self.margin,
                fd,
            );
            add_pose(pose, push);
            return Ok(());
        };
        let push =
            surface::push_out_of_bodies_adjoint(&displaced, pbar, self.bodies, self.margin, fd);
        add_pose(pose, push);
        // The passes in reverse, each taking ∂L/∂(its positions after) to ∂L/∂(before).
        for KeptPass { proj, q, disp, before } in kept.into_iter().rev() {
            let (s, stats, ramp_bar) = proj.adjoint_with(&before, &q, &disp, pbar, pose, g);
            if !stats.converged {
                return Err(Error::NotConverged {
                    solve: Solve::DensityAdjoint,
                    step: self.step,
                    iterations: stats.iterations,
                    residual: stats.relative_residual,
                    tolerance: g.solve.tolerance,
                });
            }
            let weight_bar = WeightBar { s: &s, ramp: &ramp_bar };
            density_weight_pose(&proj, &q, weight_bar, g, dual_faces, statics, pose);
            g.give_back(None, Some(disp.d));
            proj.give_back(g);
        }
        Ok(())
    }

    /// Adjoint of [`ParticleStage::advect`]: ∂L/∂(positions after the push-out) in `pbar`
    /// becomes ∂L/∂(start positions); ∂L/∂u of the start velocity is added to `ubar` and the
    /// bodies' ∂L/∂[δx; δθ] through the push-out to `pose`.
    pub fn advect_adjoint(
        &self,
        rec: &ParticleRecord,
        pbar: &mut [Vec3],
        ubar: &mut Mac,
        pose: &mut [Twist],
    ) {
        let fd = surface::jacobian_step(self.grid);
        let push =
            surface::push_out_of_bodies_adjoint(&rec.moved, pbar, self.bodies, self.margin, fd);
        add_pose(pose, push);
        surface::advect_adjoint(
            &rec.start,
            pbar,
            self.u,
            self.grid,
            self.dt,
            rec.substeps,
            self.node_sdf,
            ubar,
        );
    }

    /// Pushes the particles out of the bodies.
    fn push(&self, particles: &mut [Vec3]) {
        surface::push_out_of_bodies(particles, self.bodies, self.margin);
    }
}

/// pose += g, body by body.
fn add_pose(pose: &mut [Twist], g: Vec<Twist>) {
    for (p, g) in pose.iter_mut().zip(g) {
        for d in 0..6 {
            p[d] += g[d];
        }
    }
}

/// ∂L/∂(the density operator's weights), in the two parts the adjoint leaves them: the
/// adjoint solve's solution `s` (through the operator) and the face ramp's faded faces
/// (axis, face, ∂L/∂w; sorted).
struct WeightBar<'a> {
    s: &'a [f64],
    ramp: &'a [(usize, u32, f64)],
}

/// The density system's part of the pose derivative: its weights lose what a body covers,
/// so −sᵀ·δA·q = Σ_f ∂β_f/∂pose · Δt·dx/ρ·θ·(g·s)(g·q) over the faces the body covers in
/// part (inside the clamp of w = w_static − β).
fn density_weight_pose(
    proj: &DensityProjection,
    q: &[f64],
    bar: WeightBar<'_>,
    g: &DensityInputs<'_>,
    dual_faces: &[DualFaces],
    statics: &FaceWeights,
    pose: &mut [Twist],
) {
    // A face the projection closed at a deep cell does not see the body.
    let weights = proj.weights(g);
    let ramp = |axis: usize, f: usize| {
        let key = (axis, f as u32);
        bar.ramp.binary_search_by_key(&key, |r| (r.0, r.1)).map_or(0.0, |k| bar.ramp[k].2)
    };
    for (i, faces) in dual_faces.iter().enumerate() {
        for (axis, list) in faces.iter().enumerate() {
            for (f, beta) in list {
                let raw = statics.weight(axis, *f) - beta.v;
                if !(raw > 0.0 && raw < 1.0 && weights.weight(axis, *f) > 0.0) {
                    continue;
                }
                let w = proj.sys.weight_adjoint(axis, *f, weights, &proj.phi, bar.s, q)
                    - ramp(axis, *f);
                for k in 0..6 {
                    pose[i][k] += beta.d[k] * w;
                }
            }
        }
    }
}
