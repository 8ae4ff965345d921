//! The pressure projection (stage 4): right-hand side → solve → velocity update, each a
//! function of its own.
//!
//! Unknowns are the liquid cells only (φ_L < 0 with at least one open face), numbered in
//! lexicographic order. With face fluid weights `w_f` (open area fraction), the ghost-fluid
//! fraction θ on liquid–air faces (Gibou et al. 2002) and `s = Δt·dx/ρ`, row i reads
//!
//! ```text
//!   Σ_f s·w_f/θ_f · (p_i − p_nbr(f)) = −Σ_f σ_if·dx²·w_f·u_f       (p_air = 0, θ = 1 inside)
//! ```
//!
//! which is the paper's `A p = (1/ρ) Gᵀ M_F u` with `A = (Δt/ρ²) Gᵀ M_F G`, scaled by nothing:
//! the residual `b − A p` of row i is exactly minus the volume flux out of cell i after the
//! velocity update, so a relative residual is a relative divergence. The operator is applied
//! matrix-free from a stored 7-point stencil; rigid bodies add a rank-6 term per body.

use crate::geometry::grid::{Grid, Mac, NONE};
use crate::geometry::weights::{AxisWeights, FaceWeights};
use crate::math::buffer::{clear_for, refill};
use crate::math::par::{for_each_keyed_mut, MIN_LEN};
use crate::math::Vec3;
use crate::solvers::cg::{pcg_from, CgSettings, CgStats};
use crate::solvers::mic0::Mic0;
use crate::solvers::multigrid::Multigrid;
use crate::solvers::stencil::Stencil;
use crate::solvers::{LinearSolve, Preconditioner};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// The pressure gradient across one face in terms of the rows beside it (see
/// [`PressureSystem::face_gradient`]): `c·(p[rp] − p[rm])` with p = 0 on a side in air. A
/// face between two rows has c = 1; a face with one side in air carries the ghost-fluid 1/θ
/// on its liquid side. One coefficient for both sides, and 4-byte alignment, keep a
/// [`ProjectedFace`] at 20 bytes (aligned to 8, its coefficient made it 24: 5.8 MB more at
/// `large_tank`'s peak, whose system lists 1.4 M faces). Its fields are read by value.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, packed(4))]
pub struct FaceGradient {
    /// Row on the − side ([`NONE`] in air).
    pub rm: u32,
    /// Row on the + side ([`NONE`] in air).
    pub rp: u32,
    /// The coefficient of each side that is a row.
    pub c: f64,
}

impl FaceGradient {
    /// The − side's coefficient (0 in air).
    #[inline]
    pub fn cm(&self) -> f64 {
        if self.rm != NONE {
            self.c
        } else {
            0.0
        }
    }

    /// The + side's coefficient (0 in air).
    #[inline]
    pub fn cp(&self) -> f64 {
        if self.rp != NONE {
            self.c
        } else {
            0.0
        }
    }

    /// `cp·p[rp] − cm·p[rm]`.
    #[inline]
    pub fn apply(&self, p: &[f64]) -> f64 {
        let at = |r: u32| if r != NONE { self.c * p[r as usize] } else { 0.0 };
        at(self.rp) - at(self.rm)
    }
}

/// How the liquid and the bodies exchange momentum in a step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Coupling {
    /// One pressure solve for liquid and bodies together (Batty et al. 2007): the body's
    /// response to the pressure is part of the system, so it is stable for any density ratio.
    #[default]
    Monolithic,
    /// The partitioned baseline: the liquid is solved around each body moving at its current
    /// velocity (held fixed), then the body is pushed by the resulting pressure force. Light
    /// bodies go unstable (the added-mass instability); kept to show where, not for use.
    Weak,
}

/// Everything the pressure stage needs besides the velocities.
#[derive(Clone, Copy, Debug)]
pub struct PressureParams {
    /// Time step.
    pub dt: f64,
    /// Liquid density.
    pub density: f64,
    /// Lower clamp on θ.
    pub theta_min: f64,
}

/// The assembled (matrix-free) pressure system of one step.
#[derive(Clone, Debug)]
pub struct PressureSystem {
    /// The grid.
    pub grid: Grid,
    /// Step parameters.
    pub params: PressureParams,
    /// Cell of each unknown.
    pub cell_of_row: Vec<u32>,
    /// Unknown of each cell, [`NONE`] for air and solid.
    pub row_of_cell: Vec<u32>,
    /// The fluid stencil (empty when the system was built without its operator: see
    /// [`PressureSystem::build_without_operator_in`]).
    pub stencil: Stencil,
    /// True when some liquid cell touches air (then A is definite); false without the
    /// operator.
    pub has_air: bool,
    /// Rank-6 coupling terms, one per dynamic body.
    pub bodies: Vec<BodyCoupling>,
    /// Per axis, the faces the velocity update acts on (open faces next to a liquid cell),
    /// in increasing face order, with their pressure gradients.
    pub faces: [Vec<ProjectedFace>; 3],
    /// The preconditioner, factored from the stencil at the first solve and reused by every
    /// later one (a step's contact iterations solve up to five times with one operator).
    preconditioner: PreconditionerCache,
    /// Whether the operator (the stencil) was built.
    operator: bool,
}

/// A factored preconditioner.
enum Prepared {
    Mic0(Mic0),
    Multigrid(Multigrid),
    None,
}

/// The preconditioners a system has factored, by kind (a clone starts empty), and the memory
/// of an earlier system's multigrid for the first to be built into.
#[derive(Default)]
struct PreconditionerCache {
    factored: std::sync::Mutex<Vec<(Preconditioner, std::sync::Arc<Prepared>)>>,
    spare: std::sync::Mutex<Option<Multigrid>>,
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
    fn get(&self, kind: Preconditioner, sys: &PressureSystem) -> std::sync::Arc<Prepared> {
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
    fn into_multigrid(self) -> Option<Multigrid> {
        let factored = self.factored.into_inner().unwrap_or_else(|e| e.into_inner());
        for (_, p) in factored {
            if let Ok(Prepared::Multigrid(m)) = std::sync::Arc::try_unwrap(p) {
                return Some(m);
            }
        }
        self.spare.into_inner().unwrap_or_else(|e| e.into_inner())
    }
}

/// The memory of a system no longer needed, for the next one to be built into
/// ([`PressureSystem::build_in`]): a step builds two systems of about the same size (the
/// density projection's, then the pressure's) and the next step two more, so handing the
/// vectors on saves allocating and faulting in some 150 bytes a liquid cell each time.
#[derive(Default)]
pub struct SystemMemory {
    cell_of_row: Vec<u32>,
    row_of_cell: Vec<u32>,
    stencil: Stencil,
    faces: [Vec<ProjectedFace>; 3],
    multigrid: Option<Multigrid>,
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

/// A face the velocity update acts on.
#[derive(Clone, Copy, Debug)]
pub struct ProjectedFace {
    /// Face index on its axis's lattice.
    pub face: u32,
    /// The pressure gradient across it.
    pub gradient: FaceGradient,
}

const _: () = assert!(std::mem::size_of::<ProjectedFace>() == 20);

/// One body's coupling over the unknowns: the non-zero columns of J and Δt·M_S⁻¹.
#[derive(Clone, Debug)]
pub struct BodyCoupling {
    /// Unknowns the body touches.
    pub rows: Vec<u32>,
    /// Column of J for each of those rows.
    pub j: Vec<[f64; 6]>,
    /// Δt·M_S⁻¹, row-major.
    pub dt_minv: [[f64; 6]; 6],
}

impl BodyCoupling {
    /// Keeps the J columns of cells that are unknowns.
    pub fn new(
        row_of_cell: &[u32],
        jac: &[(usize, [f64; 6])],
        dt_minv: [[f64; 6]; 6],
    ) -> BodyCoupling {
        let (rows, j) = jac
            .iter()
            .filter(|(c, _)| row_of_cell[*c] != NONE)
            .map(|(c, col)| (row_of_cell[*c], *col))
            .unzip();
        BodyCoupling { rows, j, dt_minv }
    }

