//! The parts of a step that the forward pass and the backward pass share: where the solids
//! are ([`Geometry`]), and the step's system ([`StepSystem::assemble`]: the liquid signed
//! distance extended into the solids, the faces the step reads, the coupled pressure
//! operator). The forward step builds them once from the current state; the backward pass
//! builds them again, with the same functions, from the tape. Nothing else builds them, so a
//! change to the step is a change to both directions.

use crate::geometry::body::RigidBody;
use crate::geometry::fractions::{self, BodyFaces, NodeSdf};
use crate::geometry::grid::{Grid, Mac};
use crate::geometry::seal::Seal;
use crate::geometry::weights::FaceWeights;
use crate::math::par::{for_each_keyed_mut, sum_by};
use crate::stages::advect::{advect_into, needed_faces, FaceMask};
use crate::stages::forces::add_gravity;
use crate::stages::pressure::{
    BodyCoupling, Coupling, Entrained, PressureParams, PressureSystem, ProjectedFace, SystemMemory,
    SystemPool,
};
use crate::stages::solid_phi::SolidExtension;
use serde::Serialize;
use std::sync::Mutex;

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
    /// Cells whose centre is within [`NEAR_SOLID`] cells of a static solid or a body.
    pub near_solid: Vec<bool>,
    /// Faces covered by each body.
    pub body_faces: Vec<BodyFaces>,
    /// The faces each body seals (empty for a body at least 2 cells thick somewhere).
    pub seals: Vec<Seal>,
}

/// Each body's face fractions where it is now (volume-consistent, see
/// [`RigidBody::face_fractions`]).
pub fn body_faces(grid: &Grid, bodies: &[RigidBody]) -> Vec<BodyFaces> {
    bodies.iter().map(|b| b.face_fractions(grid)).collect()
}

impl Geometry {
    /// The static weights minus each body's fractions `faces` (one per body, in order).
    pub fn new(
        grid: &Grid,
        statics: &StaticGeometry,
        bodies: &[RigidBody],
        faces: Vec<BodyFaces>,
    ) -> Geometry {
        Geometry::new_in(None, grid, statics, bodies, faces)
    }

