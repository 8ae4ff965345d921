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
    /// segments are counted back from the last step (the first is the short one), and the
    /// last is taped in the forward pass, so it is not re-run. The forward map is
    /// deterministic, so the gradient is bit-identical to the one without.
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
        // Segments end at the last step: the first is the short one, and the last is taped
        // in the forward pass, so the backward pass re-runs every segment but that one.
        let tail = if settings.checkpoint_every.is_some() { steps.saturating_sub(seg) } else { 0 };
        let mut sim = initial.clone();
        let mut snapshots = Vec::new();
        let mut tail_start = None;
        let mut tape = Tape::default();
        for n in 0..steps {
            if n < tail {
                if n == 0 || (steps - n) % seg == 0 {
                    snapshots.push((n, sim.replay_copy()));
                }
                sim.step()?;
            } else {
                if n == tail && tail > 0 {
                    tail_start = Some(sim.replay_copy());
                }
                sim.step_taped(&mut tape)?;
            }
        }
        let forward_seconds = clock.elapsed().as_secs_f64();
        let clock = std::time::Instant::now();
        let value = loss.value(&sim);
        let adj = loss.gradient(&sim);
        let mut bytes = tape.bytes_per_step();
        let (mut adj, mut adjoint_seconds) = backward_adjoint(
            tail_start.as_ref().unwrap_or(initial),
            &tape,
            adj,
            &settings.options,
        )?;
        drop((tape, tail_start));
        // Each snapshot goes once its segment is done.
        let mut end = tail;
        while let Some((start, snap)) = snapshots.pop() {
            let mut s = snap.clone();
            let mut tape = Tape::default();
            for _ in start..end {
                s.step_taped(&mut tape)?;
            }
            bytes = bytes.max(tape.bytes_per_step());
            let (a, t) = backward_adjoint(&snap, &tape, adj, &settings.options)?;
            adj = a;
            adjoint_seconds += t;
            end = start;
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
