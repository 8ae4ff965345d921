//! A loss and its gradient in one call ([`value_and_gradient`]), and the forward run it
//! differentiates ([`Rollout`]): the whole tape, or checkpoints and the segments between them
//! re-run in the backward pass.

use super::backward::{
    backward_adjoint_hooked, check_differentiable, check_settings, to_gradient, AdjointSeconds,
    GradientOptions,
};
use super::loss::{AdjointState, Gradient, Loss};
use super::schedule::Schedule;
use crate::error::Result;
use crate::geometry::body::{BodyState, RigidBody};
use crate::math::pool::run_spread;
use crate::world::tape::Solves;
use crate::world::{Simulation, Tape};

/// What [`value_and_gradient`] computes and how.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GradientSettings {
    /// The backward pass's options.
    pub options: GradientOptions,
    /// Keep a snapshot every this many steps instead of the whole tape, and re-run one
    /// segment at a time in the backward pass (√N segments keep memory at O(√N) steps). The
    /// segments are counted back from the last step (the first is the short one), and the
    /// last is taped in the forward pass, so it is not re-run. The forward map is
    /// deterministic, so the gradient is bit-identical to the one without.
    pub checkpoint_every: Option<usize>,
    /// With checkpointing, solve again when a segment is re-run (the pressure, and with the
    /// surface moving the density projection), instead of taking what the forward pass kept
    /// (see [`Solves`]: 8 bytes a liquid cell a step, 4 MB a step on `large_tank`, for a
    /// re-run without its solves). For long runs on
    /// large grids, where N pressures outweigh √N snapshots. The gradient is the same bits.
    pub re_solve: bool,
}

impl From<GradientOptions> for GradientSettings {
    fn from(options: GradientOptions) -> Self {
        GradientSettings { options, ..Default::default() }
    }
}

/// A forward run kept for its backward pass: its segments, first to last, each the state it
/// started from and either its tape or (re-run in the backward pass) the pressures it solved
/// for. Without checkpointing it is one taped segment.
#[derive(Debug)]
pub struct Rollout {
    segments: Vec<Segment>,
    last: Simulation,
    /// The actions applied before each step, if any.
    schedule: Option<Schedule>,
    /// Every body's state at every boundary between steps, before that step's actions:
    /// `states[b]` after b steps, b = 0 ..= steps.
    states: Vec<Vec<BodyState>>,
}

/// A stretch of a [`Rollout`].
#[derive(Debug)]
struct Segment {
    /// The state it starts from (without the particles when the surface is frozen).
    start: Simulation,
    /// The run's step its first step is (from 0).
    first: usize,
    steps: usize,
    kept: Kept,
}

/// What a segment keeps of its steps.
#[derive(Debug)]
enum Kept {
    /// Their tape (the last segment, or the whole run without checkpointing).
    Tape(Tape),
    /// Nothing but (unless `re_solve`) their pressures: they are re-run, without solving.
    Rerun(Option<Solves>),
}

impl Rollout {
    /// Runs `steps` steps from `initial`, keeping what the backward pass needs as `settings`
    /// ask (the whole tape, or checkpoints; see [`GradientSettings`]). `initial` is not
    /// changed.
    pub fn run(initial: &Simulation, steps: usize, settings: &GradientSettings) -> Result<Rollout> {
        Rollout::run_with(initial, steps, settings, None)
    }

