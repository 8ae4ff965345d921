//! The memory systems are built into: a step's two systems hand their vectors on.

use crate::geometry::grid::{Grid, Mac};
use crate::solvers::multigrid::Multigrid;
use crate::solvers::stencil::Stencil;

use super::*;

/// The memory of a system no longer needed, for the next one to be built into
/// ([`PressureSystem::build_in`]): a step builds two systems of about the same size (the
/// density projection's, then the pressure's) and the next step two more, so handing the
/// vectors on saves allocating and faulting in some 150 bytes a liquid cell each time.
#[derive(Default)]
pub struct SystemMemory {
    pub(super) cell_of_row: Vec<u32>,
    pub(super) row_of_cell: Vec<u32>,
    pub(super) stencil: Stencil,
    pub(super) faces: [Vec<ProjectedFace>; 3],
    pub(super) multigrid: Option<Multigrid>,
}

/// The [`SystemMemory`]s of the systems a simulation built last, for the next ones: each
/// system takes one, and gives its own back when done. It keeps as many as were ever taken
/// and not yet given back at once, at most two: one for a forward step (its density
/// projection's system is given back before the pressure's is built, so keeping a second
/// would hold some 130 bytes a liquid cell idle all run), two once a step's adjoint has held
/// the pressure system while it built the density projection's. A system built while none is
/// kept allocates afresh. It also keeps one face field for whichever stage needs one next
/// (the density projection's displacement, then the step's advected velocity), so that no
/// field lies idle through a stage.
#[derive(Default)]
pub struct SystemPool {
    systems: std::sync::Mutex<PoolState>,
    field: std::sync::Mutex<Option<Mac>>,
}

#[derive(Default)]
struct PoolState {
    kept: Vec<SystemMemory>,
    /// Memories taken and not given back.
    out: usize,
    /// The most ever out at once (at most [`POOL_SIZE`]): how many are worth keeping.
    most: usize,
}

/// The most memories a [`SystemPool`] keeps.
const POOL_SIZE: usize = 2;

impl SystemPool {
    /// The memory given back last (empty when none is kept).
    pub fn take(&self) -> SystemMemory {
        let Ok(mut m) = self.systems.lock() else { return SystemMemory::default() };
        m.out += 1;
        m.most = m.most.max(m.out).min(POOL_SIZE);
        m.kept.pop().unwrap_or_default()
    }

    /// A face field of `grid`'s size to overwrite (the one kept, or zeros).
    pub fn field(&self, grid: &Grid) -> Mac {
        let kept = self.field.lock().ok().and_then(|mut u| u.take());
        match kept {
            Some(u) if (0..3).all(|a| u.c[a].len() == grid.faces(a).len()) => u,
            _ => Mac::zeros(grid),
        }
    }

    /// Keeps a face field no longer needed.
    pub fn keep_field(&self, u: Mac) {
        if let Ok(mut slot) = self.field.lock() {
            *slot = Some(u);
        }
    }

    /// Keeps `sys`'s memory for the next system (the oldest kept one goes when the pool
    /// holds as many as are worth keeping).
    pub fn give(&self, sys: PressureSystem) {
        if let Ok(mut m) = self.systems.lock() {
            m.out = m.out.saturating_sub(1);
            if m.kept.len() >= m.most.max(1) {
                m.kept.remove(0);
            }
            m.kept.push(sys.into_memory());
        }
    }
}

impl std::fmt::Debug for SystemPool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SystemPool")
    }
}
