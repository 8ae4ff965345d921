//! The stages of a step, in order: the one list the forward step runs down and the backward
//! pass runs up. A stage's name here is its name in the timings (`stage_seconds` of a
//! step's report, `adjoint_seconds` of a gradient), the docs and the error messages.

use serde::Serialize;

/// One stage of a step. [`Stage::ALL`] is their order in the forward step; the backward pass
/// runs their adjoints in the reverse order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Stage {
    /// Where the solids are at the start of the step: the bodies' face fractions, J's faces,
    /// the combined weights ([`crate::stages::system::Geometry`]). Its adjoint turns the
    /// step's pose derivatives into the gradient of the bodies' start poses.
    Geometry,
    /// The narrow band's update (the deep cells, the particles they trade).
    Band,
    /// The marker particles through the start velocity, pushed out of the bodies.
    AdvectParticles,
    /// The particle density projection (its system, solve and displacement) and the second
    /// push-out.
    Density,
    /// The liquid signed distance φ_L from the particles.
    Surface,
    /// The step's system: φ_L extended into the solids, the faces read, the pressure
    /// operator ([`crate::stages::system::StepSystem::assemble`]).
    Assemble,
    /// Semi-Lagrangian velocity advection and gravity on the faces the step reads.
    AdvectVelocity,
    /// The bodies' velocities with gravity and their loads.
    Forces,
    /// The coupled pressure solve (contact held inside it) and the velocity update.
    Pressure,
    /// Extrapolation into air, the bodies' velocity on the faces they cover, zero in walls.
    CorrectVelocity,
    /// Rigid integration (or rapier's contact step).
    Rigid,
}

impl Stage {
    /// Every stage, in the forward step's order.
    pub const ALL: [Stage; 11] = [
        Stage::Geometry,
        Stage::Band,
        Stage::AdvectParticles,
        Stage::Density,
        Stage::Surface,
        Stage::Assemble,
        Stage::AdvectVelocity,
        Stage::Forces,
        Stage::Pressure,
        Stage::CorrectVelocity,
        Stage::Rigid,
    ];

    /// The stage's name (its key in the timings).
    pub fn name(self) -> &'static str {
        match self {
            Stage::Geometry => "geometry",
            Stage::Band => "band",
            Stage::AdvectParticles => "advect_particles",
            Stage::Density => "density",
            Stage::Surface => "surface",
            Stage::Assemble => "assemble",
            Stage::AdvectVelocity => "advect_velocity",
            Stage::Forces => "forces",
            Stage::Pressure => "pressure",
            Stage::CorrectVelocity => "correct_velocity",
            Stage::Rigid => "rigid",
        }
    }
}

impl std::fmt::Display for Stage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Wall time of each stage, in seconds: of one step (a report's `stage_seconds`), or of
/// the adjoints over a backward pass (a gradient's `adjoint_seconds`, summed over steps).
/// A field per [`Stage`], named as [`Stage::name`].
#[derive(Clone, Copy, Debug, Default, Serialize, PartialEq)]
pub struct StageSeconds {
    /// [`Stage::Geometry`].
    pub geometry: f64,
    /// [`Stage::Band`].
    pub band: f64,
    /// [`Stage::AdvectParticles`].
    pub advect_particles: f64,
    /// [`Stage::Density`].
    pub density: f64,
    /// [`Stage::Surface`].
    pub surface: f64,
    /// [`Stage::Assemble`].
    pub assemble: f64,
    /// [`Stage::AdvectVelocity`].
    pub advect_velocity: f64,
    /// [`Stage::Forces`].
    pub forces: f64,
    /// [`Stage::Pressure`].
    pub pressure: f64,
    /// [`Stage::CorrectVelocity`].
    pub correct_velocity: f64,
    /// [`Stage::Rigid`].
    pub rigid: f64,
}

impl StageSeconds {
    /// The time of `stage`.
    pub fn get(&self, stage: Stage) -> f64 {
        let mut copy = *self;
        *copy.get_mut(stage)
    }

    /// Each stage's name and seconds, in the order of [`Stage::ALL`].
    pub fn named(&self) -> [(&'static str, f64); 11] {
        Stage::ALL.map(|s| (s.name(), self.get(s)))
    }

    /// The sum over the stages.
    pub fn total(&self) -> f64 {
        Stage::ALL.iter().map(|&s| self.get(s)).sum()
    }

    /// The time of `stage`, to add to.
    pub fn get_mut(&mut self, stage: Stage) -> &mut f64 {
        match stage {
            Stage::Geometry => &mut self.geometry,
            Stage::Band => &mut self.band,
            Stage::AdvectParticles => &mut self.advect_particles,
            Stage::Density => &mut self.density,
            Stage::Surface => &mut self.surface,
            Stage::Assemble => &mut self.assemble,
            Stage::AdvectVelocity => &mut self.advect_velocity,
            Stage::Forces => &mut self.forces,
            Stage::Pressure => &mut self.pressure,
            Stage::CorrectVelocity => &mut self.correct_velocity,
            Stage::Rigid => &mut self.rigid,
        }
    }
}

impl std::ops::AddAssign for StageSeconds {
    fn add_assign(&mut self, o: StageSeconds) {
        for s in Stage::ALL {
            *self.get_mut(s) += o.get(s);
        }
    }
}

/// Times the stages of one pass into a [`StageSeconds`] (adding to what it holds).
#[derive(Debug)]
pub struct StageClock {
    last: std::time::Instant,
}

impl Default for StageClock {
    fn default() -> StageClock {
        StageClock::new()
    }
}

impl StageClock {
    /// A clock started now.
    pub fn new() -> StageClock {
        StageClock { last: std::time::Instant::now() }
    }

    /// Ends `stage`: the time since the last lap is added to its slot of `times`.
    pub fn lap(&mut self, stage: Stage, times: &mut StageSeconds) {
        let now = std::time::Instant::now();
        *times.get_mut(stage) += (now - self.last).as_secs_f64();
        self.last = now;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every stage once in [`Stage::ALL`], its name the field of [`StageSeconds`] that
    /// serialises it.
    #[test]
    fn names_are_the_timing_keys() {
        let mut times = StageSeconds::default();
        for (k, s) in Stage::ALL.iter().enumerate() {
            *times.get_mut(*s) = k as f64 + 1.0;
        }
        let json = serde_json::to_value(times).unwrap();
        let map = json.as_object().unwrap();
        assert_eq!(map.len(), Stage::ALL.len());
        for (k, s) in Stage::ALL.iter().enumerate() {
            assert_eq!(map[s.name()], k as f64 + 1.0, "{s}");
        }
        assert_eq!(times.total(), (1..=11).sum::<usize>() as f64);
    }
}
