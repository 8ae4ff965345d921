//! The step's system, shared by both directions: where the solids are ([`Geometry`]), and
//! the system the stages read ([`StepSystem::assemble`]: the liquid signed distance extended
//! into the solids, the faces the step reads, the coupled pressure operator). The forward
//! step builds them once from the current state; the backward pass builds them again, with
//! the same functions, from the tape. Nothing else builds them, so a change to the step is a
//! change to both directions.

use crate::geometry::body::RigidBody;
use crate::geometry::fractions::{self, BodyFaces, NodeSdf};
use crate::geometry::grid::{Grid, Mac};
use crate::geometry::seal::Seal;
use crate::geometry::weights::FaceWeights;
use crate::math::par::for_each_keyed_mut;
use crate::math::{twist, Twist, Vec3};
use crate::stages::advect::{advect_into, needed_faces, FaceMask};
use crate::stages::forces::add_gravity;
use crate::stages::pressure::{
    BodyCoupling, Coupling, Entrained, PressureParams, PressureSystem, ProjectedFace, SystemMemory,
};
use crate::stages::solid_phi::{self, PartialSolid, SolidExtension};
use rayon::prelude::*;

/// Geometry that does not move: tank walls and obstacles.
#[derive(Clone, Debug)]
pub struct StaticGeometry {
    /// Signed distance of the obstacles at grid nodes.
    pub node_sdf: NodeSdf,
    /// Fluid weight of every face (0 on walls), in a byte a face.
    pub weights: FaceWeights,
    /// Cells whose centre lies inside an obstacle.
    pub centre_in_solid: Vec<bool>,
    /// Cells whose centre is within [`NEAR_SOLID`] cells of an obstacle.
    pub near_solid: Vec<bool>,
}

/// How near a solid (in cells) a cell centre counts as near it: √3, half the diagonal of
/// the box between the centres of the cell's neighbours, which the particle density
/// deposited on the cell reads (see `stages::density`).
pub const NEAR_SOLID: f64 = 1.732_050_807_568_877_2;

/// Where the solids are this step: combined face weights and the bodies' faces.
#[derive(Clone, Debug)]
pub struct Geometry {
    /// Fluid weight of every face: static weight minus the bodies' fractions, in [0, 1].
    pub weights: FaceWeights,
    /// Cells whose centre is inside a static solid or a body.
    pub centre_in_solid: Vec<bool>,
    /// Cells whose centre is less than [`solid_phi::RAMP`] cells outside a body (and in no
    /// solid), in cell order: the extension into the solids ramps in over them. Empty
    /// unless `solver.body_ramp`.
    pub partial: Vec<PartialSolid>,
    /// Faces covered by each body.
    pub body_faces: Vec<BodyFaces>,
    /// The faces each body seals (empty for a body at least 2 cells thick somewhere).
    pub seals: Vec<Seal>,
}

/// Each body's face fractions where it is now (volume-consistent, see
/// [`RigidBody::face_fractions`]).
pub fn body_faces(grid: &Grid, bodies: &[RigidBody]) -> Vec<BodyFaces> {
    // The bodies side by side, each with its own parallel loops: a body's boxes and faces
    // alone keep two threads busy only in part.
    bodies.par_iter().map(|b| b.face_fractions(grid)).collect()
}

impl Geometry {
    /// The static weights minus each body's fractions `faces` (one per body, in order);
    /// with `ramp`, the cells near the bodies that φ_L ramps into them over
    /// ([`Geometry::partial`], `solver.body_ramp`).
    pub fn new(
        grid: &Grid,
        statics: &StaticGeometry,
        bodies: &[RigidBody],
        faces: Vec<BodyFaces>,
        ramp: bool,
    ) -> Geometry {
        Geometry::new_in(None, grid, statics, bodies, faces, ramp)
    }