    /// [`Rollout::run`] with `schedule`'s actions set before each step (its steps, or
    /// `steps` when there is none).
    pub fn run_with(
        initial: &Simulation,
        steps: usize,
        settings: &GradientSettings,
        schedule: Option<&Schedule>,
    ) -> Result<Rollout> {
        let steps = schedule.map_or(steps, Schedule::steps);
        run_spread(initial.spread(), || {
            let every = settings.checkpoint_every.unwrap_or(steps).max(1);
            // Segments end at the last step: the first is the short one, and the last is
            // taped, so the backward pass re-runs every segment but that one.
            let tail =
                if settings.checkpoint_every.is_some() { steps.saturating_sub(every) } else { 0 };
            let mut sim = initial.clone();
            let mut segments = Vec::new();
            let mut states = Vec::with_capacity(steps + 1);
            let mut done = 0;
            let mut before = |sim: &mut Simulation, t: usize| {
                states.push(sim.bodies().iter().map(RigidBody::state).collect());
                if let Some(s) = schedule {
                    s.apply(sim, t);
                }
            };
            while done < steps || segments.is_empty() {
                let start = sim.replay_copy();
                let (len, kept) = if done < tail {
                    let len = match (tail - done) % every {
                        0 => every,
                        short => short,
                    };
                    let mut solves = (!settings.re_solve).then(Solves::default);
                    for t in done..done + len {
                        before(&mut sim, t);
                        match solves.as_mut() {
                            Some(solves) => sim.step_recording(solves)?,
                            None => sim.step_unreported(None)?,
                        };
                    }
                    (len, Kept::Rerun(solves))
                } else {
                    let mut tape = Tape::default();
                    for t in done..steps {
                        before(&mut sim, t);
                        sim.step_unreported(Some(&mut tape))?;
                    }
                    (steps - done, Kept::Tape(tape))
                };
                segments.push(Segment { start, first: done, steps: len, kept });
                done += len;
            }
            states.push(sim.bodies().iter().map(RigidBody::state).collect());
            Ok(Rollout { segments, last: sim, schedule: schedule.cloned(), states })
        })
    }

    /// Every body's state at every boundary between steps, before that step's actions:
    /// `states()[b]` after b steps, b = 0 ..= [`Rollout::steps`].
    pub fn states(&self) -> &[Vec<BodyState>] {
        &self.states
    }

    /// The state the run started from (without the particles when the surface is frozen).
    pub fn initial(&self) -> &Simulation {
        &self.segments[0].start
    }

    /// The state at the end of the run.
    pub fn final_state(&self) -> &Simulation {
        &self.last
    }

    /// Steps run.
    pub fn steps(&self) -> usize {
        self.segments.iter().map(|s| s.steps).sum()
    }

    /// Whether the run can be differentiated with `options` (see [`check_settings`]): an
    /// error at once instead of after a backward pass's re-runs.
    pub fn check(&self, options: &GradientOptions) -> Result<()> {
        for seg in &self.segments {
            match &seg.kept {
                Kept::Tape(tape) => check_differentiable(&seg.start, tape, options)?,
                Kept::Rerun(Some(s)) => check_settings(&seg.start, s.contact, options)?,
                // Contact is found when the segment is re-run.
                Kept::Rerun(None) => check_settings(&seg.start, false, options)?,
            }
        }
        Ok(())
    }

    /// The adjoint of the initial state from `adj`, the adjoint of the final one; the run is
    /// kept, so it can go backward again.
    pub fn backward(
        &self,
        adj: AdjointState,
        options: &GradientOptions,
    ) -> Result<(AdjointState, AdjointSeconds)> {
        self.backward_hooked(adj, options, &mut |_, _| {})
    }

    /// [`Rollout::backward`] that hands the adjoint at every boundary b < steps to
    /// `at_boundary(b, adj)` as the sweep passes it (see
    /// [`super::backward::backward_adjoint_hooked`]).
    pub fn backward_hooked(
        &self,
        adj: AdjointState,
        options: &GradientOptions,
        at_boundary: &mut (dyn FnMut(usize, &mut AdjointState) + Send),
    ) -> Result<(AdjointState, AdjointSeconds)> {
        let mut out = (adj, AdjointSeconds::default(), 0);
        for seg in self.segments.iter().rev() {
            out = seg.backward(out, options, self.schedule.as_ref(), at_boundary)?;
        }
        Ok((out.0, out.1))
    }

