//! The preconditioner a system's solves share, prepared once (MIC(0) or multigrid).

use crate::solvers::mic0::Mic0;
use crate::solvers::multigrid::Multigrid;
use crate::solvers::Preconditioner;

use super::*;

/// A factored preconditioner.
pub(super) enum Prepared {
    Mic0(Mic0),
    Multigrid(Multigrid),
    None,
}

/// The preconditioners a system has factored, by kind (a clone starts empty), and the memory
/// of an earlier system's multigrid for the first to be built into.
#[derive(Default)]
pub(super) struct PreconditionerCache {
    factored: std::sync::Mutex<Vec<(Preconditioner, std::sync::Arc<Prepared>)>>,
    pub(super) spare: std::sync::Mutex<Option<Multigrid>>,
}

impl Clone for PreconditionerCache {
    fn clone(&self) -> Self {
        PreconditionerCache::default()
    }
}

impl std::fmt::Debug for PreconditionerCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("PreconditionerCache")
    }
}

impl PreconditionerCache {
    /// The `kind` preconditioner of `sys`, factored now if it was not yet.
    pub(super) fn get(
        &self,
        kind: Preconditioner,
        sys: &PressureSystem,
    ) -> std::sync::Arc<Prepared> {
        let mut cache = self.factored.lock().expect("no solve panicked while holding the cache");
        if let Some((_, p)) = cache.iter().find(|(k, _)| *k == kind) {
            return p.clone();
        }
        let p = std::sync::Arc::new(match kind {
            Preconditioner::Mic0 => {
                Prepared::Mic0(Mic0::new(sys.operator(), sys.grid.n, &sys.cell_of_row))
            }
            Preconditioner::Multigrid => {
                let spare = self.spare.lock().map(|mut s| s.take()).unwrap_or_default();
                Prepared::Multigrid(Multigrid::new_in(
                    spare.unwrap_or_default(),
                    sys.grid.n,
                    &sys.cell_of_row,
                    sys.operator(),
                ))
            }
            Preconditioner::None | Preconditioner::Auto => Prepared::None,
        });
        cache.push((kind, p.clone()));
        p
    }

    /// The factored multigrid's memory, or the spare one (None when neither is held).
    pub(super) fn into_multigrid(self) -> Option<Multigrid> {
        let factored = self.factored.into_inner().unwrap_or_else(|e| e.into_inner());
        for (_, p) in factored {
            if let Ok(Prepared::Multigrid(m)) = std::sync::Arc::try_unwrap(p) {
                return Some(m);
            }
        }
        self.spare.into_inner().unwrap_or_else(|e| e.into_inner())
    }
}
