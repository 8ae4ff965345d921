//! The cycle's constants: what it does on each level (measured), and how finely it cuts its
//! loops into pieces for rayon.

/// Scale of the Galerkin coarse operator, `A_c = COARSE_SCALE·Pᵀ A P` (see the doc of
/// `multigrid`). Measured on the system of `benches/solve.rs` to 1e-6: 0.5 takes 8 CG
/// iterations at 64³ and 128³, 0.6 takes 9–10, and the plain Galerkin product (1.0) 22–30.
pub const COARSE_SCALE: f64 = 0.5;
/// Red–black Gauss–Seidel sweeps before and after the coarse correction on every level but
/// the coarsest. Measured as above: 1 sweep takes 13 iterations, 2 take 8 and 3 take 7; in
/// time 1 was the slowest, and 2 and 3 were within the noise of a shared 2-core machine.
pub const SMOOTHING: usize = 2;
/// Coarsening stops once a level has at most this many cells present.
pub const COARSEST_CELLS: usize = 128;
/// Red–black sweeps on the coarsest level (a few hundred cells at most: cheap).
pub const COARSEST_SWEEPS: usize = 30;

/// Smallest loop handed to rayon as one piece.
pub(super) const MIN_PAR: usize = 1024;
/// Rows a task sorts by colour when the finest level is built.
pub(super) const SORT_CHUNK: usize = 1 << 14;
/// Entries a sweep hands to rayon as one piece.
pub(super) const CHUNK: usize = 2048;
