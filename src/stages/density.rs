//! Particle density projection (Kugelstadt, Longva, Thuerey & Bender 2019, "Implicit
//! density projection for volume conserving liquids"), the `density` stage, with its adjoint.
//!
//! Trilinear interpolation of a discretely divergence-free MAC field is not divergence-free
//! between the samples, and marker particles drift together where it converges, most of all
//! in the half cell next to a wall: the grid sees a full cell, the particles fill part of it,
//! and volume is lost. The projection measures the particles' density on cell centres and
//! solves one more Poisson problem on the same operator as the pressure, whose gradient is a
//! displacement that carries each over-full cell's excess volume out of it. It is a scene
//! option (`solver.density_correction`).
//!
//! The map, for particles P: φ = SDF(P) (the operator's liquid), dens = deposit(P),
//! b = gain·excess(dens)·dx³ on liquid cells, A q = b, d = C(−G q) (one
//! extrapolation layer), and each particle moves by d(x) capped at half a cell, then is
//! kept out of the static solids. Its adjoint ([`DensityProjection::adjoint`]) is one more
//! solve with the same A, and the derivatives of the deposit, of φ (through the ghost-fluid
//! θ) and of the interpolated displacement.
//!
//! The excess is two-sided in the liquid's interior and one-sided elsewhere
//! (`excess`): a cell whose 3×3×3 block holds liquid only (no air, no solid, every face
//! open) should hold exactly one cell of particles, so it pushes out what it holds over that
//! and draws in what it lacks; a cell next to air or a solid is legitimately part empty, and
//! only pushes out an excess. With the excess alone (Kugelstadt et al. correct compressions
//! only), a body bobbing in the water was an energy pump: the particles bunch a little below
//! a rising body and spread out below a sinking one, the projection lifted each bunching to
//! the free surface (ρ·g·V·depth of potential energy) and never brought a spreading back
//! down, and a ball dropped from 5 cm above its floating height gained 2.8 J in 3 s instead
//! of settling (issue 33). Both sides have a dead zone of 10⁻⁶ (round-off in the deposit
//! must not start a solve), subtracted so that b is continuous in the density.
//!
//! The right-hand side is `gain` times the excess (`solver.density_gain`, default 1.75): the
//! deposit sees only part of a displacement (a one-cell divergence is 0.42 of its own
//! cell's reading, and none of a particle's motion within the half cell next to a wall), so
//! a displacement of exactly the excess took out 41% of the dam break's excess in a step.
//!
//! A cell's excess fades out over the tenth of a cell under the surface (its own φ_L): the
//! deposit reads the cells around, so a cell just turning liquid can be over full, and its
//! excess came on whole as it entered the operator. With `solver.surface_blend` the
//! displacement's one layer blends its liquid–air faces as the velocity's extrapolation does
//! (`DensityProjection::surface`).
//!
//! Where the interior ends, the deficit fades out instead of stopping
//! (`interior_weights`): as the block's highest φ_L rises to zero from a tenth of a cell
//! below, and as a body comes from √3 cells to half a cell closer. A yes/no interior was a
//! jump of the forward map: one cell of a block crossing φ_L = 0 switched a deficit of up to
//! 30% of a cell on or off, and moved particles by up to a quarter of a cell in that step.
//!
//! With a narrow band (`band.rs`), the deep cells are full by construction and carry no
//! particles: every face of a deep cell is closed to the projection, which then has the
//! band's cells only and pushes the band's excess along the band to the air (on
//! `large_tank`, 82 k rows instead of 470 k). Pushed into the deep cells instead, the excess
//! would only be owed back to the band. Where some excess could reach the air only through
//! the deep cells (a band sealed off by them), the closed operator is singular there, and
//! the projection is the whole liquid's, as without a band.

use crate::error::{Error, Result};
use crate::geometry::body::RigidBody;
use crate::geometry::fractions::NodeSdf;
use crate::geometry::grid::{Grid, Mac, MacSampler};
use crate::geometry::weights::FaceWeights;
use crate::math::dual::Dual;
use crate::math::{Twist, Vec3};
use crate::solvers::cg::CgStats;
use crate::solvers::LinearSolve;
use crate::stages::band::Band;
use crate::stages::extrapolate::{
    correct_velocity_adjoint, extrapolate_one_layer, extrapolate_one_layer_blended,
    extrapolate_one_layer_blended_adjoint, surface_faces, SurfaceBlend, SurfaceFaces,
};
use crate::stages::pressure::{
    has_open_face, GhostFluid, PressureParams, PressureSystem, SystemPool,
};
use crate::stages::solid_phi::{solidity_pose_adjoint, value_reads, PartialSolid, SolidExtension};
use crate::stages::surface::{self, jacobian_step, Bins, Walls};
use crate::stages::system::NEAR_SOLID;
use rayon::prelude::*;

/// Densities within this much of full count as full.
const DEAD_ZONE: f64 = 1e-6;

/// Over how much depth (in cells) a cell's deficit fades out as the highest φ_L of its
/// 3×3×3 block rises to zero (see `interior_weights`).
pub const DEPTH_RAMP: f64 = 0.1;

/// How much closer than [`NEAR_SOLID`] cells (in cells) a body may come to a cell centre
/// while the cell's deficit fades out (see `interior_weights`).
const BODY_RAMP: f64 = 0.5;

/// A cell's excess density (in cells): over `1 + DEAD_ZONE` it pushes out what it holds
/// over, times its `depth` weight ([`depth_weight`] of its own φ_L); under `1 − DEAD_ZONE`
/// it draws in what it lacks, times its `interior` weight (0 to 1). Continuous in `dens`,
/// `interior` and `depth`. The depth weight fades the excess of a cell whose centre is
/// within a tenth of a cell of the surface: the deposit reads the particles of the cells
/// around, so a cell just turning liquid can be over full (those below it bunched), and
/// its excess came on whole as it entered the operator, a jump of the step (traced on the
/// surge: a cell at φ_L = −2.4e-6 m with 2% too many particles).
#[inline]
fn excess(dens: f64, interior: f64, depth: f64) -> f64 {
    let over = dens - 1.0 - DEAD_ZONE;
    let under = dens - 1.0 + DEAD_ZONE;
    if over > 0.0 {
        depth * over
    } else if under < 0.0 {
        interior * under
    } else {
        0.0
    }
}

/// The derivatives of [`excess`] in `dens`, `interior` and `depth`.
#[inline]
fn excess_derivatives(dens: f64, interior: f64, depth: f64) -> (f64, f64, f64) {
    let over = dens - 1.0 - DEAD_ZONE;
    let under = dens - 1.0 + DEAD_ZONE;
    if over > 0.0 {
        (depth, 0.0, over)
    } else if under < 0.0 {
        (interior, under, 0.0)
    } else {
        (0.0, 0.0, 0.0)
    }
}

/// How much of each cell's deficit counts (see [`excess`]), 0 to 1: 1 in the liquid's
/// interior, where a cell at rest holds exactly one cell of particles; 0 next to air or a
/// solid, where a cell is legitimately part empty. It is a row of `sys` built on `phi`, not
/// a band's deep cell, and the least of
/// - its depth: clamp(−φ_max/([`DEPTH_RAMP`]·dx), 0, 1), φ_max the highest φ_L over its
///   3×3×3 block (within the tank: the deposit reflects at the walls, so a wall is no gap;
///   a band's deep cell counts as air), and
/// - per body, its clearance: clamp(1 + (d − [`NEAR_SOLID`]·dx)/([`BODY_RAMP`]·dx), 0, 1),
///   d the body's distance at the cell centre (within √3 cells a body reaches the box
///   between the centres of the cell's neighbours, which its deposit reads).
///
/// Cells near a static solid count 0: the static solids do not move. Both ramps keep the
/// weight continuous in the particles and the bodies' poses: a yes/no interior made the
/// projection jump when one cell of a block crossed φ_L = 0 or a body moved past a cell
/// (docs/gradients.md, "The density projection's interior"). The clearance is 1 wherever
/// the yes/no rule counted a cell: with its ramp inside (0 at √3 cells) a bobbing ball
/// gained 0.33 J in the energy audit instead of 0.22 J. The depth ramp lies inside the old
/// interior: outside it (0 from a tenth of a cell above zero) the dam break's particles
/// lost 3.3% of its volume in 50 steps (tests/physics/dam_break.rs allows 3%).
fn interior_weights(sys: &PressureSystem, phi: &[f64], g: &DensityInputs<'_>) -> Vec<f64> {
    let grid = g.grid;
    let mut high: Vec<f64> = phi
        .par_iter()
        .enumerate()
        .with_min_len(crate::math::par::MIN_LEN)
        .map(|(c, &p)| if g.counts_excess(c) { p } else { f64::INFINITY })
        .collect();
    for axis in 0..3 {
        high = block_max(grid, &high, axis);
    }
    let mut w: Vec<f64> = high
        .par_iter()
        .enumerate()
        .with_min_len(crate::math::par::MIN_LEN)
        .map(|(c, &h)| {
            let row = sys.row_of_cell[c] != crate::geometry::grid::NONE;
            if row && g.counts_excess(c) && !g.near_solid[c] {
                depth_weight(h, grid.dx)
            } else {
                0.0
            }
        })
        .collect();
    let cells = grid.cells();
    for b in g.bodies {
        // The cells whose centre may be within NEAR_SOLID cells of the body.
        let (lo, hi) = b.bounds();
        let reach = Vec3::splat(NEAR_SOLID * grid.dx);
        grid.for_cells_in_box(lo - reach, hi + reach, |c, [i, j, k]| {
            if w[c] > 0.0 {
                w[c] = w[c].min(body_weight(b.sdf(cells.position(i, j, k)), grid.dx));
            }
        });
    }
    w
}

