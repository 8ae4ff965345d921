//! From a scene to a [`Simulation`]: its settings, its shapes built and meshes loaded, its
//! bodies in their initial state; a part that cannot be built is a `Problem` naming its key.

use super::spec::{BodySpec, Scene};
use crate::error::{Error, Result};
use crate::experiments::shapes::ShapeSpec;
use crate::geometry::body::{Motion, RigidBody};
use crate::math::v3;
use crate::world::settings::{check_finite, check_positive, SettingError};
use crate::world::{Simulation, SimulationBuilder, WorldSettings};
use std::path::PathBuf;

/// The name body `i` goes by.
fn key_name(i: usize, b: &BodySpec) -> String {
    b.name_or_default(i)
}

/// A validation failure: the key it concerns and what is wrong.
pub(super) type Problem = SettingError;

pub(super) fn problem(key: impl Into<String>, message: impl Into<String>) -> Problem {
    SettingError::new(key, message)
}

impl Scene {
    /// Folder relative mesh paths start from.
    pub fn base(&self) -> PathBuf {
        self.base_dir.clone().unwrap_or_else(|| PathBuf::from("."))
    }

    /// The scene with its liquid surface held fixed (`solver.freeze_surface`): the map the
    /// frozen-surface gradient is exact for.
    pub fn with_frozen_surface(mut self) -> Scene {
        self.solver.freeze_surface = true;
        self
    }

    /// The world settings the scene asks for.
    pub fn settings(&self) -> WorldSettings {
        WorldSettings {
            dt: self.time.dt,
            fluid: self.fluid,
            solver: self.solver.clone(),
            contact: self.contact.clone(),
        }
    }

    /// The simulation the scene describes, in its initial state.
    pub fn build(&self) -> Result<Simulation> {
        let invalid = |p: Problem| Error::InvalidScene {
            origin: self.name.clone(),
            message: format!("{}: {}", p.key, p.message),
        };
        self.builder().map_err(invalid)?.build().map_err(|e| match e {
            Error::InvalidSettings { key, message } => invalid(problem(key, message)),
            e => e,
        })
    }

    /// The world builder with every part of the scene in it (shapes built, meshes loaded).
    pub(super) fn builder(&self) -> std::result::Result<SimulationBuilder, Problem> {
        let base = self.base();
        let mut b = Simulation::builder(self.domain.size, self.domain.dx).settings(self.settings());
        let mut notes = Vec::new();
        for (i, l) in self.liquid.iter().enumerate() {
            let s = l.build_noting(&base, &mut notes);
            b = b.liquid(s.map_err(|m| problem(format!("liquid[{i}]"), m))?);
        }
        for (i, o) in self.obstacle.iter().enumerate() {
            let s = o.build_noting(&base, &mut notes);
            b = b.obstacle(s.map_err(|m| problem(format!("obstacle[{i}]"), m))?);
        }
        for (i, spec) in self.body.iter().enumerate() {
            b = b.body(self.build_body(i, spec, &mut notes)?);
        }
        for n in notes {
            b = b.warning(n);
        }
        Ok(b)
    }

    /// The i-th body in its initial state.
    fn build_body(
        &self,
        i: usize,
        b: &BodySpec,
        notes: &mut Vec<String>,
    ) -> std::result::Result<RigidBody, Problem> {
        let key = format!("body[{i}]");
        let solid = match (b.shell_thickness, &b.shape) {
            (None, _) => b.placed().build_noting(&self.base(), notes),
            (Some(t), ShapeSpec::Mesh { .. }) => {
                check_positive(&format!("{key}.shell_thickness"), t)?;
                b.placed().build_shell(&self.base(), t)
            }
            (Some(_), _) => {
                let message = "applies to a mesh body (shape kind = \"mesh\") only";
                return Err(problem(format!("{key}.shell_thickness"), message));
            }
        };
        let solid = solid.map_err(|m| problem(&key, m))?;
        let (density, mass) = match (b.density, b.mass) {
            (Some(d), None) => {
                check_positive(&format!("{key}.density"), d)?;
                (d, None)
            }
            (None, Some(m)) => {
                check_positive(&format!("{key}.mass"), m)?;
                (1.0, Some(m))
            }
            _ => return Err(problem(&key, "give exactly one of density and mass")),
        };
        check_finite(&format!("{key}.velocity"), &b.velocity)?;
        check_finite(&format!("{key}.angular_velocity"), &b.angular_velocity)?;
        let mut body =
            RigidBody::with_density(b.name_or_default(i), solid.shape, solid.pose, density);
        if !(body.mass.is_finite() && body.mass > 0.0) {
            return Err(problem(&key, "the shape has no volume (degenerate shape)"));
        }
        if let Some(m) = mass {
            body.set_mass(m);
        }
        body.v = v3(b.velocity);
        body.w = v3(b.angular_velocity);
        // A body that is not dynamic but has a velocity moves along it: a prescribed motion
        // (a paddle, a wave maker) the pressure solve sees.
        // A steered body that is not dynamic starts from rest when it has no velocity.
        let steered = self.control.as_ref().is_some_and(|c| c.bodies.contains(&key_name(i, b)));
        let still = b.velocity == [0.0; 3] && b.angular_velocity == [0.0; 3] && !steered;
        body.motion = match (b.dynamic, still) {
            (true, _) => Motion::Dynamic,
            (false, true) => Motion::Fixed,
            (false, false) => Motion::Kinematic,
        };
        Ok(body)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The memory check's particle count is at least what the built-in scenes seed (so its
    /// bytes are not an underestimate), and not more than twice it: with a band, the count
    /// is the band's, not the liquid's (`large_tank` seeds 0.63 M particles; its liquid
    /// holds 3.7 M).
    #[test]
    fn memory_estimate_counts_the_particles_seeded() {
        for name in ["large_tank", "dam_break", "block_drop", "floating_box"] {
            let scene = Scene::builtin(name).unwrap();
            let builder = scene.builder().unwrap();
            let grid = builder.check().unwrap();
            let (bytes, particles) = builder.memory_estimate(&grid);
            let seeded = scene.build().unwrap().particles.len() as f64;
            // `auto` may estimate the full volume for a band it then takes (the estimate sees
            // the regions' bounds, the choice their cells): never more than that.
            let mut full = scene.clone();
            full.solver.narrow_band = 0.into();
            let full = full.builder().unwrap().memory_estimate(&grid).1;
            let auto = scene.solver.narrow_band == crate::world::NarrowBand::Auto;
            assert!(
                particles >= seeded
                    && (particles <= 2.0 * seeded || (auto && particles <= full)),
                "{name}: {particles} particles estimated, {seeded} seeded, {full} for the full volume"
            );
            assert!(bytes >= 250.0 * grid.num_cells() as f64 + 56.0 * seeded, "{name}");
        }
    }
}
