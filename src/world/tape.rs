//! What a taped forward step leaves for the backward pass: only what cannot be recomputed
//! cheaply. The step's geometry, operator and masks are rebuilt from the body states by the
//! same [`crate::world::StepSystem::assemble`] the forward step used; the pressure needs a
//! solve, so it is stored.

use crate::error::{Error, GradientError, Result};
use crate::geometry::body::BodyState;
use crate::geometry::fractions::BodyFaces;
use crate::geometry::grid::Mac;
use crate::math::Twist;
use crate::solvers::cg::CgStats;
use crate::stages::extrapolate::AirBodyFaces;
pub use crate::stages::particles::ParticleRecord;
use crate::stages::project::HeldSolve;

/// One forward step's record.
#[derive(Clone, Debug)]
pub struct StepRecord {
    /// Fluid velocity at the start of the step (advection's input).
    pub u: Mac,
    /// Bodies at the start of the step.
    pub bodies: Vec<BodyState>,
    /// Each coupled body's [v; ω] as the solve saw it before the pressure acted: the start
    /// velocity with gravity, the external force and the contact kick (the rigid velocity
    /// the projection's right-hand side reads). One per body that [`RigidBody::moves`].
    ///
    /// [`RigidBody::moves`]: crate::geometry::body::RigidBody::moves
    pub v_hat: Vec<Twist>,
    /// Each body's [v; ω] after the pressure solve (the rigid integration's input).
    pub v_after: Vec<Twist>,
    /// Pressure per liquid cell.
    pub p: Vec<f64>,
    /// Particle φ_L of the step (empty when the surface is frozen: the initial one).
    pub phi: Vec<f64>,
    /// Each body's face fractions at the start of the step (a few kB; recomputing them cost
    /// 4% of the backward pass).
    pub body_faces: Vec<BodyFaces>,
    /// Each body's external force and torque in the step, [f; τ] (the `forces` stage reads
    /// them; a per-step action changes them from step to step).
    pub loads: Vec<Twist>,
    /// The fluid velocity the correction extrapolated onto the faces the bodies cover in part
    /// that the projection did not update, before it mixed in the bodies' part (see
    /// [`correct_with_bodies`]).
    ///
    /// [`correct_with_bodies`]: crate::stages::extrapolate::correct_with_bodies
    pub air_body_faces: AirBodyFaces,
    /// Whether rapier contact acted in this step (a kick in the solve, or the contact
    /// integration): the gradient then goes through rapier's step.
    pub contact: bool,
    /// Whether rapier integrated the bodies ([`Stage::Rigid`](crate::stages::Stage::Rigid)
    /// through contact).
    pub rigid_contact: bool,
    /// The solves of the step's contact iteration before the one that stood (see
    /// [`crate::stages::project::Projection::held`]).
    pub held: Vec<HeldSolve>,
    /// The marker particles' stage (None when the surface is frozen).
    pub particles: Option<ParticleRecord>,
    /// Whether the step's solve had volume control's sources (see `solver.volume_control`).
    pub volume_control: bool,
}

/// The recorded forward pass.
#[derive(Clone, Debug, Default)]
pub struct Tape {
    /// One record per step.
    pub steps: Vec<StepRecord>,
}

impl Tape {
    /// Bytes stored per step (mean over the tape).
    pub fn bytes_per_step(&self) -> usize {
        if self.steps.is_empty() {
            return 0;
        }
        let total: usize = self
            .steps
            .iter()
            .map(|s| {
                8 * (s.u.c.iter().map(Vec::len).sum::<usize>() + s.p.len() + s.phi.len())
                    + s.held.iter().map(|h| 8 * h.p.len() + 96 * h.v_hat.len()).sum::<usize>()
                    + s.bodies.len() * std::mem::size_of::<BodyState>()
                    + (s.v_after.len() + s.v_hat.len()) * 48
                    + s.body_faces
                        .iter()
                        .map(|b| b.faces.iter().map(Vec::len).sum::<usize>() * 16)
                        .sum::<usize>()
                    + s.particles.as_ref().map_or(0, |r| {
                        24 * (r.start.len() + r.moved.len())
                            + 8 * r.density.iter().map(Vec::len).sum::<usize>()
                            + 4 * r.nearest.len()
                            + r.change.as_ref().map_or(0, |c| 4 * c.kept.len())
                            + r.deep.as_ref().map_or(0, Vec::len)
                    })
            })
            .sum();
        total / self.steps.len()
    }

    /// Whether contact acted in any step.
    pub fn through_contact(&self) -> bool {
        self.steps.iter().any(|s| s.contact)
    }
}

/// What a run of untaped steps solved for, in order: the pressures (each contact iteration's
/// solve its own) and, with the surface moving, the density projections' potentials. A
/// checkpointed forward pass keeps it for each segment besides its start state, so that
/// re-running the segment in the backward pass takes them instead of solving again. The
/// forward map is deterministic, so a re-run from the same state asks for the same solves and
/// what it takes is what it would have solved, to the bit. 8 bytes a liquid cell a step (16
/// with the surface moving).
#[derive(Clone, Debug, Default)]
pub struct Solves {
    solves: Vec<(Vec<f64>, CgStats)>,
    /// Each density projection's potential (None when it found no cell over full) and
    /// iterations.
    density: Vec<(Option<Vec<f64>>, usize)>,
    /// Whether rapier contact acted in any of the steps.
    pub contact: bool,
}

impl Solves {
    /// Keeps one solve's pressure and statistics.
    pub(crate) fn push(&mut self, p: Vec<f64>, stats: CgStats) {
        self.solves.push((p, stats));
    }

    /// Keeps one density projection's potential and iterations.
    pub(crate) fn push_density(&mut self, q: Option<Vec<f64>>, iterations: usize) {
        self.density.push((q, iterations));
    }

    /// A cursor that hands the solves out in order, from the first.
    pub(crate) fn replay(&self) -> Replay<'_> {
        Replay { solves: self, next: 0, next_density: 0 }
    }
}

/// [`Solves`] handed out in order to the steps that re-run them.
#[derive(Debug)]
pub(crate) struct Replay<'a> {
    solves: &'a Solves,
    next: usize,
    next_density: usize,
}

impl Replay<'_> {
    /// The next solve's pressure and statistics, for a system of `rows` unknowns in step
    /// `step`; an error if the re-run asks for a solve its forward pass did not make (the
    /// forward map was not deterministic), rather than a gradient of some other run.
    pub(crate) fn next(&mut self, rows: usize, step: usize) -> Result<(Vec<f64>, CgStats)> {
        match self.solves.solves.get(self.next) {
            Some((p, stats)) if p.len() == rows => {
                self.next += 1;
                Ok((p.clone(), *stats))
            }
            found => Err(GradientError::NotDeterministic {
                step,
                what: format!(
                    "asked for pressure solve {} ({rows} unknowns), which its forward pass {}",
                    self.next + 1,
                    match found {
                        Some((p, _)) => format!("made with {} unknowns", p.len()),
                        None => "did not make".into(),
                    }
                ),
            }
            .into()),
        }
    }

    /// The next density projection's potential and iterations, for step `step`.
    pub(crate) fn next_density(&mut self, step: usize) -> Result<(Option<Vec<f64>>, usize)> {
        let found = self.solves.density.get(self.next_density).cloned().ok_or_else(|| {
            Error::from(GradientError::NotDeterministic {
                step,
                what: "made a density projection its forward pass did not".into(),
            })
        })?;
        self.next_density += 1;
        Ok(found)
    }
}