/// The interior weight's depth part for the highest φ of a block, `high`.
#[inline]
fn depth_weight(high: f64, dx: f64) -> f64 {
    (-high / (DEPTH_RAMP * dx)).clamp(0.0, 1.0)
}

/// The interior weight's part for a body at distance `d` from the cell centre.
#[inline]
fn body_weight(d: f64, dx: f64) -> f64 {
    (1.0 + (d - NEAR_SOLID * dx) / (BODY_RAMP * dx)).clamp(0.0, 1.0)
}

/// Per cell, the largest of `d` over the cell and its two neighbours along `axis` within
/// the tank: three passes give the largest over the 3×3×3 block. Whole rows (or slabs) at a
/// time, a z-slab a task: `d[c].max(d[c − s]).max(d[c + s])` for the cells with both
/// neighbours, in that order of operations.
fn block_max(grid: &Grid, d: &[f64], axis: usize) -> Vec<f64> {
    let [n0, n1, n2] = grid.n;
    let slab = n0 * n1;
    let fold = |o: &mut [f64], src: &[f64]| o.iter_mut().zip(src).for_each(|(o, &v)| *o = o.max(v));
    let mut out = d.to_vec();
    out.par_chunks_mut(slab).enumerate().for_each(|(k, o)| {
        let own = &d[k * slab..][..slab];
        match axis {
            0 if n0 > 1 => {
                for (row, src) in o.chunks_mut(n0).zip(own.chunks(n0)) {
                    fold(&mut row[1..], &src[..n0 - 1]);
                    fold(&mut row[..n0 - 1], &src[1..]);
                }
            }
            1 if n1 > 1 => {
                fold(&mut o[n0..], &own[..slab - n0]);
                fold(&mut o[..slab - n0], &own[n0..]);
            }
            2 => {
                if k > 0 {
                    fold(o, &d[(k - 1) * slab..][..slab]);
                }
                if k + 1 < n2 {
                    fold(o, &d[(k + 1) * slab..][..slab]);
                }
            }
            _ => {}
        }
    });
    out
}

/// What sets the interior weight of a cell where it is strictly between 0 and 1 (see
/// `interior_weights`), for the adjoint.
enum WeightSetBy {
    /// The depth, by φ of this cell of the block.
    Depth(usize),
    /// The clearance of this body, with its distance's derivative along the pose.
    Body(usize, Dual<6>),
}

/// Which part of `interior_weights` sets the weight `w` of cell `c` (the least one; the
/// depth where they tie).
fn weight_set_by(c: usize, w: f64, phi: &[f64], g: &DensityInputs<'_>) -> WeightSetBy {
    let grid = g.grid;
    let [i, j, k] = grid.cells().ijk(c);
    let mut best = (f64::NEG_INFINITY, c);
    for l in k.saturating_sub(1)..grid.n[2].min(k + 2) {
        for m in j.saturating_sub(1)..grid.n[1].min(j + 2) {
            for n in i.saturating_sub(1)..grid.n[0].min(i + 2) {
                let b = grid.cell(n, m, l);
                let p = if g.counts_excess(b) { phi[b] } else { f64::INFINITY };
                if p > best.0 {
                    best = (p, b);
                }
            }
        }
    }
    if depth_weight(best.0, grid.dx) == w {
        return WeightSetBy::Depth(best.1);
    }
    let centre = grid.cells().position(i, j, k);
    let body = g
        .bodies
        .iter()
        .position(|b| body_weight(b.sdf(centre), grid.dx) == w)
        .expect("the interior weight is its depth's or a body's");
    WeightSetBy::Body(body, g.bodies[body].sdf_pose_dual(centre))
}

/// What the projection did.
#[derive(Clone, Copy, Debug, Default)]
pub struct DensityStats {
    /// Excess volume (m³) in over-full cells before the push.
    pub excess_volume: f64,
    /// CG iterations of the projection solve.
    pub cg_iterations: usize,
}

/// Geometry the projection needs.
pub struct DensityInputs<'a> {
    /// The grid.
    pub grid: &'a Grid,
    /// Face fluid weights of the solids.
    pub weights: &'a FaceWeights,
    /// Solid signed distance at nodes.
    pub node_sdf: &'a NodeSdf,
    /// Cells whose centre is in a solid.
    pub centre_in_solid: &'a [bool],
    /// Those of them partly in a body (see [`crate::stages::system::Geometry::partial`]).
    pub partial: &'a [PartialSolid],
    /// Cells whose centre is within [`NEAR_SOLID`] cells of a static solid (it reaches the box
    /// between the centres of their neighbours, which their deposit reads).
    pub near_solid: &'a [bool],
    /// The bodies where the step's geometry has them (their clearance weighs the cells'
    /// deficit, see `interior_weights`).
    pub bodies: &'a [RigidBody],
    /// The sites each of `bodies` displaced (the soft minimum of φ_L counts them where the
    /// bodies are, see `stages/surface/ghosts.rs`).
    pub displaced: &'a [surface::Displaced],
    /// Gravity, m/s² (φ_L is carried into the solids across it, see [`SolidExtension`]).
    pub gravity: [f64; 3],
    /// How φ_L is made from the particles.
    pub surface: surface::SurfaceModel,
    /// Whether φ_L's value is made in every cell (`solver.surface_interior_values`), not
    /// only where the projection reads it (see [`surface::Reads`]).
    pub interior_values: bool,
    /// Marker particles seeded per cell (the density of a full cell).
    pub particles_per_cell: usize,
    /// How many times its excess a cell's displacement carries (`solver.density_gain`).
    pub gain: f64,
    /// How many times a step runs the projection (`solver.density_passes`; see
    /// [`crate::stages::particles::ParticleStage::settle`]).
    pub passes: usize,
    /// Below this weight a face carries its weight's share of the displacement
    /// (`solver.density_face_ramp`; 0: every open face all of it).
    pub face_ramp: f64,
    /// The ghost-fluid θ of the projection's operator.
    pub ghost: GhostFluid,
    /// How the displacement's liquid–air faces blend into its extrapolation layer (see
    /// [`SurfaceBlend`]; off, the yes/no rule, when its θ₁ is 0).
    pub blend: SurfaceBlend,
    /// How to solve it.
    pub solve: LinearSolve,
    /// The narrow band's deep cells (full liquid without particles), if the liquid has one.
    pub band: Option<&'a Band>,
    /// Memory to build the projection's system into, and to give it back to when done.
    pub systems: Option<&'a SystemPool>,
}

impl DensityInputs<'_> {
    /// The bodies' ghosts where they are, for a soft minimum of φ_L (none otherwise).
    fn ghosts(&self) -> Vec<Vec3> {
        surface::counted_ghosts(&self.surface, self.bodies, self.displaced)
    }

    /// A face field to overwrite (the pool's, when there is one).
    fn field(&self) -> Mac {
        self.systems.map_or_else(|| Mac::zeros(self.grid), |pool| pool.field(self.grid))
    }

    /// Hands a system and a face field no longer needed back to the pool, if there is one.
    pub fn give_back(&self, sys: Option<PressureSystem>, field: Option<Mac>) {
        let Some(pool) = self.systems else { return };
        if let Some(sys) = sys {
            pool.give(sys);
        }
        if let Some(field) = field {
            pool.keep_field(field);
        }
    }

    /// Whether the projection pushes out cell `c`'s excess: not in a band's deep cells, full
    /// by construction (what the particles near them deposit there is not an excess).
    fn counts_excess(&self, c: usize) -> bool {
        !self.band.is_some_and(|b| b.deep[c])
    }
}

