//! What a step keeps between steps ([`Spare`]) and what it reports ([`StepReport`]). The
//! step's system, which both directions build, is [`crate::stages::system`]; the stages and
//! their order are [`crate::stages::Stage`].

use crate::geometry::grid::{Grid, Mac};
use crate::geometry::weights::FaceWeights;
use crate::math::par::sum_by;
use crate::stages::pressure::{PressureSystem, SystemPool};
pub use crate::stages::system::{
    body_faces, dt_minv, generalized_velocity, predicted_velocity, Geometry, StaticGeometry,
    StepParams, StepSystem, NEAR_SOLID,
};
pub use crate::stages::StageSeconds;
use serde::Serialize;
use std::sync::Mutex;

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

/// Pressure force and torque on one body in one step, as written to `summary.json`.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct BodyForce {
    /// Body name.
    pub name: String,
    /// Pressure force J·p (first three rows), N.
    pub force: [f64; 3],
    /// Pressure torque about the centre of mass, N·m.
    pub torque: [f64; 3],
    /// |Σβ·dx³ − V| / V of its face fractions (see
    /// [`crate::geometry::fractions::BodyFaces::volume_error`]): zero unless the body is too
    /// small or thin for the grid.
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