    /// [`Rollout::backward`] that drops each segment once it is done (for memory), and
    /// returns the final state and the largest tape held per step, in bytes.
    fn into_backward(
        mut self,
        adj: AdjointState,
        options: &GradientOptions,
    ) -> Result<(AdjointState, AdjointSeconds, usize, Simulation)> {
        let mut out = (adj, AdjointSeconds::default(), 0);
        while let Some(seg) = self.segments.pop() {
            out = seg.backward(out, options, self.schedule.as_ref(), &mut |_, _| {})?;
        }
        Ok((out.0, out.1, out.2, self.last))
    }
}

impl Segment {
    /// From the adjoint at the segment's end (with the time and the largest tape per step so
    /// far), the adjoint at its start: re-runs the segment first when its tape is not kept.
    fn backward(
        &self,
        (adj, mut seconds, bytes): (AdjointState, AdjointSeconds, usize),
        options: &GradientOptions,
        schedule: Option<&Schedule>,
        at_boundary: &mut (dyn FnMut(usize, &mut AdjointState) + Send),
    ) -> Result<(AdjointState, AdjointSeconds, usize)> {
        let rerun;
        let tape = match &self.kept {
            Kept::Tape(tape) => tape,
            Kept::Rerun(solves) => {
                let mut sim = self.start.clone();
                let mut tape = Tape::default();
                let mut replay = solves.as_ref().map(Solves::replay);
                for t in self.first..self.first + self.steps {
                    if let Some(s) = schedule {
                        s.apply(&mut sim, t);
                    }
                    match replay.as_mut() {
                        Some(replay) => sim.step_replayed(&mut tape, replay)?,
                        None => sim.step_unreported(Some(&mut tape))?,
                    }
                }
                rerun = tape;
                &rerun
            }
        };
        let (adj, t) =
            backward_adjoint_hooked(&self.start, tape, adj, options, self.first, at_boundary)?;
        seconds += t;
        Ok((adj, seconds, bytes.max(tape.bytes_per_step())))
    }
}

/// A loss and its gradient, with what they cost.
#[derive(Clone, Debug)]
pub struct GradientRun {
    /// L at the final state.
    pub loss: f64,
    /// ∂L/∂(initial state).
    pub gradient: Gradient,
    /// The final state.
    pub final_state: Simulation,
    /// Tape bytes per step (of the segment held at once, with checkpointing).
    pub tape_bytes_per_step: usize,
    /// Wall time of the forward pass, s.
    pub forward_seconds: f64,
    /// Wall time of the backward pass (including re-running segments), s.
    pub backward_seconds: f64,
    /// The backward pass's time per stage adjoint.
    pub adjoint_seconds: AdjointSeconds,
}

/// The loss after `steps` steps from `sim` (forward only, untaped, the reports' liquid
/// measures off: the loss reads the bodies).
pub fn value(mut sim: Simulation, steps: usize, loss: &dyn Loss) -> Result<f64> {
    sim.set_report_measures(false);
    for _ in 0..steps {
        sim.step()?;
    }
    Ok(loss.value(&sim))
}

/// Runs `steps` steps from `initial`, evaluates `loss` and its gradient with respect to the
/// initial state.
pub fn value_and_gradient(
    initial: &Simulation,
    steps: usize,
    loss: &dyn Loss,
    settings: &GradientSettings,
) -> Result<GradientRun> {
    let clock = std::time::Instant::now();
    let rollout = Rollout::run(initial, steps, settings)?;
    let forward_seconds = clock.elapsed().as_secs_f64();
    let clock = std::time::Instant::now();
    let value = loss.value(rollout.final_state());
    let adj = loss.gradient(rollout.final_state());
    let (adj, adjoint_seconds, tape_bytes_per_step, final_state) =
        rollout.into_backward(adj, &settings.options)?;
    Ok(GradientRun {
        loss: value,
        gradient: to_gradient(initial, adj),
        final_state,
        tape_bytes_per_step,
        forward_seconds,
        backward_seconds: clock.elapsed().as_secs_f64(),
        adjoint_seconds,
    })
}