/// One projection's system for particles P: what the displacement and the adjoint read.
pub struct DensityProjection {
    /// φ_L of P, extended into solids.
    pub phi: Vec<f64>,
    /// How φ_L was carried into the solids.
    pub extension: SolidExtension,
    /// The particle each cell's φ is the distance to (see [`surface::liquid_sdf_nearest`];
    /// `NONE` where the extension into the solids set φ). Empty in a forward step's
    /// projection, which has no adjoint.
    pub nearest: Vec<u32>,
    /// Particle density at cell centres.
    pub dens: Vec<f64>,
    /// How much of each cell's deficit counts (see `interior_weights`).
    pub interior: Vec<f64>,
    /// The operator (unit Δt and density: its velocity update is a displacement in metres).
    pub sys: PressureSystem,
    /// The right-hand side, the excess volume per row.
    pub b: Vec<f64>,
    /// Whether the operator was built closed at the band's deep cells (see the module's
    /// notes): with the inputs' weights, every face of a deep cell closed.
    pub deep_closed: bool,
    /// Those weights, when [`DensityProjection::deep_closed`], for the adjoint (a forward
    /// projection drops them before its solve).
    pub closed: Option<FaceWeights>,
    /// The displacement's liquid–air faces known in part under the inputs' blend (none when
    /// it is off; see [`SurfaceBlend`]).
    pub surface: SurfaceFaces,
}

impl DensityProjection {
    /// The system for particles `particles`, with all its adjoint reads; None when no cell
    /// is over full.
    pub fn build(particles: &[Vec3], g: &DensityInputs<'_>) -> Option<DensityProjection> {
        DensityProjection::build_with(particles, g, true)
    }

    /// [`DensityProjection::build`] for a forward step: without what only the adjoint reads
    /// (see [`DensityProjection::without_adjoint_inputs`]; the nearest particles are not
    /// even found).
    fn build_forward(particles: &[Vec3], g: &DensityInputs<'_>) -> Option<DensityProjection> {
        let proj = DensityProjection::build_with(particles, g, false)?;
        Some(proj.without_adjoint_inputs())
    }

    /// [`DensityProjection::build`], with [`DensityProjection::nearest`] only when
    /// `adjoint` (empty otherwise).
    fn build_with(
        particles: &[Vec3],
        g: &DensityInputs<'_>,
        adjoint: bool,
    ) -> Option<DensityProjection> {
        let grid = g.grid;
        let deep = g.band.map(Band::deep);
        // The bins serve φ_L only, so they are gone before the deposit's arrays are made.
        let (mut phi, nearest) = {
            let bins = Bins::new(particles, grid);
            let ghosts = g.ghosts();
            let (model, everywhere) = (&g.surface, g.interior_values);
            let near_solids = value_reads(grid, g.centre_in_solid, g.partial, model, everywhere);
            let reads = near_solids.as_deref().map(|near_solids| surface::Reads { near_solids });
            if adjoint {
                surface::liquid_sdf_nearest(particles, &bins, &ghosts, grid, model, deep, reads)
            } else {
                let phi = surface::liquid_sdf(particles, &bins, &ghosts, grid, model, deep, reads);
                (phi, Vec::new())
            }
        };
        // The weights closed at the deep cells beside φ's extension into the solids, which
        // they do not read (neither keeps two threads busy alone).
        let (extension, mut closed) = rayon::join(
            || SolidExtension::apply_new(grid, g.centre_in_solid, g.partial, g.gravity, &mut phi),
            || {
                g.band.filter(|b| b.deep.par_iter().any(|&d| d)).map(|b| {
                    g.weights
                        .close_faces(|a, kind, shut| closed_at_deep(grid, a, &b.deep, kind, shut))
                })
            },
        );
        let params = PressureParams { dt: 1.0, density: 1.0, ghost: g.ghost };
        let memory = g.systems.map(SystemPool::take).unwrap_or_default();
        let weights = closed.as_ref().unwrap_or(g.weights);
        // The deposit beside the operator's build, which reads φ only: the deposit's loops
        // keep two threads busy, the build's passes less so.
        let base = g.band.map(|b| b.density.as_slice());
        let (dens, mut sys) = rayon::join(
            || surface::particle_density(particles, grid, g.particles_per_cell, base),
            || PressureSystem::build_in(memory, grid, &phi, weights, params),
        );
        // When a row is over full the solve will come (unless the excess has no way to the
        // air, rare): its preconditioner is factored beside the interior weights and that
        // check, which do not read it (neither keeps two threads busy alone). The same
        // factoring as the solve's own, so the same bits.
        let over_full =
            sys.cell_of_row.par_iter().with_min_len(crate::math::par::MIN_LEN).any(|&c| {
                let c = c as usize;
                g.counts_excess(c) && excess(dens[c], 0.0, 1.0) > 0.0
            });
        let ((), (mut interior, reaches)) = rayon::join(
            || {
                if over_full {
                    sys.prepare(&g.solve);
                }
            },
            || {
                let interior = interior_weights(&sys, &phi, g);
                let reaches = closed.is_none()
                    || excess_reaches_air(&sys, weights, &phi, &dens, &interior, g);
                (interior, reaches)
            },
        );
        if !reaches {
            // Some excess has no way to the air but through the deep cells: the whole liquid's
            // operator, as without a band.
            closed = None;
            sys = PressureSystem::build_in(sys.into_memory(), grid, &phi, g.weights, params);
            interior = interior_weights(&sys, &phi, g);
        }
        let vol = grid.dx.powi(3);
        let b: Vec<f64> = sys
            .cell_of_row
            .par_iter()
            .with_min_len(crate::math::par::MIN_LEN)
            .map(|&c| {
                let c = c as usize;
                if g.counts_excess(c) {
                    g.gain * excess(dens[c], interior[c], depth_weight(phi[c], grid.dx)) * vol
                } else {
                    0.0
                }
            })
            .collect();
        let deep_closed = closed.is_some();
        // No body covers a face here: the weights are not read.
        let surface = surface_faces(&sys, &phi, &[], g.weights, g.weights, g.blend);
        let proj = DensityProjection {
            phi,
            extension,
            nearest,
            dens,
            interior,
            sys,
            b,
            deep_closed,
            closed,
            surface,
        };
        if proj.b.par_iter().all(|&x| x == 0.0) {
            proj.give_back(g);
            return None;
        }
        Some(proj)
    }

