//! A loss and its gradient in one call: the forward pass taped (or checkpointed), the loss,
//! the backward pass.

use super::backward::{backward_adjoint, to_gradient, AdjointSeconds, GradientOptions};
use super::loss::{Gradient, Loss};
use crate::error::Result;
use crate::geometry::grid::on_pool;
use crate::world::{Simulation, Tape};

/// What [`value_and_gradient`] computes and how.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GradientSettings {
    /// The backward pass's options.
    pub options: GradientOptions,
    /// Keep a snapshot every this many steps instead of the whole tape, and re-run one
    /// segment at a time in the backward pass (√N segments keep memory at O(√N) steps). The
    /// forward map is deterministic, so the gradient is bit-identical to the one without.
    pub checkpoint_every: Option<usize>,
}

impl From<GradientOptions> for GradientSettings {
    fn from(options: GradientOptions) -> Self {
        GradientSettings { options, checkpoint_every: None }
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

/// Runs `steps` steps from `initial`, evaluates `loss` and its gradient with respect to the
/// initial state.
pub fn value_and_gradient(
    initial: &Simulation,
    steps: usize,
    loss: &dyn Loss,
    settings: &GradientSettings,
) -> Result<GradientRun> {
    on_pool(|| {
        let clock = std::time::Instant::now();
        let seg = settings.checkpoint_every.unwrap_or(steps).max(1);
        let mut sim = initial.clone();
        let mut snapshots = Vec::new();
        let mut full_tape = Tape::default();
        for n in 0..steps {
            if settings.checkpoint_every.is_some() {
                if n % seg == 0 {
                    snapshots.push(sim.replay_copy());
                }
                sim.step()?;
            } else {
                sim.step_taped(&mut full_tape)?;
            }
        }
        let forward_seconds = clock.elapsed().as_secs_f64();
        let clock = std::time::Instant::now();
        let value = loss.value(&sim);
        let mut adj = loss.gradient(&sim);
        let mut bytes = full_tape.bytes_per_step();
        let mut adjoint_seconds = AdjointSeconds::default();
        if settings.checkpoint_every.is_none() {
            let (a, t) = backward_adjoint(initial, &full_tape, adj, &settings.options)?;
            adj = a;
            adjoint_seconds += t;
        } else {
            // Each snapshot goes once its segment is done.
            while let Some(snap) = snapshots.pop() {
                let k = snapshots.len();
                let len = seg.min(steps - k * seg);
                let mut s = snap.clone();
                let mut tape = Tape::default();
                for _ in 0..len {
                    s.step_taped(&mut tape)?;
                }
                bytes = bytes.max(tape.bytes_per_step());
                let (a, t) = backward_adjoint(&snap, &tape, adj, &settings.options)?;
                adj = a;
                adjoint_seconds += t;
            }
        }
        Ok(GradientRun {
            loss: value,
            gradient: to_gradient(initial, adj),
            final_state: sim,
            tape_bytes_per_step: bytes,
            forward_seconds,
            backward_seconds: clock.elapsed().as_secs_f64(),
            adjoint_seconds,
        })
    })
}