    /// [`Geometry::new`] into the arrays of a geometry no longer needed (the static weights
    /// copied over them instead of cloned).
    pub fn new_in(
        old: Option<Geometry>,
        grid: &Grid,
        statics: &StaticGeometry,
        bodies: &[RigidBody],
        faces: Vec<BodyFaces>,
        ramp: bool,
    ) -> Geometry {
        assert_eq!(bodies.len(), faces.len());
        let (mut weights, mut centre_in_solid, mut partial) = match old {
            Some(Geometry { mut weights, mut centre_in_solid, mut partial, .. })
                if centre_in_solid.len() == statics.centre_in_solid.len() =>
            {
                weights.copy_from(&statics.weights);
                centre_in_solid.copy_from_slice(&statics.centre_in_solid);
                partial.clear();
                (weights, centre_in_solid, partial)
            }
            _ => (statics.weights.clone(), statics.centre_in_solid.clone(), Vec::new()),
        };
        let cells = grid.cells();
        for (body, (b, faces)) in bodies.iter().zip(&faces).enumerate() {
            // β is already snapped to 0 or 1 where it is within round-off of them, so
            // w + β = 1 holds exactly on every face a body alone covers.
            weights.subtract(&faces.faces);
            let (lo, hi) = b.bounds();
            let reach = Vec3::splat(if ramp { solid_phi::RAMP * grid.dx } else { 0.0 });
            grid.for_cells_in_box(lo - reach, hi + reach, |c, [i, j, k]| {
                let d = b.sdf(cells.position(i, j, k));
                if d < 0.0 {
                    centre_in_solid[c] = true;
                } else if ramp && d < solid_phi::RAMP * grid.dx {
                    let s = solid_phi::solidity(d, grid.dx);
                    partial.push(PartialSolid { cell: c as u32, body: body as u32, s });
                }
            });
        }
        // Per cell the nearest body's, and none in a solid.
        partial.sort_unstable_by(|a, b| a.cell.cmp(&b.cell).then(b.s.total_cmp(&a.s)));
        partial.dedup_by_key(|p| p.cell);
        partial.retain(|p| p.s > 0.0 && !centre_in_solid[p.cell as usize]);
        // Thin bodies seal the faces they cut, once every body's fractions are off.
        let seals: Vec<Seal> =
            bodies.iter().zip(&faces).map(|(b, f)| Seal::new(grid, b, f, &weights)).collect();
        for seal in seals.iter().filter(|s| !s.is_empty()) {
            weights.subtract(&seal.closing());
        }
        Geometry { weights, centre_in_solid, partial, body_faces: faces, seals }
    }

    /// The faces of body `i`'s columns of J: its fractions, and on the faces it seals and
    /// crosses the whole of their open part ([`Seal::coupling`]).
    pub fn coupling_faces(&self, i: usize) -> BodyFaces {
        self.seals[i].coupling(&self.body_faces[i])
    }
}

/// What a step's projection is assembled from besides the geometry.
#[derive(Clone, Copy, Debug)]
pub struct StepParams {
    /// The pressure operator's Δt, density and θ clamp.
    pub pressure: PressureParams,
    /// Monolithic or weak coupling.
    pub coupling: Coupling,
    /// Gravity, m/s² (φ_L is carried into the solids across it).
    pub gravity: [f64; 3],
    /// Whether the step solves for its pressures: false for a step given them (a
    /// checkpointed gradient's re-run), whose system is then built without the operator.
    pub solves: bool,
}

/// One step's system, built once and shared by every stage that reads it.
#[derive(Clone, Debug)]
pub struct StepSystem {
    /// Where the solids are.
    pub geometry: Geometry,
    /// φ_L at cell centres, extended into the solids (the pressure stage's liquid).
    pub phi: Vec<f64>,
    /// How φ_L was carried into the solids (its transpose carries ∂L/∂φ back).
    pub extension: SolidExtension,
    /// The faces whose advected velocity the step reads.
    pub needed: FaceMask,
    /// The pressure operator; with monolithic coupling its `bodies` are the coupled bodies'
    /// terms.
    pub pressure: PressureSystem,
    /// Indices of the bodies in the solve (those that [`RigidBody::moves`]), in order.
    pub coupled: Vec<usize>,
    /// The liquid each coupled body carries (empty but for thin bodies), in the order of
    /// [`StepSystem::coupled`]: the solve's M_S is theirs together.
    pub entrained: Vec<Entrained>,
    /// With weak coupling, the coupled bodies' J and Δt·M⁻¹ (outside the operator).
    weak: Vec<BodyCoupling>,
    /// Kinematic bodies: index, J (its Δt·M⁻¹ unused) and the prescribed [v; ω], a moving
    /// boundary of the solve.
    pub kinematic: Vec<(usize, BodyCoupling, Twist)>,
    /// Per row, the volume flux out of its liquid cell the solve asks for, m³/s (empty but
    /// with volume control, see [`volume_source`]).
    pub volume_source: Vec<f64>,
}

/// How far over a full cell (in cells) volume control's ramp takes to reach its full slope
/// (see [`volume_source`]).
pub const VOLUME_RAMP: f64 = 0.1;