    /// The face weights the operator was built with (see [`DensityProjection::closed`]).
    ///
    /// # Panics
    /// When the projection was closed at the deep cells and its closed weights were dropped
    /// (a forward projection's, which no adjoint reads).
    pub fn weights<'w>(&'w self, g: &'w DensityInputs<'_>) -> &'w FaceWeights {
        assert_eq!(self.closed.is_some(), self.deep_closed, "the closed weights were dropped");
        self.closed.as_ref().unwrap_or(g.weights)
    }

    /// Hands the system's memory back to the inputs' pool.
    pub fn give_back(self, g: &DensityInputs<'_>) {
        g.give_back(Some(self.sys), None);
    }

    /// The projection with only what a forward step reads after the build (the system and
    /// the right-hand side): φ, the nearest particles and the density, which only the
    /// adjoint reads, freed before the solve (21 MB at a million cells), and the closed
    /// weights (3 MB).
    fn without_adjoint_inputs(self) -> DensityProjection {
        let (phi, nearest, dens, interior) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        DensityProjection { phi, nearest, dens, interior, closed: None, ..self }
    }

    /// Solves for the potential q. `step` names the step in errors.
    pub fn solve(&self, g: &DensityInputs<'_>, step: usize) -> Result<(Vec<f64>, CgStats)> {
        let (q, stats) = self.sys.solve(&self.b, &g.solve);
        if !stats.converged {
            return Err(Error::NotConverged {
                solve: crate::error::Solve::Density,
                step,
                iterations: stats.iterations,
                residual: stats.relative_residual,
                tolerance: g.solve.tolerance,
            });
        }
        Ok((q, stats))
    }

    /// The displacement field of potential `q` and the faces it was projected on.
    pub fn displacement(&self, q: &[f64], g: &DensityInputs<'_>) -> Displacement {
        // C(−G q) with one layer: zero, then the faces of the rows by the update, then the
        // layer from their neighbours only, zero on the faces the operator is closed at (the
        // inputs' closed faces, and every face of a deep cell: the closed weights' zeros,
        // without reading them). The same bits as `correct_velocity` and `closed_at_deep`
        // (`displacement_by_passes` in the tests), without their passes over the lattices.
        let (mut d, valid0) = self.updated(q, g);
        let surface = &self.surface;
        for (a, field) in d.c.iter_mut().enumerate() {
            let lat = g.grid.faces(a);
            let closed = self.closed_at(g, a);
            if surface[a].is_empty() {
                let face = |pf: &crate::stages::pressure::ProjectedFace| pf.face as usize;
                extrapolate_one_layer(field, &valid0[a], &self.sys.faces[a], face, &lat, closed);
            } else {
                extrapolate_one_layer_blended(field, &valid0[a], &surface[a], &lat, closed);
            }
        }
        through_walls(&mut d, g.grid);
        Displacement { d, valid0 }
    }

    /// −G q on the faces of the rows, zero elsewhere (a field of the inputs' pool), and the
    /// faces it set: the displacement before its extrapolation layer.
    fn updated(&self, q: &[f64], g: &DensityInputs<'_>) -> (Mac, [Vec<u8>; 3]) {
        let mut d = g.field();
        for c in &mut d.c {
            c.par_chunks_mut(crate::math::par::MIN_LEN).for_each(|c| c.fill(0.0));
        }
        let valid0 = self.sys.velocity_update_into(q, &mut d);
        for (a, f, share) in self.faded_faces(g) {
            d.c[a][f as usize] *= share;
        }
        (d, valid0)
    }

    /// The faces the face ramp fades (`g.face_ramp`): (axis, face, its share w/`face_ramp`)
    /// of each face the update acts on whose weight w is under the ramp, in face order. The
    /// weights are the inputs': a face the update acts on is open, so not one the projection
    /// closed at a deep cell, whose weights a forward step's projection no longer keeps.
    fn faded_faces(&self, g: &DensityInputs<'_>) -> Vec<(usize, u32, f64)> {
        let ramp = g.face_ramp;
        let mut out = Vec::new();
        if ramp <= 0.0 {
            return out;
        }
        let weights = g.weights;
        for (a, faces) in self.sys.faces.iter().enumerate() {
            for pf in faces {
                let w = weights.weight(a, pf.face as usize);
                if w < ramp {
                    out.push((a, pf.face, w / ramp));
                }
            }
        }
        out
    }

    /// Adjoint of the face ramp of [`DensityProjection::updated`] (`g.face_ramp`): scales
    /// `dbar` on the faded faces by their share and returns, per faded face (axis, face),
    /// ∂L/∂w: the displacement it would carry unfaded, over the ramp, times its d̄.
    fn face_ramp_adjoint(
        &self,
        q: &[f64],
        g: &DensityInputs<'_>,
        dbar: &mut Mac,
    ) -> Vec<(usize, u32, f64)> {
        let faded = self.faded_faces(g);
        let ramp = g.face_ramp;
        faded
            .into_iter()
            .map(|(a, f, share)| {
                let bar = &mut dbar.c[a][f as usize];
                let full = -self.sys.velocity_update_at(a, f as usize, q);
                let wbar = *bar * full / ramp;
                *bar *= share;
                (a, f, wbar)
            })
            .collect()
    }

    /// Whether the operator is closed at face `f` of `axis`: the inputs' closed faces, and
    /// every face of a deep cell when [`DensityProjection::deep_closed`] (the closed
    /// weights' zeros, without reading them).
    fn closed_at<'g>(
        &self,
        g: &'g DensityInputs<'_>,
        axis: usize,
    ) -> impl Fn(usize) -> bool + Sync + 'g {
        let grid = g.grid;
        let lat = grid.faces(axis);
        let deep = self
            .deep_closed
            .then(|| &g.band.expect("a projection closed at deep cells has a band").deep);
        move |f: usize| {
            g.weights.closed(axis, f)
                || deep.is_some_and(|deep| {
                    let (m, p) = grid.face_cells(axis, lat.ijk(f));
                    m.is_some_and(|c| deep[c]) || p.is_some_and(|c| deep[c])
                })
        }
    }

    /// [`DensityProjection::displacement`] as it was computed before (whole-lattice
    /// passes): the reference its bits are checked against.
    #[cfg(test)]
    fn displacement_by_passes(&self, q: &[f64], g: &DensityInputs<'_>) -> Displacement {
        let mut d = g.field();
        let valid0 = self.sys.velocity_update_into(q, &mut d);
        let mut valid = valid0.clone();
        crate::stages::extrapolate::correct_velocity(&mut d, &mut valid, g.weights, g.grid, 1);
        if self.deep_closed {
            let deep = &g.band.expect("a projection closed at deep cells has a band").deep;
            for (a, field) in d.c.iter_mut().enumerate() {
                closed_at_deep(g.grid, a, deep, field, 0.0);
            }
        }
        through_walls(&mut d, g.grid);
        Displacement { d, valid0 }
    }

    /// Moves the particles by the displacement of potential `q` (capped at half a cell),
    /// keeping them out of the static solids.
    pub fn displace(&self, particles: &mut [Vec3], q: &[f64], g: &DensityInputs<'_>) {
        let disp = self.displacement(q, g);
        self.displace_by(particles, &disp, g);
        g.give_back(None, Some(disp.d));
    }

    /// [`DensityProjection::displace`] by a displacement already computed.
    pub fn displace_by(&self, particles: &mut [Vec3], disp: &Displacement, g: &DensityInputs<'_>) {
        let walls = Walls::new(g.grid, g.node_sdf);
        let d = MacSampler::new(&disp.d, g.grid);
        particles.par_iter_mut().for_each(|x| *x = walls.keep(*x + capped(d.velocity(*x), g.grid)));
    }

    /// Adjoint of [`DensityProjection::displace`] composed with the system's dependence on
    /// the particles: given ∂L/∂(displaced positions) in `pbar`, leaves ∂L/∂(positions before)
    /// there. `particles` are the positions the system was built from, `q` its solution.
    /// The bodies' ∂L/∂[δx; δθ] through the interior weights is added to `pose` (one per
    /// body of the inputs). Returns the adjoint solve's solution s (for the pose derivative of
    /// the weights, which the caller takes) and its statistics, and ∂L/∂w of the faces the
    /// face ramp faded (axis, face, ∂L/∂w; for the same).
    pub fn adjoint(
        &self,
        particles: &[Vec3],
        q: &[f64],
        pbar: &mut [Vec3],
        pose: &mut [Twist],
        g: &DensityInputs<'_>,
    ) -> WeightAdjoint {
        let disp = self.displacement(q, g);
        let out = self.adjoint_with(particles, q, &disp, pbar, pose, g);
        g.give_back(None, Some(disp.d));
        out
    }

    /// [`DensityProjection::adjoint`] with the displacement of `q` already computed (the
    /// backward pass has it from replaying the displacement).
    pub fn adjoint_with(
        &self,
        particles: &[Vec3],
        q: &[f64],
        disp: &Displacement,
        pbar: &mut [Vec3],
        pose: &mut [Twist],
        g: &DensityInputs<'_>,
    ) -> WeightAdjoint {
        let grid = g.grid;
        assert_eq!(
            self.nearest.len(),
            grid.num_cells(),
            "a forward step's projection (built without its adjoint's inputs) has no adjoint"
        );
        let Displacement { d, valid0 } = disp;
        let walls = Walls::new(grid, g.node_sdf);
        let step = jacobian_step(grid);
        // y = x + cap(d(x)), x' = keep(y): each particle's own part in parallel, its read of d
        // at x scattered into d̄ in particle order.
        let mut dbar = Mac::zeros(grid);
        surface::scatter_reads_in_chunks(pbar, 1, grid, &mut dbar, |first, xbs, reads| {
            let xs = &particles[first..first + xbs.len()];
            xs.par_iter()
                .zip(xbs.par_iter_mut())
                .zip(reads.par_iter_mut())
                .with_min_len(1024)
                .for_each(|((x, xb), read)| {
                    if *xb == Vec3::ZERO {
                        *read = (*x, Vec3::ZERO);
                        return;
                    }
                    let (v, jd) = d.velocity_jacobian(grid, *x);
                    let y = *x + capped(v, grid);
                    let ybar =
                        if walls.keep(y) == y { *xb } else { walls.keep_adjoint(y, *xb, step) };
                    let vbar = capped_adjoint(v, grid, ybar);
                    *xb = ybar + vbar.x * jd[0] + vbar.y * jd[1] + vbar.z * jd[2];
                    *read = (*x, vbar);
                });
        });
        // The tank walls' faces are their neighbours' (`through_walls`).
        through_walls_adjoint(&mut dbar, grid);
        // d = C(−k·G·q), its blended faces' shares read from φ.
        let surface = &self.surface;
        let mut share_bar = Vec::new();
        if surface.iter().all(Vec::is_empty) {
            correct_velocity_adjoint(&mut dbar, valid0, self.weights(g), grid, 1);
        } else {
            let (input, _) = self.updated(q, g);
            for (a, sf) in surface.iter().enumerate() {
                let (lat, closed) = (grid.faces(a), self.closed_at(g, a));
                let (adj, inp) = (&mut dbar.c[a], &input.c[a]);
                let bars =
                    extrapolate_one_layer_blended_adjoint(adj, inp, &valid0[a], sf, &lat, closed);
                share_bar.extend(sf.iter().zip(bars));
            }
            g.give_back(None, Some(input));
        }
        let ramp_bar = self.face_ramp_adjoint(q, g, &mut dbar);
        let qbar = self.sys.update_velocity_adjoint(&dbar);
        let (s, stats) = self.sys.solve(&qbar, &g.solve);
        // b = gain·excess(dens, interior, depth)·dx³ on the rows (0 on a band's deep cells).
        let vol = g.gain * grid.dx.powi(3);
        let mut dens_bar = vec![0.0; grid.num_cells()];
        let (mut interior_bar, mut depth_bar) = (Vec::new(), Vec::new());
        for (r, &c) in self.sys.cell_of_row.iter().enumerate() {
            let c = c as usize;
            if !g.counts_excess(c) {
                continue;
            }
            let depth = depth_weight(self.phi[c], grid.dx);
            let (d_dens, d_interior, d_depth) =
                excess_derivatives(self.dens[c], self.interior[c], depth);
            dens_bar[c] = vol * s[r] * d_dens;
            if d_depth != 0.0 && depth > 0.0 && depth < 1.0 {
                depth_bar.push((c, vol * s[r] * d_depth));
            }
            if d_interior != 0.0 && self.interior[c] > 0.0 && self.interior[c] < 1.0 {
                interior_bar.push((c, vol * s[r] * d_interior));
            }
        }
        surface::particle_density_adjoint(particles, grid, g.particles_per_cell, &dens_bar, pbar);
        // The operator and the update read φ through the ghost-fluid θ, the interior
        // weights through the depth (and the bodies' poses through the clearance).
        let mut phi_bar = self.sys.phi_adjoint(&self.phi, self.weights(g), &s, q, &dbar);
        for (sf, c_bar) in share_bar {
            phi_bar[sf.liquid as usize] += c_bar * sf.gradient[0];
            phi_bar[sf.air as usize] += c_bar * sf.gradient[1];
        }
        for (c, bar) in depth_bar {
            phi_bar[c] -= bar / (DEPTH_RAMP * grid.dx);
        }
        for (c, bar) in interior_bar {
            match weight_set_by(c, self.interior[c], &self.phi, g) {
                WeightSetBy::Depth(n) => phi_bar[n] -= bar / (DEPTH_RAMP * grid.dx),
                WeightSetBy::Body(i, d) => {
                    for (p, dd) in pose[i].iter_mut().zip(d.d) {
                        *p += bar * dd / (BODY_RAMP * grid.dx);
                    }
                }
            }
        }
        let sbar = self.extension.transpose(&self.phi, &mut phi_bar);
        let raw = self.extension.raw(&self.phi);
        solidity_pose_adjoint(grid, g.bodies, &sbar, pose);
        let deep = g.band.map(|b| b.deep.as_slice());
        let ghosts = g.ghosts();
        let mut gbar = vec![Vec3::ZERO; ghosts.len()];
        surface::liquid_sdf_adjoint(
            particles,
            &ghosts,
            &self.nearest,
            Some(&raw),
            grid,
            &g.surface,
            deep,
            &phi_bar,
            pbar,
            &mut gbar,
        );
        surface::ghost_pose_adjoint(g.bodies, g.displaced, &gbar, pose);
        (s, stats, ramp_bar)
    }
}