    /// J·x: the generalised force of a pressure field (force, torque).
    pub fn force(&self, x: &[f64]) -> [f64; 6] {
        let mut t = [0.0; 6];
        for (r, col) in self.rows.iter().zip(&self.j) {
            let xr = x[*r as usize];
            for d in 0..6 {
                t[d] += col[d] * xr;
            }
        }
        t
    }

    /// Δt·M⁻¹·f.
    pub fn dt_minv_times(&self, f: &[f64; 6]) -> [f64; 6] {
        let mut s = [0.0; 6];
        for r in 0..6 {
            for c in 0..6 {
                s[r] += self.dt_minv[r][c] * f[c];
            }
        }
        s
    }

    /// y += J ᵀ·s.
    pub fn add_jt(&self, s: &[f64; 6], y: &mut [f64]) {
        for (r, col) in self.rows.iter().zip(&self.j) {
            y[*r as usize] += (0..6).map(|d| col[d] * s[d]).sum::<f64>();
        }
    }
}

/// Ghost-fluid fraction of a liquid–air face: where φ_L crosses zero between the centres,
/// measured from the liquid side, clamped below.
#[inline]
pub fn ghost_theta(phi_liquid: f64, phi_air: f64, theta_min: f64) -> f64 {
    (phi_liquid / (phi_liquid - phi_air)).max(theta_min)
}

/// Calls `visit(face, − cell, + cell)` for the open faces (weight > 0) of `axis` in slab k of
/// its face lattice that have a cell on both sides, in face order, without a division per
/// face: f runs over the face lattice, c over the cell on each face's + side.
#[inline]
fn open_faces(
    grid: &Grid,
    axis: usize,
    k: usize,
    weights: &FaceWeights,
    mut visit: impl FnMut(usize, usize, usize),
) {
    let [nx, ny, _] = grid.faces(axis).n;
    let n = grid.n;
    let w = weights.axis(axis);
    // The cell on the − side of a face is this far below the one on its + side.
    let below = [1, n[0], n[0] * n[1]][axis];
    if axis == 2 && (k == 0 || k == n[2]) {
        return;
    }
    for j in 0..ny {
        if axis == 1 && (j == 0 || j == n[1]) {
            continue;
        }
        let (f0, c0) = (nx * (j + ny * k), n[0] * (j + n[1] * k));
        let (lo, hi) = if axis == 0 { (1, n[0]) } else { (0, nx) };
        for i in lo..hi {
            let f = f0 + i;
            if w.open(f) {
                let c = c0 + i;
                visit(f, c - below, c);
            }
        }
    }
}

/// The face index of the −side (`side = 0`) or +side (`side = 1`) face of cell `ijk` along `axis`.
#[inline]
fn cell_face(grid: &Grid, axis: usize, ijk: [usize; 3], side: usize) -> usize {
    let mut f = ijk;
    f[axis] += side;
    grid.faces(axis).index(f[0], f[1], f[2])
}

/// Whether cell `c` has a face of positive weight (a liquid cell is an unknown when it has).
pub fn has_open_face(grid: &Grid, weights: &FaceWeights, c: usize) -> bool {
    has_open_face_at(grid, &weights.axes(), grid.cells().ijk(c))
}

/// [`has_open_face`] of the cell at `ijk`, with each axis's weights.
#[inline]
fn has_open_face_at(grid: &Grid, w: &[AxisWeights<'_>; 3], ijk: [usize; 3]) -> bool {
    (0..3).any(|a| (0..2).any(|s| w[a].open(cell_face(grid, a, ijk, s))))
}

/// The neighbouring cell of cell `c` (at `ijk`) across its −side or +side face of axis
/// `axis` and the face's weight, when the face is open (weight > 0) and the neighbour inside
/// the grid: a liquid neighbour is coupled to the cell, any other is air (a ghost-fluid face).
#[inline]
fn open_neighbour(
    grid: &Grid,
    weights: &[AxisWeights<'_>; 3],
    c: usize,
    ijk: [usize; 3],
    axis: usize,
    side: usize,
) -> Option<(usize, f64)> {
    let w = weights[axis].weight(cell_face(grid, axis, ijk, side));
    if w <= 0.0 {
        return None;
    }
    grid.cells().neighbour(c, ijk, axis, side).map(|n| (n, w))
}

impl PressureSystem {
    /// Classifies cells and builds the stencil from the liquid signed distance `phi` (cell
    /// centres) and the face fluid weights.
    pub fn build(grid: &Grid, phi: &[f64], weights: &FaceWeights, params: PressureParams) -> Self {
        PressureSystem::build_in(SystemMemory::default(), grid, phi, weights, params)
    }

    /// [`PressureSystem::build`] into the memory of a system no longer needed: the same system,
    /// its vectors refilled instead of allocated.
    pub fn build_in(
        memory: SystemMemory,
        grid: &Grid,
        phi: &[f64],
        weights: &FaceWeights,
        params: PressureParams,
    ) -> Self {
        PressureSystem::build_parts_in(memory, grid, phi, weights, params, true)
    }

    /// [`PressureSystem::build_in`] without the operator, for a step that is given its
    /// pressures instead of solving for them (a checkpointed gradient's re-run): the unknowns,
    /// the velocity update and the bodies' terms are built, the stencil is not (half the
    /// build). Solving with it, or applying it, panics.
    pub fn build_without_operator_in(
        memory: SystemMemory,
        grid: &Grid,
        phi: &[f64],
        weights: &FaceWeights,
        params: PressureParams,
    ) -> Self {
        PressureSystem::build_parts_in(memory, grid, phi, weights, params, false)
    }

    /// The build, with the operator or without.
    fn build_parts_in(
        memory: SystemMemory,
        grid: &Grid,
        phi: &[f64],
        weights: &FaceWeights,
        params: PressureParams,
        operator: bool,
    ) -> Self {
        let SystemMemory { mut cell_of_row, mut row_of_cell, mut stencil, faces, multigrid } =
            memory;
        let cells = grid.cells();
        let axes = weights.axes();
        // The unknowns: liquid cells with an open face, marked, counted, then numbered. A
        // z-slab a task, walked by (i, j): a cell's (i, j, k) from its flat index is two
        // integer divisions, which were a third of this loop's time.
        refill(&mut row_of_cell, cells.len(), NONE);
        let slab = cells.slab();
        let rows: usize = row_of_cell
            .par_chunks_mut(slab)
            .zip(phi.par_chunks(slab))
            .enumerate()
            .map(|(k, (rows, phi))| {
                let mut open = 0;
                for j in 0..grid.n[1] {
                    let first = grid.n[0] * j;
                    for i in 0..grid.n[0] {
                        if phi[first + i] < 0.0 && has_open_face_at(grid, &axes, [i, j, k]) {
                            rows[first + i] = 0;
                            open += 1;
                        }
                    }
                }
                open
            })
            .sum();
        clear_for(&mut cell_of_row, rows);
        cell_of_row.par_extend(
            (0..cells.len() as u32)
                .into_par_iter()
                .with_min_len(MIN_LEN)
                .filter(|&c| row_of_cell[c as usize] != NONE),
        );
        for_each_keyed_mut(
            &mut row_of_cell,
            &cell_of_row,
            |&c| c as usize,
            |r, _, x| *x = r as u32,
        );
        // Only a solve reads the operator: without it the stencil is left empty (its memory
        // kept for the next system).
        let has_air = if operator {
            let s = params.dt * grid.dx / params.density;
            let len = cell_of_row.len();
            refill(&mut stencil.diag, len, 0.0);
            refill(&mut stencil.plus, len, [0.0; 3]);
            refill(&mut stencil.nbr, len, [NONE; 6]);
            let air = stencil
                .diag
                .par_iter_mut()
                .zip(stencil.plus.par_iter_mut())
                .zip(stencil.nbr.par_iter_mut())
                .zip(cell_of_row.par_iter())
                .map(|(((diag_r, plus_r), nbr_r), &c)| {
                    let c = c as usize;
                    let ijk = cells.ijk(c);
                    let mut diag = 0.0;
                    let mut plus = [0.0; 3];
                    let mut nbr = [NONE; 6];
                    let mut air = false;
                    for a in 0..3 {
                        for side in 0..2 {
                            let Some((n, w)) = open_neighbour(grid, &axes, c, ijk, a, side) else {
                                continue;
                            };
                            let rn = row_of_cell[n];
                            if rn != NONE {
                                diag += s * w;
                                nbr[2 * a + side] = rn;
                                if side == 1 {
                                    plus[a] = s * w;
                                }
                            } else {
                                diag += s * w / ghost_theta(phi[c], phi[n], params.theta_min);
                                air = true;
                            }
                        }
                    }
                    (*diag_r, *plus_r, *nbr_r) = (diag, plus, nbr);
                    air
                })
                .reduce(|| false, |a, b| a || b);
            stencil.find_runs();
            air
        } else {
            stencil.diag.clear();
            stencil.plus.clear();
            stencil.nbr.clear();
            stencil.runs.clear();
            false
        };
        let preconditioner = PreconditionerCache::default();
        if let Ok(mut spare) = preconditioner.spare.lock() {
            *spare = multigrid;
        }
        let mut sys = PressureSystem {
            grid: *grid,
            params,
            cell_of_row,
            row_of_cell,
            stencil,
            has_air,
            bodies: Vec::new(),
            faces: Default::default(),
            preconditioner,
            operator,
        };
        let [mut fx, mut fy, mut fz] = faces;
        sys.projected_faces(0, weights, phi, &mut fx);
        sys.projected_faces(1, weights, phi, &mut fy);
        sys.projected_faces(2, weights, phi, &mut fz);
        sys.faces = [fx, fy, fz];
        sys
    }

    /// Per row, whether it reaches a row next to air through the stencil's couplings
    /// (`weights`: the face weights the system was built with). The potential of the rows
    /// that do is held by the air; a group of rows closed on every side by faces of zero
    /// weight makes A singular, and only a right-hand side that sums to zero over it can be
    /// solved for.
    pub fn rows_reaching_air(&self, weights: &FaceWeights) -> Vec<bool> {
        let (grid, cells) = (&self.grid, self.grid.cells());
        let axes = weights.axes();
        let mut reached: Vec<bool> = self
            .cell_of_row
            .par_iter()
            .with_min_len(MIN_LEN)
            .map(|&c| {
                let c = c as usize;
                let ijk = cells.ijk(c);
                (0..3).any(|a| {
                    (0..2).any(|s| {
                        open_neighbour(grid, &axes, c, ijk, a, s)
                            .is_some_and(|(n, _)| self.row_of_cell[n] == NONE)
                    })
                })
            })
            .collect();
        let mut stack: Vec<u32> =
            (0..reached.len() as u32).filter(|&r| reached[r as usize]).collect();
        while let Some(r) = stack.pop() {
            for &n in &self.operator().nbr[r as usize] {
                if n != NONE && !reached[n as usize] {
                    reached[n as usize] = true;
                    stack.push(n);
                }
            }
        }
        reached
    }

    /// The system's vectors and factored multigrid, for the next system to be built into.
    pub fn into_memory(self) -> SystemMemory {
        let PressureSystem { cell_of_row, row_of_cell, stencil, faces, preconditioner, .. } = self;
        SystemMemory {
            cell_of_row,
            row_of_cell,
            stencil,
            faces,
            multigrid: preconditioner.into_multigrid(),
        }
    }

    /// The faces of `axis` next to a liquid cell that the velocity update acts on, each once,
    /// sorted, into `out`: those where [`PressureSystem::face_gradient`] gives a gradient. In
    /// two parallel passes over the slabs of the face lattice (count, then fill each slab's
    /// share of `out`), so nothing but `out` is allocated.
    fn projected_faces(
        &self,
        axis: usize,
        weights: &FaceWeights,
        phi: &[f64],
        out: &mut Vec<ProjectedFace>,
    ) {
        let lat = self.grid.faces(axis);
        let nz = lat.n[2];
        let rows = &self.row_of_cell;
        // A face has a gradient when a cell on either side is an unknown: counted without
        // computing it.
        let counts: Vec<usize> = (0..nz)
            .into_par_iter()
            .map(|k| {
                let mut count = 0;
                open_faces(&self.grid, axis, k, weights, |_, m, pl| {
                    count += usize::from(rows[m] != NONE || rows[pl] != NONE);
                });
                count
            })
            .collect();
        let empty = FaceGradient { rm: NONE, rp: NONE, c: 0.0 };
        refill(out, counts.iter().sum(), ProjectedFace { face: 0, gradient: empty });
        let mut slabs = Vec::with_capacity(nz);
        let mut rest = out.as_mut_slice();
        for &c in &counts {
            let (part, tail) = rest.split_at_mut(c);
            slabs.push(part);
            rest = tail;
        }
        slabs.into_par_iter().enumerate().for_each(|(k, part)| {
            let mut next = part.iter_mut();
            open_faces(&self.grid, axis, k, weights, |f, m, pl| {
                if let Some(gradient) = self.gradient_between(m, pl, phi) {
                    *next.next().expect("counted") = ProjectedFace { face: f as u32, gradient };
                }
            });
        });
    }

    /// Number of unknowns.
    pub fn len(&self) -> usize {
        self.cell_of_row.len()
    }

    /// True when there is no liquid cell.
    pub fn is_empty(&self) -> bool {
        self.cell_of_row.is_empty()
    }

    /// The fluid stencil, which a solve reads.
    ///
    /// # Panics
    /// When the system was built without it ([`PressureSystem::build_without_operator_in`]).
    pub fn operator(&self) -> &Stencil {
        assert!(
            self.operator,
            "the pressure system was built without its operator (for a step given its \
             pressures), and cannot be solved or applied"
        );
        &self.stencil
    }

    /// y = A x (the fluid stencil).
    pub fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.operator().apply(x, y);
        for b in &self.bodies {
            let s = b.dt_minv_times(&b.force(x));
            b.add_jt(&s, y);
        }
    }

    /// Volume flux out of each liquid cell through its fluid faces, `Σ_f σ_if·dx²·w_f·u_f`.
    pub fn fluid_flux(&self, u: &Mac, weights: &FaceWeights) -> Vec<f64> {
        let grid = &self.grid;
        let area = grid.dx * grid.dx;
        let cells = grid.cells();
        let w = weights.axes();
        self.cell_of_row
            .par_iter()
            .map(|&c| {
                let ijk = cells.ijk(c as usize);
                let mut f = 0.0;
                for a in 0..3 {
                    let lo = cell_face(grid, a, ijk, 0);
                    let hi = cell_face(grid, a, ijk, 1);
                    f += w[a].weight(hi) * u.c[a][hi] - w[a].weight(lo) * u.c[a][lo];
                }
                f * area
            })
            .collect()
    }

    /// Right-hand side `(1/ρ) Gᵀ M_F u − Jᵀ V`: minus the volume flux out of each cell,
    /// through its fluid faces and pushed by each body's velocity `V = [v; ω]` (one per
    /// entry of `bodies`).
    pub fn rhs(&self, u: &Mac, weights: &FaceWeights, body_velocity: &[[f64; 6]]) -> Vec<f64> {
        assert_eq!(body_velocity.len(), self.bodies.len());
        let mut b = self.fluid_flux(u, weights);
        b.iter_mut().for_each(|x| *x = -*x);
        for (body, v) in self.bodies.iter().zip(body_velocity) {
            let minus_v = v.map(|x| -x);
            body.add_jt(&minus_v, &mut b);
        }
        b
    }

    /// Solves A p = b from p = 0 ([`Preconditioner::Auto`] picks the preconditioner by the
    /// number of unknowns).
    pub fn solve(&self, b: &[f64], how: &LinearSolve) -> (Vec<f64>, CgStats) {
        self.solve_from(b, vec![0.0; self.len()], how)
    }

    /// [`PressureSystem::solve`] from the initial guess `p` (one value per unknown).
    pub fn solve_from(&self, b: &[f64], mut p: Vec<f64>, how: &LinearSolve) -> (Vec<f64>, CgStats) {
        assert_eq!(p.len(), self.len());
        let settings = CgSettings {
            tolerance: how.tolerance,
            max_iterations: how.max_iterations,
            project_constant: !self.has_air,
        };
        let apply = |x: &[f64], y: &mut [f64]| self.apply(x, y);
        // The solve runs as one task on a rayon worker, so its many small parallel loops
        // (dozens per wavefront-scheduled MIC(0) or per V-cycle) are forked from inside the
        // pool instead of each waking a worker from outside (two thread switches apiece).
        let stats = rayon::scope(|_| {
            let prepared = self.preconditioner.get(how.preconditioner.resolve(self.len()), self);
            match prepared.as_ref() {
                Prepared::Mic0(m) => pcg_from(
                    apply,
                    |r: &[f64], z: &mut [f64]| m.apply(self.operator(), r, z),
                    b,
                    &mut p,
                    &settings,
                ),
                Prepared::Multigrid(m) => {
                    pcg_from(apply, |r: &[f64], z: &mut [f64]| m.apply(r, z), b, &mut p, &settings)
                }
                Prepared::None => pcg_from(
                    apply,
                    |r: &[f64], z: &mut [f64]| z.copy_from_slice(r),
                    b,
                    &mut p,
                    &settings,
                ),
            }
        });
        (p, stats)
    }

    /// Applies `u −= (Δt/ρ) ∇p` on every open face next to a liquid cell (with p = 0 in air
    /// at distance θ·dx) and returns the mask of faces so updated (the valid faces).
    pub fn update_velocity(&self, p: &[f64], u: &mut Mac) -> [Vec<u8>; 3] {
        self.velocity_update_with(p, u, |x, du| *x -= du)
    }

    /// [`PressureSystem::update_velocity`] of a zero field, written over those faces of `u`
    /// (its other faces left as they are, whatever they hold).
    pub fn velocity_update_into(&self, p: &[f64], u: &mut Mac) -> [Vec<u8>; 3] {
        self.velocity_update_with(p, u, |x, du| *x = 0.0 - du)
    }

    /// `apply(u_f, (Δt/ρ) ∇p)` on the faces the update acts on; their mask.
    fn velocity_update_with(
        &self,
        p: &[f64],
        u: &mut Mac,
        apply: impl Fn(&mut f64, f64) + Sync,
    ) -> [Vec<u8>; 3] {
        let grid = &self.grid;
        let k = self.params.dt / (self.params.density * grid.dx);
        let mut valid = [0, 1, 2].map(|a| vec![0u8; grid.faces(a).len()]);
        for a in 0..3 {
            let face = |pf: &ProjectedFace| pf.face as usize;
            for_each_keyed_mut(&mut u.c[a], &self.faces[a], face, |_, pf, x| {
                apply(x, k * pf.gradient.apply(p))
            });
            for_each_keyed_mut(&mut valid[a], &self.faces[a], face, |_, _, v| *v = 1);
        }
        valid
    }

    /// What [`PressureSystem::update_velocity`] subtracts from face `f` of `axis` for the
    /// pressure `p` (0 on a face it does not update).
    pub fn velocity_update_at(&self, axis: usize, f: usize, p: &[f64]) -> f64 {
        let k = self.params.dt / (self.params.density * self.grid.dx);
        match self.faces[axis].binary_search_by_key(&(f as u32), |pf| pf.face) {
            Ok(i) => k * self.faces[axis][i].gradient.apply(p),
            Err(_) => 0.0,
        }
    }

    /// The pressure gradient across face `f` of `axis` as `cp·p[rp] − cm·p[rm]` (scaled by
    /// 1/dx elsewhere), when the velocity update acts on the face: an open face next to a
    /// liquid cell. A side in air has no row (p = 0 there) and the other side's coefficient
    /// carries the ghost-fluid 1/θ.
    #[inline]
    pub fn face_gradient(
        &self,
        axis: usize,
        f: usize,
        weights: &FaceWeights,
        phi: &[f64],
    ) -> Option<FaceGradient> {
        if weights.closed(axis, f) {
            return None;
        }
        let grid = &self.grid;
        let (m, pl) = grid.face_cells(axis, grid.faces(axis).ijk(f));
        self.gradient_between(m?, pl?, phi)
    }

    /// [`PressureSystem::face_gradient`] of an open face between cells `m` (its − side) and
    /// `pl`: Some exactly when either is an unknown (the condition `projected_faces` counts
    /// by, without computing the coefficient: measured 3–5 ms a system build faster).
    #[inline]
    fn gradient_between(&self, m: usize, pl: usize, phi: &[f64]) -> Option<FaceGradient> {
        let (rm, rp) = (self.row_of_cell[m], self.row_of_cell[pl]);
        let tmin = self.params.theta_min;
        match (rm != NONE, rp != NONE) {
            (true, true) => Some(FaceGradient { rm, rp, c: 1.0 }),
            (true, false) => {
                Some(FaceGradient { rm, rp, c: 1.0 / ghost_theta(phi[m], phi[pl], tmin) })
            }
            (false, true) => {
                Some(FaceGradient { rm, rp, c: 1.0 / ghost_theta(phi[pl], phi[m], tmin) })
            }
            (false, false) => None,
        }
    }

    /// −∂/∂w_f of ⟨s, A(w)·p⟩ for face `f` of `axis`: `Δt·dx/ρ · θ·(g·s)(g·p)` with g the
    /// face's pressure gradient (carrying 1/θ on a ghost-fluid face), 0 where the update does
    /// not act. With δw = −δβ on a face a body covers, this times ∂β/∂pose is the operator's
    /// part of the pose derivative −sᵀ·δA·p.
    pub fn weight_adjoint(
        &self,
        axis: usize,
        f: usize,
        weights: &FaceWeights,
        phi: &[f64],
        s: &[f64],
        p: &[f64],
    ) -> f64 {
        let Some(fg) = self.face_gradient(axis, f, weights, phi) else {
            return 0.0;
        };
        let theta = 1.0 / fg.c;
        let scale = self.params.dt * self.grid.dx / self.params.density;
        scale * theta * fg.apply(s) * fg.apply(p)
    }

    /// ∂L/∂φ per cell through the ghost-fluid θ = φ_l/(φ_l − φ_a) of the liquid–air faces
    /// (the free surface's position), for the solve's solution `p`, the adjoint solve's `s`
    /// and the adjoint `ubar` of the updated velocity: dL = −sᵀ·(∂A/∂θ)·p·dθ + ūᵀ·(∂u/∂θ)·dθ,
    /// with A ∋ Δt·dx/ρ·w/θ on the liquid cell's diagonal and u_f = û_f ∓ k·p_l/θ. Zero where
    /// θ is clamped at θ_min.
    /// `weights` are the face weights the system was built with.
    pub fn phi_adjoint(
        &self,
        phi: &[f64],
        weights: &FaceWeights,
        s: &[f64],
        p: &[f64],
        ubar: &Mac,
    ) -> Vec<f64> {
        let mut out = vec![0.0; self.grid.num_cells()];
        let scale = self.params.dt * self.grid.dx / self.params.density;
        let k = self.params.dt / (self.params.density * self.grid.dx);
        for a in 0..3 {
            let lat = self.grid.faces(a);
            for pf in &self.faces[a] {
                let g = &pf.gradient;
                // The liquid row and its side: + side liquid when the − side is air.
                let (r, sign) = match (g.rm == NONE, g.rp == NONE) {
                    (true, false) => (g.rp as usize, 1.0),
                    (false, true) => (g.rm as usize, -1.0),
                    _ => continue,
                };
                let (m, pl) = self.grid.face_cells(a, lat.ijk(pf.face as usize));
                let (m, pl) = (m.expect("an interior face"), pl.expect("an interior face"));
                let (l, air) = if sign > 0.0 { (pl, m) } else { (m, pl) };
                let (pl_, pa) = (phi[l], phi[air]);
                let raw = pl_ / (pl_ - pa);
                if raw <= self.params.theta_min {
                    continue;
                }
                let theta2 = raw * raw;
                // u_f = û_f − k·sign·p_l/θ.
                let theta_bar = s[r] * scale * weights.weight(a, pf.face as usize) * p[r] / theta2
                    + ubar.c[a][pf.face as usize] * sign * k * p[r] / theta2;
                let den = (pl_ - pa) * (pl_ - pa);
                out[l] += theta_bar * (-pa) / den;
                out[air] += theta_bar * pl_ / den;
            }
        }
        out
    }

    /// Adjoint of [`PressureSystem::update_velocity`] with respect to p: given the adjoint
    /// of the updated face velocities, returns `−k·G̃ᵀ·adj` per row.
    pub fn update_velocity_adjoint(&self, adj_u: &Mac) -> Vec<f64> {
        let k = self.params.dt / (self.params.density * self.grid.dx);
        let mut out = vec![0.0; self.len()];
        for a in 0..3 {
            for pf in &self.faces[a] {
                let adj = adj_u.c[a][pf.face as usize];
                if adj == 0.0 {
                    continue;
                }
                let g = &pf.gradient;
                if g.rp != NONE {
                    out[g.rp as usize] -= k * g.c * adj;
                }
                if g.rm != NONE {
                    out[g.rm as usize] += k * g.c * adj;
                }
            }
        }
        out
    }

    /// Subtracts from `adj` the transpose of [`PressureSystem::fluid_flux`] applied to a row
    /// adjoint `s` (zero in air and solid): the face adjoint `dx²·w_f·(s_m − s_p)` on each
    /// projected face, for the system's face weights `weights`.
    pub fn subtract_fluid_flux_adjoint(&self, s: &[f64], weights: &FaceWeights, adj: &mut Mac) {
        let area = self.grid.dx * self.grid.dx;
        let sv = |r: u32| if r != NONE { s[r as usize] } else { 0.0 };
        for a in 0..3 {
            let face = |pf: &ProjectedFace| pf.face as usize;
            let w = weights.axis(a);
            for_each_keyed_mut(&mut adj.c[a], &self.faces[a], face, |_, pf, x| {
                let g = &pf.gradient;
                *x -= area * w.weight(pf.face as usize) * (sv(g.rm) - sv(g.rp));
            });
        }
    }

    /// The adjoint solve of the projection: from the adjoints of the projected face
    /// velocities `adj_u` and of the bodies' `[v; ω]` after the solve, `s` with
    /// `A s = ∂(velocity update)ᵀ·adj_u + Δt·J M_S⁻¹·adj_v` (one more solve with the same
    /// operator).
    pub fn adjoint_solve(
        &self,
        adj_u: &Mac,
        adj_v: &[[f64; 6]],
        how: &LinearSolve,
    ) -> (Vec<f64>, CgStats) {
        let mut pbar = self.update_velocity_adjoint(adj_u);
        for (b, av) in self.bodies.iter().zip(adj_v) {
            b.add_jt(&b.dt_minv_times(av), &mut pbar);
        }
        // No warm start here: the adjoint pressure of the step after this one saves half an
        // iteration of 18 on block_drop, one of 9 on large_tank.
        self.solve(&pbar, how)
    }

    /// The coupled bodies' `[v; ω]` adjoint before the projection, `adj_v − J s`.
    pub fn body_velocity_adjoint(&self, adj_v: &[[f64; 6]], s: &[f64]) -> Vec<[f64; 6]> {
        self.bodies
            .iter()
            .zip(adj_v)
            .map(|(b, av)| {
                let js = b.force(s);
                std::array::from_fn(|d| av[d] - js[d])
            })
            .collect()
    }

    /// Adjoint of the whole projection (right-hand side, solve, velocity and body updates)
    /// for fixed geometry (paper, eqs. 8–9, in this code's terms): from the adjoints of the
    /// projected face velocities `adj_u` and of the bodies' `[v; ω]` after the solve, one more
    /// solve with the same operator gives `s` ([`PressureSystem::adjoint_solve`]), and the
    /// adjoints before the projection are `adj_u − Fᵀ s` and `adj_v − J s`. Returns (adjoint
    /// of u, of each body's velocity, s). `weights` are the face weights the system was built
    /// with. (The backward pass calls the three parts itself, to update its field in place.)
    pub fn projection_adjoint(
        &self,
        adj_u: &Mac,
        adj_v: &[[f64; 6]],
        weights: &FaceWeights,
        how: &LinearSolve,
    ) -> (Mac, Vec<[f64; 6]>, Vec<f64>, CgStats) {
        let (s, stats) = self.adjoint_solve(adj_u, adj_v, how);
        let mut u_hat = adj_u.clone();
        self.subtract_fluid_flux_adjoint(&s, weights, &mut u_hat);
        let v_hat = self.body_velocity_adjoint(adj_v, &s);
        (u_hat, v_hat, s, stats)
    }

    /// Pressure on the whole cell grid (zero outside the liquid).
    pub fn scatter(&self, p: &[f64]) -> Vec<f64> {
        let mut out = Vec::new();
        self.scatter_into(p, &mut out);
        out
    }

    /// [`PressureSystem::scatter`] written over `out`.
    pub fn scatter_into(&self, p: &[f64], out: &mut Vec<f64>) {
        refill(out, self.grid.num_cells(), 0.0);
        for (r, &c) in self.cell_of_row.iter().enumerate() {
            out[c as usize] = p[r];
        }
    }
}

/// What the pose part of the projection adjoint ([`projection_pose_adjoint`]) reads.
pub struct PoseAdjointInputs<'a> {
    /// The step's system (its `bodies` the coupled bodies' terms).
    pub sys: &'a PressureSystem,
    /// The combined fluid weights.
    pub weights: &'a FaceWeights,
    /// φ_L (extended into the solids).
    pub phi: &'a [f64],
    /// The static solids' weights.
    pub static_weights: &'a FaceWeights,
    /// The fluid velocity before the projection.
    pub u_hat: &'a Mac,
    /// The step's pressure.
    pub p: &'a [f64],
    /// The adjoint solve's solution.
    pub s: &'a [f64],
    /// The step.
    pub dt: f64,
}

/// ∂L/∂[δx; δθ] of one body through the projection's geometry, for fixed velocities: with
/// the adjoint solve's s and the adjoint V′ of the body's velocity after the solve,
/// `dL = sᵀ(δb − δA·p) + V′·(δMi·J p + Mi·δJ p)` where b = −F(w)·û − Jᵀ v̂,
/// A = S(w) + Jᵀ Mi J and Mi = Δt·M⁻¹. δw = −δβ on faces the clamp leaves alone, δJ comes
/// from δβ and from the torque arms (δr = −δx), δMi from the rotation of the inertia.
pub fn projection_pose_adjoint(
    g: &PoseAdjointInputs<'_>,
    body: &crate::geometry::body::RigidBody,
    faces: &[Vec<(usize, crate::math::dual::Dual<6>)>; 3],
    coupling: usize,
    v_hat: &[f64; 6],
    adj_v: &[f64; 6],
) -> [f64; 6] {
    body_pose_adjoint(g, body, faces, &g.sys.bodies[coupling], true, v_hat, adj_v)
}

/// [`projection_pose_adjoint`] of a kinematic body (`sys.kinematic`'s coupling `bc`, its
/// prescribed [v; ω]): its J pushes the right-hand side and its fractions take the fluid's
/// weights, but nothing of the solve moves it (no M⁻¹ terms).
pub fn kinematic_pose_adjoint(
    g: &PoseAdjointInputs<'_>,
    body: &crate::geometry::body::RigidBody,
    faces: &[Vec<(usize, crate::math::dual::Dual<6>)>; 3],
    bc: &BodyCoupling,
    v: &[f64; 6],
) -> [f64; 6] {
    body_pose_adjoint(g, body, faces, bc, false, v, &[0.0; 6])
}

/// The pose part of the projection adjoint of a body whose coupling is `bc`, in the
/// operator (`coupled`, a dynamic body) or only in the right-hand side (a kinematic one).
fn body_pose_adjoint(
    g: &PoseAdjointInputs<'_>,
    body: &crate::geometry::body::RigidBody,
    faces: &[Vec<(usize, crate::math::dual::Dual<6>)>; 3],
    bc: &BodyCoupling,
    coupled: bool,
    v_hat: &[f64; 6],
    adj_v: &[f64; 6],
) -> [f64; 6] {
    let sys = g.sys;
    let grid = sys.grid;
    let area = grid.dx * grid.dx;
    let row_val = |c: Option<usize>, x: &[f64]| match c.map(|c| sys.row_of_cell[c]) {
        Some(r) if r != crate::geometry::grid::NONE => x[r as usize],
        _ => 0.0,
    };
    let spin = body.spin();
    let (js, jp) = (bc.force(g.s), bc.force(g.p));
    let mi = bc.dt_minv;
    let mi_jp = bc.dt_minv_times(&jp);
    let mut out = [0.0; 6];
    // δJ·x for x = s and x = p, per direction: [direction][component].
    let mut djs = [[0.0; 6]; 6];
    let mut djp = [[0.0; 6]; 6];
    for axis in 0..3 {
        let lat = grid.faces(axis);
        let e = crate::math::unit(axis);
        for (f, beta) in faces[axis].iter() {
            let f = *f;
            let ijk = lat.ijk(f);
            let (m, pl) = grid.face_cells(axis, ijk);
            // Fluid weight: w = clamp(w_static − β): its derivative is −δβ inside the clamp.
            let raw = g.static_weights.weight(axis, f) - beta.v;
            if raw > 0.0 && raw < 1.0 && g.weights.weight(axis, f) > 0.0 {
                let uh = g.u_hat.c[axis][f];
                let flux = area * uh * (row_val(m, g.s) - row_val(pl, g.s));
                let stencil = sys.weight_adjoint(axis, f, g.weights, g.phi, g.s, g.p);
                // sᵀδb ∋ −sᵀ δF û = −Σ dx²·δw·û·(s_m − s_p), δw = −δβ; −sᵀ δS p likewise.
                for k in 0..6 {
                    out[k] += beta.d[k] * (flux + stencil);
                }
            }
            // δJ columns on the two cells beside the face.
            let r = lat.position(ijk[0], ijk[1], ijk[2]) - body.x;
            let t = spin.project(r.cross(e));
            let col = [e.x, e.y, e.z, t.x, t.y, t.z];
            let (sm, sp) = (row_val(m, g.s), row_val(pl, g.s));
            let (pm, pp) = (row_val(m, g.p), row_val(pl, g.p));
            let (ns, np) = (area * (sm - sp), area * (pm - pp));
            for k in 0..6 {
                for c in 0..6 {
                    djs[k][c] += ns * beta.d[k] * col[c];
                    djp[k][c] += np * beta.d[k] * col[c];
                }
                // δr = −e_k: δ(P·(r × e)) = −P·(e_k × e); a rotation δθ = e_k turns the
                // symmetry axis of P: δP·(r × e).
                let dt_ = if k < 3 {
                    spin.project(-crate::math::unit(k).cross(e))
                } else {
                    spin.rotation_derivative(r.cross(e), crate::math::unit(k - 3))
                };
                for c in 0..3 {
                    djs[k][3 + c] += ns * beta.v * crate::math::comp(dt_, c);
                    djp[k][3 + c] += np * beta.v * crate::math::comp(dt_, c);
                }
            }
        }
    }
    let dot6 = |a: &[f64; 6], b: &[f64; 6]| (0..6).map(|i| a[i] * b[i]).sum::<f64>();
    let mv = |m: &[[f64; 6]; 6], x: &[f64; 6]| -> [f64; 6] {
        std::array::from_fn(|r| (0..6).map(|c| m[r][c] * x[c]).sum())
    };
    // δMi for the rotation directions: Δt·([e]×·I⁻¹ − I⁻¹·[e]×) on the angular block.
    let inv = body.world_inertia().inverse();
    let inv_a: [[f64; 3]; 3] =
        std::array::from_fn(|r| std::array::from_fn(|c| inv.col(c).to_array()[r]));
    for k in 0..6 {
        let mut dmi = [[0.0; 6]; 6];
        if k >= 3 && coupled {
            let ax = crate::math::unit(k - 3);
            let cross = |v: [f64; 3]| {
                let w = ax.cross(Vec3::new(v[0], v[1], v[2]));
                [w.x, w.y, w.z]
            };
            // [e]× I⁻¹: columns of I⁻¹ crossed; I⁻¹ [e]×: I⁻¹ applied to e × unit columns.
            for c in 0..3 {
                let colc = [inv_a[0][c], inv_a[1][c], inv_a[2][c]];
                let left = cross(colc);
                let ec = ax.cross(crate::math::unit(c));
                for r in 0..3 {
                    let right = (0..3).map(|q| inv_a[r][q] * crate::math::comp(ec, q)).sum::<f64>();
                    dmi[3 + r][3 + c] = g.dt * (left[r] - right);
                }
            }
        }
        let dmi_jp = mv(&dmi, &jp);
        let mi_djp = mv(&mi, &djp[k]);
        let lhs = -dot6(&djs[k], v_hat)
            - (dot6(&djs[k], &mi_jp) + dot6(&js, &dmi_jp) + dot6(&js, &mi_djp));
        out[k] += lhs + dot6(adj_v, &dmi_jp) + dot6(adj_v, &mi_djp);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small tank with a free surface and a partly blocked face.
    /// The system with the φ_L and face weights it was built from.
    fn system() -> PressureSystem {
        system_with_inputs().0
    }

    fn system_with_inputs() -> (PressureSystem, Vec<f64>, FaceWeights) {
        let grid = Grid { n: [5, 6, 4], dx: 0.1 };
        let cells = grid.cells();
        let mut phi = vec![0.0; cells.len()];
        cells.fill_par(&mut phi, |_, j, _| (j as f64 + 0.5) * 0.1 - 0.33);
        let mut weights = [0, 1, 2].map(|a| {
            let lat = grid.faces(a);
            let mut w = vec![1.0; lat.len()];
            lat.fill_par(&mut w, |i, j, k| {
                let f = [i, j, k];
                if f[a] == 0 || f[a] == grid.n[a] {
                    0.0
                } else {
                    1.0
                }
            });
            w
        });
        weights[0][grid.faces(0).index(2, 1, 1)] = 0.3;
        let weights = FaceWeights::new(&weights);
        let sys = PressureSystem::build(
            &grid,
            &phi,
            &weights,
            PressureParams { dt: 0.01, density: 1000.0, theta_min: 0.01 },
        );
        (sys, phi, weights)
    }

    #[test]
    fn projected_faces_are_every_face_with_a_gradient_once() {
        // The face list the velocity update walks must be exactly the faces where the
        // per-face rule gives a gradient, each once, in order.
        let (sys, phi, weights) = system_with_inputs();
        for a in 0..3 {
            let brute: Vec<u32> = (0..sys.grid.faces(a).len())
                .filter(|&f| sys.face_gradient(a, f, &weights, &phi).is_some())
                .map(|f| f as u32)
                .collect();
            let listed: Vec<u32> = sys.faces[a].iter().map(|pf| pf.face).collect();
            assert!(!brute.is_empty());
            assert_eq!(listed, brute, "axis {a}");
            for pf in &sys.faces[a] {
                let g = sys.face_gradient(a, pf.face as usize, &weights, &phi).unwrap();
                let h = pf.gradient;
                assert_eq!(g, h, "face {}", pf.face);
            }
        }
    }

    /// A system built into another's memory (a larger grid's, its multigrid factored) is the
    /// system built afresh, and solves the same to the bit.
    #[test]
    fn built_into_old_memory_is_built_afresh() {
        let (sys, phi, weights) = system_with_inputs();
        let grid = Grid { n: [9, 7, 8], dx: 0.1 };
        let other_phi = vec![-1.0; grid.num_cells()];
        let other_w = FaceWeights::new(&[0, 1, 2].map(|a| vec![0.5; grid.faces(a).len()]));
        let other = PressureSystem::build(&grid, &other_phi, &other_w, sys.params);
        let how = LinearSolve {
            tolerance: 1e-10,
            max_iterations: 200,
            preconditioner: Preconditioner::Multigrid,
        };
        let _ = other.solve(&vec![1.0; other.len()], &how);
        let pool = SystemPool::default();
        pool.give(other);
        let memory = pool.take();
        assert!(memory.multigrid.is_some(), "the factored multigrid is handed on");
        let reused = PressureSystem::build_in(memory, &sys.grid, &phi, &weights, sys.params);
        assert_eq!(reused.cell_of_row, sys.cell_of_row);
        assert_eq!(reused.row_of_cell, sys.row_of_cell);
        assert_eq!(reused.stencil.diag, sys.stencil.diag);
        assert_eq!(reused.stencil.plus, sys.stencil.plus);
        assert_eq!(reused.stencil.nbr, sys.stencil.nbr);
        assert_eq!(reused.has_air, sys.has_air);
        for a in 0..3 {
            let key = |f: &ProjectedFace| {
                let g = f.gradient;
                (f.face, g.rm, g.rp, g.c.to_bits())
            };
            let (x, y): (Vec<_>, Vec<_>) =
                (reused.faces[a].iter().map(key).collect(), sys.faces[a].iter().map(key).collect());
            assert_eq!(x, y, "axis {a}");
        }
        let b: Vec<f64> = (0..sys.len()).map(|r| ((r * 7) % 5) as f64 - 2.0).collect();
        let (p0, _) = sys.solve(&b, &how);
        let (p1, _) = reused.solve(&b, &how);
        assert!(p0.iter().zip(&p1).all(|(x, y)| x.to_bits() == y.to_bits()));
    }

    /// Built without its operator, into a solved system's memory: the unknowns and the
    /// velocity update are the full build's to the bit, and solving panics instead of reading
    /// the old system's stencil.
    #[test]
    fn built_without_operator_updates_alike_and_cannot_solve() {
        let (sys, phi, weights) = system_with_inputs();
        let how = LinearSolve {
            tolerance: 1e-10,
            max_iterations: 200,
            preconditioner: Preconditioner::Multigrid,
        };
        let b: Vec<f64> = (0..sys.len()).map(|r| ((r * 7) % 5) as f64 - 2.0).collect();
        let (p, _) = sys.solve(&b, &how);
        let pool = SystemPool::default();
        pool.give(sys.clone());
        let lean = PressureSystem::build_without_operator_in(
            pool.take(),
            &sys.grid,
            &phi,
            &weights,
            sys.params,
        );
        assert_eq!(lean.cell_of_row, sys.cell_of_row);
        assert_eq!(lean.row_of_cell, sys.row_of_cell);
        assert!(lean.stencil.diag.is_empty() && lean.stencil.nbr.is_empty());
        let field = |s: &PressureSystem| {
            let mut u = Mac::zeros(&s.grid);
            s.update_velocity(&p, &mut u);
            u.c.map(|c| c.iter().map(|x| x.to_bits()).collect::<Vec<_>>())
        };
        assert_eq!(field(&lean), field(&sys));
        let solved =
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| lean.solve(&b, &how)));
        let message = solved.expect_err("a system without its operator solved");
        let text = message
            .downcast_ref::<&str>()
            .copied()
            .or_else(|| message.downcast_ref::<String>().map(String::as_str))
            .unwrap_or("");
        assert!(text.contains("without its operator"), "{text}");
    }