/// Volume control: the volume flux out of a liquid cell, m³/s, that spreads in a step of
/// `dt` the fraction `rate` of what its marker particles hold over a full cell (`density`,
/// in cells), for a cell of volume `cell`. Particles that bunch are how a marker-particle
/// liquid loses volume; this pushes them apart through the velocity. The excess is taken
/// through a ramp that is continuously differentiable (nothing at or below a full cell,
/// (d − 1)²/(2·[`VOLUME_RAMP`]) up to it, then d − 1 − [`VOLUME_RAMP`]/2): a cell of
/// particles at rest holds exactly one full cell, so a kink there would sit under every
/// cell of still liquid.
pub fn volume_source(rate: f64, density: f64, cell: f64, dt: f64) -> f64 {
    let x = density - 1.0;
    let ramp = if x <= 0.0 {
        0.0
    } else if x < VOLUME_RAMP {
        x * x / (2.0 * VOLUME_RAMP)
    } else {
        x - 0.5 * VOLUME_RAMP
    };
    rate * cell * ramp / dt
}

/// ∂[`volume_source`]/∂density.
pub fn volume_source_derivative(rate: f64, density: f64, cell: f64, dt: f64) -> f64 {
    let x = density - 1.0;
    let slope = if x <= 0.0 { 0.0 } else { (x / VOLUME_RAMP).min(1.0) };
    rate * cell * slope / dt
}

impl StepSystem {
    /// Assembles the step's system from the geometry and the particles' φ_L (before its
    /// extension into the solids). The pressure system is built into `memory` (see
    /// `world::step::Spare`).
    pub fn assemble(
        grid: &Grid,
        bodies: &[RigidBody],
        geometry: Geometry,
        mut phi: Vec<f64>,
        params: StepParams,
        memory: SystemMemory,
    ) -> StepSystem {
        let extension = SolidExtension::apply_new(
            grid,
            &geometry.centre_in_solid,
            &geometry.partial,
            params.gravity,
            &mut phi,
        );
        let build = if params.solves {
            PressureSystem::build_in
        } else {
            PressureSystem::build_without_operator_in
        };
        let coupled: Vec<usize> = (0..bodies.len()).filter(|&i| bodies[i].moves()).collect();
        let kinematic: Vec<usize> = (0..bodies.len())
            .filter(|&i| bodies[i].motion == crate::geometry::body::Motion::Kinematic)
            .collect();
        let jacobian = |&i: &usize| {
            let b = &bodies[i];
            fractions::body_jacobian(grid, &geometry.coupling_faces(i), b.x, b.spin())
        };
        // The faces the advection fills and the bodies' Jacobians (a body at a time) beside
        // the pressure system's build, which neither reads: none keeps two threads busy alone.
        let ((needed, (jacobians, kinematic_jacobians)), mut pressure) = rayon::join(
            || {
                rayon::join(
                    || needed_faces(grid, &phi, &geometry.body_faces),
                    || {
                        let coupled: Vec<_> = coupled.par_iter().map(jacobian).collect();
                        (coupled, kinematic.iter().map(jacobian).collect::<Vec<_>>())
                    },
                )
            },
            || build(memory, grid, &phi, &geometry.weights, params.pressure),
        );
        let dt = params.pressure.dt;
        let entrained: Vec<Entrained> = coupled
            .iter()
            .map(|&i| {
                let seal = &geometry.seals[i];
                if seal.is_empty() {
                    Entrained::default()
                } else {
                    Entrained::new(grid, &bodies[i], seal, &phi, &params.pressure)
                }
            })
            .collect();
        let couplings: Vec<BodyCoupling> = coupled
            .iter()
            .zip(&jacobians)
            .zip(&entrained)
            .map(|((&i, jac), ent)| {
                let mi = if ent.is_empty() { dt_minv(&bodies[i], dt) } else { ent.dt_minv(dt) };
                BodyCoupling::new(&pressure.row_of_cell, jac, mi)
            })
            .collect();
        let kinematic = kinematic
            .iter()
            .zip(&kinematic_jacobians)
            .map(|(&i, jac)| {
                (
                    i,
                    BodyCoupling::new(&pressure.row_of_cell, jac, [[0.0; 6]; 6]),
                    generalized_velocity(&bodies[i]),
                )
            })
            .collect();
        let weak = match params.coupling {
            Coupling::Monolithic => {
                pressure.bodies = couplings;
                Vec::new()
            }
            Coupling::Weak => couplings,
        };
        StepSystem {
            geometry,
            phi,
            extension,
            needed,
            pressure,
            coupled,
            entrained,
            weak,
            kinematic,
            volume_source: Vec::new(),
        }
    }