/// What [`DensityProjection::adjoint`] leaves for the pose derivative of the operator's
/// weights: the adjoint solve's solution s, its statistics, and per face the face ramp faded
/// (axis, face) its ∂L/∂w.
pub type WeightAdjoint = (Vec<f64>, CgStats, Vec<(usize, u32, f64)>);

/// Sets every face of a `deep` cell of `field` (the faces normal to `axis`, in the face
/// lattice's order) to `shut`, and leaves the others as they are. A deep cell is full by
/// construction (the narrow band carries no particles there), so the band's excess is not
/// pushed into it, where it would only be owed back to the band, but along the band to the
/// air: the projection's operator has the band's cells only, a few times fewer rows. Closes
/// the weights (`shut` the closed byte) and zeroes a displacement (`shut` = 0.0).
fn closed_at_deep<T: Copy + Send + Sync>(
    grid: &Grid,
    axis: usize,
    deep: &[bool],
    field: &mut [T],
    shut: T,
) {
    let n = grid.n;
    let lat = grid.faces(axis);
    let slab = lat.slab().max(1);
    field.par_chunks_mut(slab).enumerate().for_each(|(k, chunk)| {
        for (j, row) in chunk.chunks_mut(lat.n[0]).enumerate() {
            // The cells on either side of the row's faces, as rows of `deep`: the row itself
            // along x (its faces between cells i − 1 and i), the rows at j − 1 and j (k − 1
            // and k) along y (z), missing beyond the walls.
            let cells = |j: usize, k: usize| &deep[grid.cell(0, j, k)..][..n[0]];
            match axis {
                0 => {
                    let c = cells(j, k);
                    let m = n[0];
                    close_where(&mut row[1..m], &c[1..], Some(&c[..m - 1]), shut);
                    close_where(&mut row[..1], &c[..1], None, shut);
                    close_where(&mut row[m..], &c[m - 1..], None, shut);
                }
                _ => {
                    // The row `back` cells behind this one along y or z.
                    let behind = |back: usize| {
                        if axis == 1 {
                            cells(j - back, k)
                        } else {
                            cells(j, k - back)
                        }
                    };
                    let at = [j, k][axis - 1];
                    let below = (at > 0).then(|| behind(1));
                    match (at < n[axis]).then(|| behind(0)) {
                        Some(c) => close_where(row, c, below, shut),
                        None => close_where(row, below.expect("a face row"), None, shut),
                    }
                }
            }
        }
    });
}

/// `out[i] = shut` where `a[i]` or `b[i]` (a deep cell on either side of the face): a row at
/// a time.
#[inline(always)]
fn close_where<T: Copy>(out: &mut [T], a: &[bool], b: Option<&[bool]>, shut: T) {
    let len = out.len();
    let a = &a[..len];
    let b = b.map_or(a, |b| &b[..len]);
    for i in 0..len {
        if a[i] | b[i] {
            out[i] = shut;
        }
    }
}

/// Whether every over-full cell of `sys` (built with `weights`; its `interior_weights`
/// `interior`) can send its excess to the air: it is an unknown (when it has an open face in
/// the inputs' weights), and its unknown reaches one next to air through the operator.
/// Otherwise the system closed at the deep cells is singular where the excess is, or misses
/// it.
fn excess_reaches_air(
    sys: &PressureSystem,
    weights: &FaceWeights,
    phi: &[f64],
    dens: &[f64],
    interior: &[f64],
    g: &DensityInputs<'_>,
) -> bool {
    let dx = g.grid.dx;
    let excess = |c: usize| {
        excess(dens[c], interior[c], depth_weight(phi[c], dx)) != 0.0 && g.counts_excess(c)
    };
    let reached = sys.rows_reaching_air(weights);
    let rows_reach =
        sys.cell_of_row.par_iter().zip(&reached).all(|(&c, &r)| r || !excess(c as usize));
    rows_reach
        && (0..phi.len()).into_par_iter().with_min_len(crate::math::par::MIN_LEN).all(|c| {
            !(phi[c] < 0.0
                && excess(c)
                && sys.row_of_cell[c] == crate::geometry::grid::NONE
                && has_open_face(g.grid, g.weights, c))
        })
}

/// The displacement field of a density potential and the faces it was projected on: what
/// [`DensityProjection::displace`] moves the particles by, and what its adjoint reads.
#[derive(Debug)]
pub struct Displacement {
    /// The displacement on the faces (extrapolated one layer; the tank walls' faces their
    /// neighbours', see `through_walls`).
    pub d: Mac,
    /// The faces the potential's gradient set, before the extrapolation.
    pub valid0: [Vec<u8>; 3],
}

/// Each tank wall's faces of `d` (the faces normal to a wall, on it) given the value of the
/// face next to them inside: what the particles in the half cell next to a wall move by.
/// The displacement is zero on a wall, and interpolated it fell to zero across that half
/// cell, where the deposit (which folds the wall's side back into the cell) sees no motion:
/// a particle there moved by a fraction of what its cell asked and the wall cells kept
/// their excess, where every mode's volume went (docs/gradients.md, "The smooth
/// defaults"). The potential and the faces it sets are unchanged: only what the particles
/// read.
fn through_walls(d: &mut Mac, grid: &Grid) {
    for_wall_faces(grid, |a, wall, inner| d.c[a][wall] = d.c[a][inner]);
}

/// Adjoint of [`through_walls`], in place: each wall face's adjoint moved to the face next
/// to it.
fn through_walls_adjoint(dbar: &mut Mac, grid: &Grid) {
    for_wall_faces(grid, |a, wall, inner| {
        let bar = std::mem::take(&mut dbar.c[a][wall]);
        dbar.c[a][inner] += bar;
    });
}