    #[test]
    fn projection_adjoint_is_the_transpose() {
        // For fixed geometry the projection is linear in (û, v̂):
        // ⟨P(û, v̂), (ū, v̄)⟩ = ⟨(û, v̂), Pᵀ(ū, v̄)⟩, to the solver's tolerance.
        let (mut sys, _, weights) = system_with_inputs();
        let grid = sys.grid;
        // A body touching a few rows, with an SPD Δt·M⁻¹.
        let jac: Vec<(usize, [f64; 6])> = (0..6)
            .map(|r| {
                let c = sys.cell_of_row[r * 3] as usize;
                (c, std::array::from_fn(|d| ((r * 7 + d * 3) % 5) as f64 * 0.01 - 0.02))
            })
            .collect();
        let mut m = [[0.0; 6]; 6];
        for d in 0..6 {
            m[d][d] = 0.05 + 0.01 * d as f64;
        }
        m[3][4] = 0.004;
        m[4][3] = 0.004;
        sys.bodies.push(BodyCoupling::new(&sys.row_of_cell, &jac, m));
        let field = |seed: usize| {
            let mut u = Mac::zeros(&grid);
            for a in 0..3 {
                for (f, x) in u.c[a].iter_mut().enumerate() {
                    *x = ((f * 7919 + a * 131 + seed) % 97) as f64 / 48.0 - 1.0;
                }
            }
            u
        };
        let (uh, ub) = (field(1), field(2));
        let (vh, vb) = ([0.3, -0.2, 0.5, 0.1, 0.7, -0.4], [-0.6, 0.25, 0.1, 0.9, -0.3, 0.2]);
        let tol = 1e-14;
        // Forward.
        let b = sys.rhs(&uh, &weights, &[vh]);
        let how = LinearSolve {
            preconditioner: Preconditioner::Mic0,
            tolerance: tol,
            max_iterations: 10_000,
        };
        let (p, _) = sys.solve(&b, &how);
        let mut u1 = uh.clone();
        sys.update_velocity(&p, &mut u1);
        let dv = sys.bodies[0].dt_minv_times(&sys.bodies[0].force(&p));
        let v1: [f64; 6] = std::array::from_fn(|d| vh[d] + dv[d]);
        // Adjoint.
        let (ua, va, _, _) = sys.projection_adjoint(&ub, &[vb], &weights, &how);
        let lhs = u1.dot(&ub) + (0..6).map(|d| v1[d] * vb[d]).sum::<f64>();
        let rhs = uh.dot(&ua) + (0..6).map(|d| vh[d] * va[0][d]).sum::<f64>();
        assert!((lhs - rhs).abs() <= 1e-10 * lhs.abs().max(rhs.abs()), "{lhs} vs {rhs}");
    }