    /// [`Geometry::new`] into the arrays of a geometry no longer needed (the static weights
    /// copied over them instead of cloned).
    pub fn new_in(
        old: Option<Geometry>,
        grid: &Grid,
        statics: &StaticGeometry,
        bodies: &[RigidBody],
        faces: Vec<BodyFaces>,
    ) -> Geometry {
        assert_eq!(bodies.len(), faces.len());
        let (mut weights, mut centre_in_solid, mut near_solid) = match old {
            Some(Geometry { mut weights, mut centre_in_solid, mut near_solid, .. })
                if centre_in_solid.len() == statics.centre_in_solid.len()
                    && near_solid.len() == statics.near_solid.len() =>
            {
                weights.copy_from(&statics.weights);
                centre_in_solid.copy_from_slice(&statics.centre_in_solid);
                near_solid.copy_from_slice(&statics.near_solid);
                (weights, centre_in_solid, near_solid)
            }
            _ => (
                statics.weights.clone(),
                statics.centre_in_solid.clone(),
                statics.near_solid.clone(),
            ),
        };
        let cells = grid.cells();
        let reach = NEAR_SOLID * grid.dx;
        for (b, faces) in bodies.iter().zip(&faces) {
            // β is already snapped to 0 or 1 where it is within round-off of them, so
            // w + β = 1 holds exactly on every face a body alone covers.
            weights.subtract(&faces.faces);
            let (lo, hi) = b.bounds();
            let lo = lo.to_array().map(|x| (((x - reach) / grid.dx).floor().max(0.0)) as usize);
            let hi = hi.to_array().map(|x| ((x + reach) / grid.dx).ceil() as usize + 1);
            for k in lo[2]..grid.n[2].min(hi[2]) {
                for j in lo[1]..grid.n[1].min(hi[1]) {
                    for i in lo[0]..grid.n[0].min(hi[0]) {
                        let d = b.sdf(cells.position(i, j, k));
                        let c = grid.cell(i, j, k);
                        if d < 0.0 {
                            centre_in_solid[c] = true;
                        }
                        if d < reach {
                            near_solid[c] = true;
                        }
                    }
                }
            }
        }
        // Thin bodies seal the faces they cut, once every body's fractions are off.
        let seals: Vec<Seal> =
            bodies.iter().zip(&faces).map(|(b, f)| Seal::new(grid, b, f, &weights)).collect();
        for seal in seals.iter().filter(|s| !s.is_empty()) {
            weights.subtract(&seal.closing());
        }
        Geometry { weights, centre_in_solid, near_solid, body_faces: faces, seals }
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
    pub kinematic: Vec<(usize, BodyCoupling, [f64; 6])>,
}

impl StepSystem {
    /// Assembles the step's system from the geometry and the particles' φ_L (before its
    /// extension into the solids). The pressure system is built into `memory` (see
    /// [`Spare`]).
    pub fn assemble(
        grid: &Grid,
        bodies: &[RigidBody],
        geometry: Geometry,
        mut phi: Vec<f64>,
        params: StepParams,
        memory: SystemMemory,
    ) -> StepSystem {
        let extension = SolidExtension::new(grid, &geometry.centre_in_solid, params.gravity);
        extension.apply(&mut phi);
        let needed = needed_faces(grid, &phi, &geometry.body_faces);
        let build = if params.solves {
            PressureSystem::build_in
        } else {
            PressureSystem::build_without_operator_in
        };
        let mut pressure = build(memory, grid, &phi, &geometry.weights, params.pressure);
        let coupled: Vec<usize> = (0..bodies.len()).filter(|&i| bodies[i].moves()).collect();
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
            .zip(&entrained)
            .map(|(&i, ent)| {
                let b = &bodies[i];
                let faces = geometry.coupling_faces(i);
                let jac = fractions::body_jacobian(grid, &faces, b.x, b.spin());
                let mi = if ent.is_empty() { dt_minv(b, dt) } else { ent.dt_minv(dt) };
                BodyCoupling::new(&pressure.row_of_cell, &jac, mi)
            })
            .collect();
        let kinematic = (0..bodies.len())
            .filter(|&i| bodies[i].motion == crate::geometry::body::Motion::Kinematic)
            .map(|i| {
                let b = &bodies[i];
                let faces = geometry.coupling_faces(i);
                let jac = fractions::body_jacobian(grid, &faces, b.x, b.spin());
                (
                    i,
                    BodyCoupling::new(&pressure.row_of_cell, &jac, [[0.0; 6]; 6]),
                    generalized_velocity(b),
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
        }
    }

    /// The coupled bodies' velocities `v` before the solve with the liquid they carry
    /// (`u`, the fluid's): [`Entrained::velocity`] where a body carries some, `v` itself
    /// where it carries none.
    pub fn entrained_velocities(&self, v: &[[f64; 6]], u: &Mac) -> Vec<[f64; 6]> {
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
    pub fn rhs(&self, u: &Mac, v: &[[f64; 6]]) -> Vec<f64> {
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
        b
    }

    /// The volume flux out of each liquid cell after the projection: through the fluid
    /// faces of `u`, pushed by the coupled bodies at `v` and by the kinematic ones.
    pub fn flux(&self, u: &Mac, v: &[[f64; 6]]) -> Vec<f64> {
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

/// The whole-grid arrays a step builds (the combined face weights, the pressure and density
/// systems with their multigrid, the advected field), kept from one step, or one step's
/// adjoint, to be built into by the next instead of allocated and faulted in afresh: about
/// 200 bytes a liquid cell a step that the allocator would otherwise hand back to the system
/// and take again. Each slot holds one set (the systems two), so what it keeps is bounded by
/// one step's arrays; what is built while a slot is empty allocates. A simulation and its
/// clones (checkpoint snapshots, finite differences) share one; nothing here changes a
/// result.
#[derive(Default)]
pub struct Spare {
    systems: SystemPool,
    geometry: Mutex<Option<Geometry>>,
}

impl Spare {
    /// The pressure and density systems' memory.
    pub fn systems(&self) -> &SystemPool {
        &self.systems
    }

    /// A geometry to build into, if one is kept.
    pub fn geometry(&self) -> Option<Geometry> {
        self.geometry.lock().ok().and_then(|mut g| g.take())
    }

    /// A field of `grid`'s size to overwrite (a kept one, or zeros).
    pub fn velocity(&self, grid: &Grid) -> Mac {
        self.systems.field(grid)
    }

    /// Keeps a field no longer needed.
    pub fn keep_velocity(&self, u: Mac) {
        self.systems.keep_field(u);
    }

    /// Keeps a step's geometry and pressure system (the rest of it is dropped).
    pub fn keep_system(&self, geometry: Geometry, pressure: PressureSystem) {
        self.systems.give(pressure);
        if let Ok(mut slot) = self.geometry.lock() {
            *slot = Some(geometry);
        }
    }
}

impl std::fmt::Debug for Spare {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Spare")
    }
}

/// Wall time of each stage of one step, in seconds.
#[derive(Clone, Copy, Debug, Default, Serialize, PartialEq)]
pub struct StageSeconds {
    /// Stage 3a: the bodies' face fractions, J and the combined weights.
    pub geometry: f64,
    /// Stage 0, with a narrow band: its update (the deep cells, the particles they trade).
    pub band: f64,
    /// Stage 0: marker particles advected and pushed out of the solids.
    pub advect_particles: f64,
    /// Stage 0: the particle density projection (its system, solve and displacement).
    pub density: f64,
    /// Stage 3: the liquid signed distance from the particles.
    pub surface: f64,
    /// The step's system: φ_L extended into solids, the faces read, the pressure operator.
    pub assemble: f64,
    /// Stage 1: velocity advection.
    pub advect_velocity: f64,
    /// Stage 2: gravity and external forces.
    pub forces: f64,
    /// Stage 4: the pressure solves (with contact held inside) and the velocity update.
    pub pressure: f64,
    /// Stage 5: extrapolation and solid velocities.
    pub correct_velocity: f64,
    /// Stage 6: rigid integration or contact.
    pub rigid: f64,
}

impl StageSeconds {
    /// Each stage's name (as in `summary.json`) and seconds, in the order the step runs them.
    pub fn named(&self) -> [(&'static str, f64); 11] {
        [
            ("geometry", self.geometry),
            ("band", self.band),
            ("advect_particles", self.advect_particles),
            ("density", self.density),
            ("surface", self.surface),
            ("assemble", self.assemble),
            ("advect_velocity", self.advect_velocity),
            ("forces", self.forces),
            ("pressure", self.pressure),
            ("correct_velocity", self.correct_velocity),
            ("rigid", self.rigid),
        ]
    }
}

/// Pressure force and torque on one body in one step, as written to `summary.json`.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct BodyForce {
    /// Body name.
    pub name: String,
    /// Pressure force J·p (first three rows), N.
    pub force: [f64; 3],
    /// Pressure torque about the centre of mass, N·m.
    pub torque: [f64; 3],
    /// |Σβ·dx³ − V| / V of its face fractions (see [`BodyFaces::volume_error`]): zero
    /// unless the body is too small or thin for the grid.
    pub volume_error: f64,
}

/// What one step did, as written to `summary.json`.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct StepReport {
    /// Step number, from 1.
    pub step: usize,
    /// Simulated time at the end of the step, s.
    pub time: f64,
    /// Unknowns of the pressure solve (liquid cells).
    pub liquid_cells: usize,
    /// CG iterations.
    pub cg_iterations: usize,
    /// ‖b − A p‖₂ / ‖b‖₂ at the end of the solve.
    pub cg_relative_residual: f64,
    /// CG iterations of the particle density projection (0 when it is off or found no
    /// over-full cell).
    pub density_cg_iterations: usize,
    /// Largest |∇·u| over liquid cells after projection, 1/s.
    pub max_divergence: f64,
    /// Liquid volume from the marker particles, m³ (see [`crate::stages::surface::liquid_volume`]).
    pub liquid_volume: f64,
    /// Largest liquid speed at a liquid cell centre, m/s.
    pub max_speed: f64,
    /// Kinetic energy of the liquid, ½ Σ ρ·w_f·dx³·u_f² over faces next to liquid, J.
    pub kinetic_energy: f64,
    /// The mechanical energy of the liquid and the bodies at the end of the step.
    pub energy: Energy,
    /// Pressure force and torque on each body in the solve.
    pub bodies: Vec<BodyForce>,
    /// Extra pressure solves made to hold contact impulses (0 without contact).
    pub contact_iterations: usize,
    /// Largest velocity change contact still made after the last solve, m/s (0 when it
    /// converged or contact was off).
    pub contact_residual: f64,
    /// Wall time per stage.
    pub stage_seconds: StageSeconds,
    /// What this step found that a user should know and that is not an error (each kind
    /// once per run): a body whose face fractions cannot hold its volume.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

/// ½ Σ ρ·w_f·dx³·u_f² over the faces the projection updated. Sequential on purpose: the
/// sum is cheap and its order fixed.
pub fn kinetic_energy(u: &Mac, sys: &PressureSystem, weights: &FaceWeights, rho: f64) -> f64 {
    let e: f64 = (0..3)
        .map(|a| {
            let w = weights.axis(a);
            sum_by(&sys.faces[a], |pf| {
                let uf = u.c[a][pf.face as usize];
                w.weight(pf.face as usize) * uf * uf
            })
        })
        .sum();
    0.5 * rho * sys.grid.dx.powi(3) * e
}

/// The mechanical energy of the liquid and the bodies, J: what a closed system without
/// forcing may lose (semi-Lagrangian advection dissipates) but never gain. Potential energy
/// is −m·g·x, zero at the origin.
#[derive(Clone, Copy, Debug, Default, Serialize, PartialEq)]
pub struct Energy {
    /// Σ ½·m_p·|u(x_p)|² over the marker particles (see `liquid_potential`).
    pub liquid_kinetic: f64,
    /// Σ −m_p·g·x_p over the marker particles (m_p = ρ·dx³ per particles per cell), plus
    /// −ρ·dx³·g·x_c over a narrow band's deep cells (full of liquid without particles).
    pub liquid_potential: f64,
    /// Σ ½·m·|v|² + ½·ω·I·ω over the bodies.
    pub body_kinetic: f64,
    /// Σ −m·g·x over the bodies.
    pub body_potential: f64,
}

impl Energy {
    /// The sum of the four.
    pub fn total(&self) -> f64 {
        self.liquid_kinetic + self.liquid_potential + self.body_kinetic + self.body_potential
    }
}

/// `[v; ω]`.
pub fn generalized_velocity(b: &RigidBody) -> [f64; 6] {
    [b.v.x, b.v.y, b.v.z, b.w.x, b.w.y, b.w.z]
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