/// Calls `visit(axis, wall face, the face next to it inside)` for every face on a tank wall
/// normal to it (both walls of each axis).
fn for_wall_faces(grid: &Grid, mut visit: impl FnMut(usize, usize, usize)) {
    for a in 0..3 {
        let lat = grid.faces(a);
        let n = lat.n;
        let (b, c) = ((a + 1) % 3, (a + 2) % 3);
        for (wall, inner) in [(0, 1), (n[a] - 1, n[a] - 2)] {
            for j in 0..n[b] {
                for k in 0..n[c] {
                    let at = |along: usize| {
                        let mut ijk = [0; 3];
                        (ijk[a], ijk[b], ijk[c]) = (along, j, k);
                        lat.index(ijk[0], ijk[1], ijk[2])
                    };
                    visit(a, at(wall), at(inner));
                }
            }
        }
    }
}

/// The displacement `v` capped at half a cell.
#[inline]
fn capped(v: Vec3, grid: &Grid) -> Vec3 {
    let cap = 0.5 * grid.dx;
    let len = v.length();
    if len > cap {
        v * (cap / len)
    } else {
        v
    }
}

/// Transpose of the Jacobian of [`capped`] at `v`, applied to `bar`.
#[inline]
fn capped_adjoint(v: Vec3, grid: &Grid, bar: Vec3) -> Vec3 {
    let cap = 0.5 * grid.dx;
    let len = v.length();
    if len > cap {
        let n = v / len;
        (cap / len) * (bar - n * n.dot(bar))
    } else {
        bar
    }
}

/// Pushes particles out of over-full cells. `step` names the step in errors. Returns what
/// it did and the potential q (None when no cell was over full), which a tape keeps.
pub fn correct(
    particles: &mut [Vec3],
    g: &DensityInputs<'_>,
    step: usize,
) -> Result<(DensityStats, Option<Vec<f64>>)> {
    let Some(proj) = DensityProjection::build_forward(particles, g) else {
        return Ok((DensityStats::default(), None));
    };
    let (q, stats) = proj.solve(g, step)?;
    Ok(displaced(proj, particles, q, stats.iterations, g))
}

/// [`correct`] with the potential a recorded run of the same step solved for (`q`, None when
/// it found no cell over full) and its iterations, instead of solving: a checkpointed
/// segment's re-run. An error if the particles do not build the system the record says.
pub fn correct_replayed(
    particles: &mut [Vec3],
    g: &DensityInputs<'_>,
    (q, iterations): (Option<Vec<f64>>, usize),
    step: usize,
) -> Result<(DensityStats, Option<Vec<f64>>)> {
    match (DensityProjection::build_forward(particles, g), q) {
        (None, None) => Ok((DensityStats::default(), None)),
        (Some(proj), Some(q)) if q.len() == proj.sys.len() => {
            Ok(displaced(proj, particles, q, iterations, g))
        }
        (proj, _) => {
            if let Some(p) = proj {
                p.give_back(g);
            }
            Err(crate::error::GradientError::NotDeterministic {
                step,
                what: "built another density projection than its forward pass".into(),
            }
            .into())
        }
    }
}