    /// The coupled bodies' velocities `v` before the solve with the liquid they carry
    /// (`u`, the fluid's): [`Entrained::velocity`] where a body carries some, `v` itself
    /// where it carries none.
    pub fn entrained_velocities(&self, v: &[Twist], u: &Mac) -> Vec<Twist> {
        v.iter()
            .zip(&self.entrained)
            .map(|(v, e)| if e.is_empty() { *v } else { e.velocity(v, u) })
            .collect()
    }

    /// The coupled bodies' J and Δt·M⁻¹, in the order of [`StepSystem::coupled`].
    pub fn couplings(&self) -> &[BodyCoupling] {
        if self.weak.is_empty() {
            &self.pressure.bodies
        } else {
            &self.weak
        }
    }

    /// The right-hand side for the fluid velocity `u` and the coupled bodies' velocities
    /// `v` (one per coupled body): minus the volume flux out of each liquid cell.
    pub fn rhs(&self, u: &Mac, v: &[Twist]) -> Vec<f64> {
        let mut b = if self.weak.is_empty() {
            self.pressure.rhs(u, &self.geometry.weights, v)
        } else {
            // Partitioned: the bodies are boundaries moving at their current velocity.
            let mut b = self.pressure.rhs(u, &self.geometry.weights, &[]);
            for (c, v) in self.weak.iter().zip(v) {
                c.add_jt(&v.map(|x| -x), &mut b);
            }
            b
        };
        // Kinematic bodies push their volume flux at their prescribed velocity.
        for (_, c, v) in &self.kinematic {
            c.add_jt(&v.map(|x| -x), &mut b);
        }
        // Volume control: the flux out of every liquid cell the solve leaves.
        for (x, q) in b.iter_mut().zip(&self.volume_source) {
            *x += q;
        }
        b
    }

    /// The volume flux out of each liquid cell after the projection: through the fluid
    /// faces of `u`, pushed by the coupled bodies at `v` and by the kinematic ones.
    pub fn flux(&self, u: &Mac, v: &[Twist]) -> Vec<f64> {
        let mut flux = self.pressure.fluid_flux(u, &self.geometry.weights);
        for (coupling, v) in self.couplings().iter().zip(v) {
            coupling.add_jt(v, &mut flux);
        }
        for (_, c, v) in &self.kinematic {
            c.add_jt(v, &mut flux);
        }
        flux
    }

    /// The faces the pressure update acts on, a byte a face (1: updated).
    pub fn projected_mask(&self) -> [Vec<u8>; 3] {
        let grid = &self.pressure.grid;
        let mut mask = [0, 1, 2].map(|a| vec![0u8; grid.faces(a).len()]);
        for a in 0..3 {
            let face = |pf: &ProjectedFace| pf.face as usize;
            for_each_keyed_mut(&mut mask[a], &self.pressure.faces[a], face, |_, _, v| *v = 1);
        }
        mask
    }
}

/// Stages 1 and 2 on the fluid: `u` advected through itself for `dt` on the faces of `mask`,
/// plus gravity, written over `out` (a field of the grid's size, whatever it holds). The
/// forward step asks for the faces the step reads; the backward pass asks for the faces it
/// reads the intermediate field on.
pub fn predicted_velocity(
    u: &Mac,
    grid: &Grid,
    dt: f64,
    gravity: [f64; 3],
    mask: &FaceMask,
    mut out: Mac,
) -> Mac {
    advect_into(u, grid, dt, Some(mask), &mut out);
    add_gravity(&mut out, gravity, dt);
    out
}

/// `[v; ω]`.
pub fn generalized_velocity(b: &RigidBody) -> Twist {
    twist(b.v, b.w)
}

/// Δt·M_S⁻¹ for a body: `diag(Δt/m·I, Δt·(R I Rᵀ)⁻¹)`.
pub fn dt_minv(b: &RigidBody, dt: f64) -> [[f64; 6]; 6] {
    let mut m = [[0.0; 6]; 6];
    for d in 0..3 {
        m[d][d] = dt / b.mass;
    }
    let inv = b.world_inertia().inverse();
    for r in 0..3 {
        for c in 0..3 {
            m[3 + r][3 + c] = dt * inv.col(c).to_array()[r];
        }
    }
    m
}
