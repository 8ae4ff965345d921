//! Building the system: the unknowns, the stencil, the faces the update acts on.

use crate::geometry::grid::{Grid, NONE};
use crate::geometry::weights::FaceWeights;
use crate::math::buffer::{clear_for, refill};
use crate::math::par::{for_each_keyed_mut, MIN_LEN};
use rayon::prelude::*;

use super::*;

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
                                diag += s * w / params.ghost.theta(phi[c], phi[n]);
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
        let busy = sys.rows_with_unknowns();
        sys.projected_faces(0, weights, phi, &busy, &mut fx);
        sys.projected_faces(1, weights, phi, &busy, &mut fy);
        sys.projected_faces(2, weights, phi, &busy, &mut fz);
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
        // A row's six faces and neighbours are some ten times a plain pass's work a cell: in
        // pieces of a tenth of a pass's (on the pool's 18 k rows, one piece was 0.26 ms, the
        // same on one thread and two).
        let mut reached: Vec<bool> = self
            .cell_of_row
            .par_iter()
            .with_min_len(MIN_LEN / 10)
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

    /// Per row of cells along x (index j + n₁·k), whether it holds an unknown.
    fn rows_with_unknowns(&self) -> Vec<bool> {
        let n = self.grid.n;
        let mut busy = vec![false; n[1] * n[2]];
        for &c in &self.cell_of_row {
            busy[c as usize / n[0]] = true;
        }
        busy
    }

    /// The faces of `axis` next to a liquid cell that the velocity update acts on, each once,
    /// sorted, into `out`: those where [`PressureSystem::face_gradient`] gives a gradient. In
    /// two parallel passes over the slabs of the face lattice (count, then fill each slab's
    /// share of `out`), so nothing but `out` is allocated. A row of faces between rows of
    /// cells without unknowns (`busy`, see [`PressureSystem::rows_with_unknowns`]) has none
    /// and is skipped: the air above a pool, and a band's deep cells below its surface.
    fn projected_faces(
        &self,
        axis: usize,
        weights: &FaceWeights,
        phi: &[f64],
        busy: &[bool],
        out: &mut Vec<ProjectedFace>,
    ) {
        let lat = self.grid.faces(axis);
        let nz = lat.n[2];
        let rows = &self.row_of_cell;
        let [_, n1, _] = self.grid.n;
        // The rows of cells on either side of the faces (j, k) of `axis`: the same row along
        // x, the rows at j − 1 and j (k − 1 and k) along y (z).
        let live = |j: usize, k: usize| match axis {
            0 => busy[j + n1 * k],
            1 => busy[j - 1 + n1 * k] || busy[j + n1 * k],
            _ => busy[j + n1 * (k - 1)] || busy[j + n1 * k],
        };
        // A face has a gradient when a cell on either side is an unknown: counted without
        // computing it.
        let counts: Vec<usize> = (0..nz)
            .into_par_iter()
            .map(|k| {
                let mut count = 0;
                open_faces(&self.grid, axis, k, weights, live, |_, m, pl| {
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
            open_faces(&self.grid, axis, k, weights, live, |f, m, pl| {
                if let Some(gradient) = self.gradient_between(m, pl, phi) {
                    *next.next().expect("counted") = ProjectedFace { face: f as u32, gradient };
                }
            });
        });
    }
}