/// The particles moved by the potential `q` of `proj` (found in `iterations`), and what the
/// projection did.
fn displaced(
    proj: DensityProjection,
    particles: &mut [Vec3],
    q: Vec<f64>,
    iterations: usize,
    g: &DensityInputs<'_>,
) -> (DensityStats, Option<Vec<f64>>) {
    proj.displace(particles, &q, g);
    let excess_volume = proj.b.iter().map(|b| b.max(0.0)).sum::<f64>() / g.gain;
    let stats = DensityStats { excess_volume, cg_iterations: iterations };
    proj.give_back(g);
    (stats, Some(q))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::shape::Solid;
    use crate::solvers::Preconditioner;

    /// A pool of 8×4×6 cells in a tank of 8×8×6 with its bottom layers over full: particles
    /// squeezed toward the floor, and jittered off the seeding lattice, whose symmetry makes
    /// the nearest particle of a cell centre a tie (a kink of φ_L). With a band, when `deep`
    /// picks cells: their particles taken out.
    struct SqueezedPool {
        grid: Grid,
        particles: Vec<Vec3>,
        weights: FaceWeights,
        node_sdf: NodeSdf,
        centre_in_solid: Vec<bool>,
        deep: Vec<bool>,
        band: Option<Band>,
    }

    impl SqueezedPool {
        fn new(deep: Option<fn([usize; 3]) -> bool>) -> SqueezedPool {
            let grid = Grid { n: [8, 8, 6], dx: 0.1 };
            let node_sdf = NodeSdf::new(&grid, &[]);
            let pool = Solid::aabb(Vec3::ZERO, Vec3::new(0.8, 0.4, 0.6));
            let mut particles = surface::seed(&grid, &[pool], 8, &node_sdf, None);
            for (i, x) in particles.iter_mut().enumerate() {
                let r = |k: usize| ((i * 7919 + k * 104729) % 1009) as f64 / 1009.0 - 0.5;
                x.y *= 0.8;
                *x += 4e-3 * Vec3::new(r(1), r(2), r(3));
            }
            let cells = grid.cells();
            let deep: Vec<bool> =
                (0..cells.len()).map(|c| deep.is_some_and(|d| d(cells.ijk(c)))).collect();
            particles.retain(|x| !deep[surface::cell_of(&grid, *x)]);
            let radius = surface::particle_radius(grid.dx, 2);
            let band = deep.contains(&true).then(|| {
                Band::with_deep(&grid, deep.clone(), &surface::SurfaceModel::nearest(radius, 2))
            });
            SqueezedPool {
                grid,
                particles,
                weights: FaceWeights::new(&crate::geometry::fractions::face_weights(&grid, &[])),
                node_sdf,
                centre_in_solid: vec![false; grid.num_cells()],
                deep,
                band,
            }
        }

        /// What the projection reads: exact solves, and the band if there is one.
        fn inputs(&self) -> DensityInputs<'_> {
            DensityInputs {
                grid: &self.grid,
                weights: &self.weights,
                node_sdf: &self.node_sdf,
                centre_in_solid: &self.centre_in_solid,
                partial: &[],
                near_solid: &self.centre_in_solid,
                bodies: &[],
                displaced: &[],
                gravity: [0.0, -9.81, 0.0],
                surface: surface::SurfaceModel {
                    radius: surface::particle_radius(self.grid.dx, 2),
                    sparse_cells: true,
                    sparse_depth: 0.0,
                    softness: 0.0,
                    per_axis: 2,
                },
                interior_values: false,
                particles_per_cell: 8,
                gain: 1.75,
                passes: 1,
                face_ramp: 0.0,
                ghost: GhostFluid::clamped(0.01),
                blend: SurfaceBlend { theta: 0.0 },
                solve: LinearSolve::new(Preconditioner::Mic0, 1e-13, 10_000),
                band: self.band.as_ref(),
                systems: None,
            }
        }
    }

    /// The whole projection (its system built from the particles, the solve, the capped
    /// displacement, the wall push) against central differences in the particle positions,
    /// for the squeezed pool.
    #[test]
    fn adjoint_matches_central_differences() {
        let pool = SqueezedPool::new(None);
        let inputs = pool.inputs();
        let proj = DensityProjection::build(&pool.particles, &inputs).expect("over-full cells");
        assert!(!proj.deep_closed);
        assert_adjoint_is_central_difference(&pool.particles, &inputs);
    }

    /// In the half cell next to a wall a particle moves by what the face next to the wall
    /// asks, not by a share of it falling to zero at the wall: the squeezed pool's floor
    /// cells push their particles up by the same amount a quarter of a cell over the floor
    /// as one cell over it, and the same holds at the side walls.
    #[test]
    fn particles_next_to_a_wall_move_by_the_face_inside() {
        let pool = SqueezedPool::new(None);
        let inputs = pool.inputs();
        let proj = DensityProjection::build(&pool.particles, &inputs).expect("over-full cells");
        let (q, _) = proj.solve(&inputs, 1).unwrap();
        let d = proj.displacement(&q, &inputs).d;
        let (dx, size) = (pool.grid.dx, pool.grid.size());
        let mut lifted = 0;
        for (i, k) in [(0.5, 0.5), (3.3, 2.7), (7.5, 5.5)] {
            let at = |y: f64| d.velocity(&pool.grid, Vec3::new(i * dx, y, k * dx));
            let (near, inside) = (at(0.25 * dx), at(dx));
            assert!((near.y - inside.y).abs() <= 1e-12 * inside.y.abs(), "{near} {inside}");
            lifted += usize::from(inside.y > 1e-6 * dx);
        }
        assert!(lifted == 3, "the floor cells are over full and push up");
        for (axis, wall, inner) in [(0, 0.1, 1.0), (0, 7.9, 7.0), (2, 0.2, 1.0), (2, 5.8, 5.0)] {
            let mut p = Vec3::new(0.5 * size.x, 0.55 * dx, 0.5 * size.z);
            p[axis] = wall * dx;
            let near = d.velocity(&pool.grid, p)[axis];
            p[axis] = inner * dx;
            assert_eq!(near, d.velocity(&pool.grid, p)[axis], "axis {axis} at {wall} cells");
        }
    }

    /// A cell over full within a tenth of a cell of the surface pushes out only part of its
    /// excess, fading to none as its centre reaches the surface (a cell just turning liquid
    /// was a jump of the step), and the adjoint through that fade matches central
    /// differences: the squeezed pool with a clump of particles under its surface, raised
    /// until an over-full cell's centre lies just under it.
    #[test]
    fn excess_fades_at_the_surface() {
        let dx = 0.1;
        assert_eq!(excess(1.2, 1.0, depth_weight(0.0, dx)), 0.0);
        let whole = excess(1.2, 1.0, 1.0);
        assert!((excess(1.2, 1.0, depth_weight(-0.005, dx)) - 0.5 * whole).abs() < 1e-12);
        assert_eq!(excess(1.2, 1.0, depth_weight(-0.02, dx)), excess(1.2, 1.0, 1.0));
        let mut pool = SqueezedPool::new(None);
        let faded = |pool: &SqueezedPool| {
            let inputs = pool.inputs();
            let proj = DensityProjection::build(&pool.particles, &inputs).expect("over full");
            (0..proj.sys.len())
                .filter(|&r| {
                    let c = proj.sys.cell_of_row[r] as usize;
                    let w = depth_weight(proj.phi[c], dx);
                    w > 0.0 && w < 1.0 && excess_derivatives(proj.dens[c], 1.0, w).2 != 0.0
                })
                .count()
        };
        // A clump of particles in the top half cell under the surface at one column, raised
        // until the centre of the cell above it lies just under the surface, over full.
        let top = pool.particles.iter().map(|x| x.y).fold(f64::MIN, f64::max);
        let centre = Vec3::new(3.5 * dx, top, 2.5 * dx);
        let clump = (0..24).map(|i| {
            let r = |k: usize| ((i * 7919 + k * 104729) % 1009) as f64 / 1009.0 - 0.5;
            centre + dx * Vec3::new(0.5 * r(1), -0.1 - 0.2 * r(2).abs(), 0.5 * r(3))
        });
        pool.particles.extend(clump);
        let mut shift = 0.0;
        while faded(&pool) == 0 {
            assert!(shift < dx, "no over-full cell came within a tenth of a cell of the surface");
            pool.particles.iter_mut().for_each(|x| x.y += 2e-4);
            shift += 2e-4;
        }
        let inputs = pool.inputs();
        assert_adjoint_is_central_difference(&pool.particles, &inputs);
    }

    /// With the displacement's liquid–air faces blended into its layer
    /// (`solver.surface_blend`), with and without a band: faces known in part exist, the
    /// displacement is not the yes/no rule's, and the adjoint, through the shares to φ_L,
    /// still matches central differences.
    #[test]
    fn blended_adjoint_matches_central_differences() {
        type Deep = Option<fn([usize; 3]) -> bool>;
        let under: Deep = Some(|[i, j, k]| j == 0 && (1..7).contains(&i) && (1..5).contains(&k));
        for deep in [None, under] {
            let pool = SqueezedPool::new(deep);
            let inputs = DensityInputs { blend: SurfaceBlend { theta: 0.5 }, ..pool.inputs() };
            let proj = DensityProjection::build(&pool.particles, &inputs).expect("over full");
            let parts: usize = proj.surface.iter().map(Vec::len).sum();
            assert!(parts > 0, "no liquid–air face is known in part");
            let (q, _) = proj.solve(&inputs, 1).unwrap();
            let blended = proj.displacement(&q, &inputs).d;
            let plain = DensityProjection { surface: Default::default(), ..proj }
                .displacement(&q, &inputs)
                .d;
            let gap = (0..3)
                .flat_map(|a| blended.c[a].iter().zip(&plain.c[a]).map(|(x, y)| (x - y).abs()))
                .fold(0.0, f64::max);
            assert!(gap > 1e-6 * pool.grid.dx, "the blend changed nothing: {gap:e}");
            assert_adjoint_is_central_difference(&pool.particles, &inputs);
        }
    }

    /// With deep cells under the over-full ones, the operator has the band's cells only
    /// (every face of a deep cell closed), the displacement crosses no face of a deep cell,
    /// and the adjoint still matches central differences.
    #[test]
    fn band_projection_is_closed_at_the_deep_cells() {
        // The bottom layer's inner cells.
        let pool = SqueezedPool::new(Some(|[i, j, k]| {
            j == 0 && (1..7).contains(&i) && (1..5).contains(&k)
        }));
        let (grid, deep, inputs) = (&pool.grid, &pool.deep, pool.inputs());
        let proj = DensityProjection::build(&pool.particles, &inputs).expect("over-full cells");
        assert!(proj.deep_closed, "the band's excess reaches the air");
        assert!(proj.sys.cell_of_row.iter().all(|&c| !deep[c as usize]));
        let (q, _) = proj.solve(&inputs, 1).unwrap();
        let d = proj.displacement(&q, &inputs).d;
        // The six faces of each deep cell: the lower and upper face along each axis.
        for c in (0..deep.len()).filter(|&c| deep[c]) {
            let ijk = grid.cells().ijk(c);
            for a in 0..3 {
                let lat = grid.faces(a);
                let mut up = ijk;
                up[a] += 1;
                for f in [ijk, up] {
                    let f = lat.index(f[0], f[1], f[2]);
                    assert_eq!(d.c[a][f], 0.0, "axis {a} face {f} of deep cell {c}");
                }
            }
        }
        let moved: usize = d.c.iter().map(|c| c.iter().filter(|&&x| x != 0.0).count()).sum();
        assert!(moved > 100, "the band's excess moved ({moved} faces)");
        // A forward step's projection, its closed weights dropped, displaces the same.
        let forward = proj.without_adjoint_inputs();
        assert!(forward.closed.is_none());
        assert_eq!(forward.displacement(&q, &inputs).d, d);
        assert_adjoint_is_central_difference(&pool.particles, &inputs);
    }

    /// A displacement written over a kept field that holds anything (here the last one's
    /// values scaled, and NaN) is the one built on zeros: every face is written.
    #[test]
    fn displacement_over_a_kept_field_is_the_one_on_zeros() {
        let pool = SqueezedPool::new(Some(|[i, j, k]| {
            j == 0 && (1..7).contains(&i) && (1..5).contains(&k)
        }));
        let fresh = pool.inputs();
        let proj = DensityProjection::build(&pool.particles, &fresh).expect("over-full cells");
        let (q, _) = proj.solve(&fresh, 1).unwrap();
        let on_zeros = proj.displacement(&q, &fresh);
        let systems = SystemPool::default();
        let mut dirty = on_zeros.d.clone();
        for (a, c) in dirty.c.iter_mut().enumerate() {
            c.iter_mut()
                .enumerate()
                .for_each(|(f, x)| *x = if (f + a) % 3 == 0 { f64::NAN } else { 1e3 * *x - 1.0 });
        }
        systems.keep_field(dirty);
        let kept = DensityInputs { systems: Some(&systems), ..pool.inputs() };
        let over = proj.displacement(&q, &kept);
        assert!(on_zeros.d.c.iter().any(|c| c.iter().any(|&x| x != 0.0)));
        for a in 0..3 {
            let (x, y) = (&over.d.c[a], &on_zeros.d.c[a]);
            assert!(x.iter().zip(y).all(|(x, y)| x.to_bits() == y.to_bits()), "axis {a}");
        }
        assert_eq!(over.valid0, on_zeros.valid0);
    }

    /// The displacement by the sources' neighbours (`extrapolate_one_layer`) is the one by
    /// passes over the lattices (`correct_velocity`, then `closed_at_deep`), to the bit:
    /// without a band, closed at the deep cells, and sealed off by them (the whole liquid's
    /// operator with a band), each over a kept field that holds NaN and garbage.
    #[test]
    fn displacement_is_the_one_by_passes() {
        let bottom: fn([usize; 3]) -> bool =
            |[i, j, k]| j == 0 && (1..7).contains(&i) && (1..5).contains(&k);
        let layer: fn([usize; 3]) -> bool = |[_, j, _]| j == 1;
        for (deep, closed) in [(None, false), (Some(bottom), true), (Some(layer), false)] {
            let pool = SqueezedPool::new(deep);
            let fresh = pool.inputs();
            let proj = DensityProjection::build(&pool.particles, &fresh).expect("over full");
            assert_eq!(proj.deep_closed, closed);
            let (q, _) = proj.solve(&fresh, 1).unwrap();
            let by_passes = proj.displacement_by_passes(&q, &fresh);
            let systems = SystemPool::default();
            let mut dirty = by_passes.d.clone();
            for (a, c) in dirty.c.iter_mut().enumerate() {
                c.iter_mut().enumerate().for_each(|(f, x)| {
                    *x = if (f + a) % 3 == 0 { f64::NAN } else { 1e3 * *x - 1.0 }
                });
            }
            systems.keep_field(dirty);
            let kept = DensityInputs { systems: Some(&systems), ..pool.inputs() };
            let sparse = proj.displacement(&q, &kept);
            let layer: usize = (0..3)
                .map(|a| {
                    let (x, y) = (&sparse.d.c[a], &by_passes.d.c[a]);
                    assert!(x.iter().zip(y).all(|(x, y)| x.to_bits() == y.to_bits()), "axis {a}");
                    let v = &by_passes.valid0[a];
                    x.iter().zip(v).filter(|&(&x, &v)| v == 0 && x != 0.0).count()
                })
                .sum();
            assert!(layer > 10, "the layer is set ({layer} faces)");
            assert_eq!(sparse.valid0, by_passes.valid0);
        }
    }

    /// Deep cells that seal over-full band cells off from the air (a whole layer of them
    /// above): the closed operator would be singular there, so the projection is the whole
    /// liquid's, as without a band.
    #[test]
    fn band_projection_sealed_from_the_air_is_the_whole_liquids() {
        let pool = SqueezedPool::new(Some(|[_, j, _]| j == 1));
        let inputs = pool.inputs();
        let proj = DensityProjection::build(&pool.particles, &inputs).expect("over-full cells");
        assert!(!proj.deep_closed);
        assert!(proj.sys.cell_of_row.iter().any(|&c| pool.deep[c as usize]));
        let excess_below = proj
            .sys
            .cell_of_row
            .iter()
            .zip(&proj.b)
            .any(|(&c, &b)| pool.grid.cells().ijk(c as usize)[1] == 0 && b > 0.0);
        assert!(excess_below, "the sealed layer is over full");
        let (_, stats) = proj.solve(&inputs, 1).unwrap();
        assert!(stats.converged);
    }

    /// Three passes of `block_max` are the largest over each cell's 3×3×3 block within the
    /// tank, to the bit, on a grid with one cell along an axis too.
    #[test]
    fn block_max_is_the_largest_over_the_block() {
        for n in [[7, 5, 4], [6, 1, 5]] {
            let grid = Grid { n, dx: 0.1 };
            let d: Vec<f64> = (0..grid.num_cells())
                .map(|c| ((c * 7919) % 1013) as f64 / 1013.0 - if c % 5 == 0 { 0.0 } else { 0.5 })
                .collect();
            let mut high = d.clone();
            for axis in 0..3 {
                high = block_max(&grid, &high, axis);
            }
            let cells = grid.cells();
            for c in 0..grid.num_cells() {
                let [i, j, k] = cells.ijk(c);
                let mut best = f64::NEG_INFINITY;
                for o in 0..grid.num_cells() {
                    let [a, b, e] = cells.ijk(o);
                    if a.abs_diff(i) <= 1 && b.abs_diff(j) <= 1 && e.abs_diff(k) <= 1 {
                        best = best.max(d[o]);
                    }
                }
                assert_eq!(high[c].to_bits(), best.to_bits(), "cell {c} of {n:?}");
            }
        }
    }

    /// The interior weights' two ramps (see `interior_weights`): a pool squeezed in height
    /// until its top layer's cells are liquid by less than a tenth of a cell, and rippled
    /// along x, so that cells deep in the liquid are over and under full in turn, and a ball just
    /// above it whose clearance ramp reaches the pool's interior. The adjoint
    /// matches central differences in the particles and in the ball's position, which enters
    /// the projection only through the weights here (its faces are not in the inputs).
    #[test]
    fn interior_weights_adjoint_matches_central_differences() {
        use crate::math::{Pose, Rotation, SharedShape};
        let mut pool = SqueezedPool::new(None);
        let region = Solid::aabb(Vec3::ZERO, Vec3::new(0.8, 0.4, 0.6));
        pool.particles = surface::seed(&pool.grid, &[region], 8, &pool.node_sdf, None);
        for (i, x) in pool.particles.iter_mut().enumerate() {
            let r = |k: usize| ((i * 7919 + k * 104729) % 1009) as f64 / 1009.0 - 0.5;
            x.y *= 0.8;
            x.x += 0.04 * (std::f64::consts::TAU * x.x / 0.8).sin();
            *x += 4e-3 * Vec3::new(r(1), r(2), r(3));
        }
        let ball_at = |x: Vec3| {
            let pose = Pose::from_parts(x, Rotation::IDENTITY);
            [RigidBody::with_density("ball".into(), SharedShape::ball(0.1), pose, 500.0)]
        };
        let x0 = Vec3::new(0.13, 0.4, 0.3);
        let bodies = ball_at(x0);
        let inputs = DensityInputs { bodies: &bodies, ..pool.inputs() };
        let proj = DensityProjection::build(&pool.particles, &inputs).expect("over-full cells");
        let (mut by_depth, mut by_body) = (0, 0);
        for c in (0..proj.interior.len()).filter(|&c| proj.interior[c] > 0.0) {
            let w = proj.interior[c];
            if w < 1.0 && excess_derivatives(proj.dens[c], w, 1.0).1 != 0.0 {
                match weight_set_by(c, w, &proj.phi, &inputs) {
                    WeightSetBy::Depth(_) => by_depth += 1,
                    WeightSetBy::Body(..) => by_body += 1,
                }
            }
        }
        assert!(
            by_depth > 0 && by_body > 0,
            "deficits weighed: {by_depth} by depth, {by_body} by the ball"
        );
        assert_adjoint_is_central_difference(&pool.particles, &inputs);
        // The ball's position, along a direction.
        let c: Vec<Vec3> = (0..pool.particles.len())
            .map(|i| Vec3::new(((i * 7) % 5) as f64 - 2.0, ((i * 3) % 7) as f64 - 3.0, 1.0))
            .collect();
        let run = |x: Vec3| {
            let bodies = ball_at(x);
            let inputs = DensityInputs { bodies: &bodies, ..pool.inputs() };
            let mut p = pool.particles.clone();
            correct(&mut p, &inputs, 1).unwrap();
            // The displacement only: the positions' sum would drown it in round-off.
            let moved = p.iter().zip(&pool.particles).map(|(a, b)| *a - *b);
            moved.zip(&c).map(|(a, b)| a.dot(*b)).sum::<f64>()
        };
        let e = Vec3::new(0.3, -0.8, 0.5);
        let eps = 1e-6;
        let fd = (run(x0 + eps * e) - run(x0 - eps * e)) / (2.0 * eps);
        let (q, _) = proj.solve(&inputs, 1).unwrap();
        let (mut pbar, mut pose) = (c.clone(), [[0.0; 6]]);
        proj.adjoint(&pool.particles, &q, &mut pbar, &mut pose, &inputs);
        let ad = pose[0][0] * e.x + pose[0][1] * e.y + pose[0][2] * e.z;
        assert!(fd.abs() > 1e-3, "the ball's clearance moved nothing ({fd:e})");
        assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "adjoint {ad:e}, central difference {fd:e}");
    }

    /// The adjoint of the projection of `p0` against central differences of [`correct`].
    fn assert_adjoint_is_central_difference(p0: &[Vec3], inputs: &DensityInputs<'_>) {
        let proj = DensityProjection::build(p0, inputs).expect("over-full cells");
        let c: Vec<Vec3> = (0..p0.len())
            .map(|i| Vec3::new(((i * 7) % 5) as f64 - 2.0, ((i * 3) % 7) as f64 - 3.0, 1.0))
            .collect();
        let run = |p: &[Vec3]| {
            let mut q = p.to_vec();
            correct(&mut q, inputs, 1).unwrap();
            q.iter().zip(&c).map(|(a, b)| a.dot(*b)).sum::<f64>()
        };
        let (q, _) = proj.solve(inputs, 1).unwrap();
        let mut pbar = c.clone();
        proj.adjoint(p0, &q, &mut pbar, &mut vec![[0.0; 6]; inputs.bodies.len()], inputs);
        let d: Vec<Vec3> = (0..p0.len())
            .map(|i| {
                Vec3::new(((i * 11) % 9) as f64 / 4.0 - 1.0, ((i * 5) % 7) as f64 / 3.0 - 1.0, 0.3)
            })
            .collect();
        let eps = 1e-8;
        let shift = |s: f64| p0.iter().zip(&d).map(|(x, y)| *x + s * *y).collect::<Vec<_>>();
        let fd = (run(&shift(eps)) - run(&shift(-eps))) / (2.0 * eps);
        let ad: f64 = pbar.iter().zip(&d).map(|(a, b)| a.dot(*b)).sum();
        // The identity part alone would be Σ c·d; the projection's own share must show.
        let identity: f64 = c.iter().zip(&d).map(|(a, b)| a.dot(*b)).sum();
        assert!((fd - identity).abs() > 1e-3 * fd.abs(), "the projection moved nothing");
        assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "adjoint {ad:e}, central difference {fd:e}");
    }
}