    /// The free surface's position: ∂L/∂φ through the ghost-fluid θ (operator and update)
    /// against central differences of the whole projection, L = ⟨c, u'⟩.
    #[test]
    fn phi_adjoint_matches_central_differences() {
        let (sys, phi, weights) = system_with_inputs();
        let grid = sys.grid;
        let params = sys.params;
        let mut uh = Mac::zeros(&grid);
        let mut c = Mac::zeros(&grid);
        for a in 0..3 {
            for (f, x) in uh.c[a].iter_mut().enumerate() {
                *x = ((f * 7919 + a * 131) % 97) as f64 / 48.0 - 1.0;
            }
            for (f, x) in c.c[a].iter_mut().enumerate() {
                *x = ((f * 104729 + a * 71) % 89) as f64 / 44.0 - 1.0;
            }
        }
        let how = LinearSolve {
            preconditioner: Preconditioner::Mic0,
            tolerance: 1e-14,
            max_iterations: 10_000,
        };
        let run = |phi: &[f64]| {
            let sys = PressureSystem::build(&grid, phi, &weights, params);
            let (p, _) = sys.solve(&sys.rhs(&uh, &weights, &[]), &how);
            let mut u = uh.clone();
            sys.update_velocity(&p, &mut u);
            (u.dot(&c), p)
        };
        let (_, p) = run(&phi);
        let (s, _) = sys.solve(&sys.update_velocity_adjoint(&c), &how);
        let g = sys.phi_adjoint(&phi, &weights, &s, &p, &c);
        assert!(g.iter().filter(|x| **x != 0.0).count() > 20, "the surface cells carry a gradient");
        let d: Vec<f64> = (0..phi.len()).map(|i| ((i * 13) % 7) as f64 / 3.0 - 1.0).collect();
        let eps = 1e-8;
        let at = |s: f64| run(&phi.iter().zip(&d).map(|(x, y)| x + s * y).collect::<Vec<_>>()).0;
        let fd = (at(eps) - at(-eps)) / (2.0 * eps);
        let ad: f64 = g.iter().zip(&d).map(|(a, b)| a * b).sum();
        assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "adjoint {ad:e}, central difference {fd:e}");
    }

    #[test]
    fn operator_is_symmetric() {
        let sys = system();
        let n = sys.len();
        let x: Vec<f64> = (0..n).map(|i| ((i * 7919) % 13) as f64 - 6.0).collect();
        let y: Vec<f64> = (0..n).map(|i| ((i * 104729) % 17) as f64 - 8.0).collect();
        let (mut ax, mut ay) = (vec![0.0; n], vec![0.0; n]);
        sys.apply(&x, &mut ax);
        sys.apply(&y, &mut ay);
        let (l, r) = (crate::geometry::grid::dot(&ax, &y), crate::geometry::grid::dot(&x, &ay));
        assert!((l - r).abs() <= 1e-13 * l.abs().max(r.abs()), "{l} vs {r}");
    }
}
