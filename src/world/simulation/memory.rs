//! How much memory a simulation will take, and how much the machine has: a scene over its
//! limit is refused before it runs.

use super::SimulationBuilder;
use crate::geometry::grid::Grid;
use crate::math::Vec3;
use crate::world::settings::NarrowBand;

impl SimulationBuilder {
    /// Bytes a forward run of this world takes at its peak, roughly, and the marker
    /// particles it seeds: 250 bytes per grid cell (the velocity and its advected copy, the
    /// face weights, φ_L, the pressure and density systems and their multigrids; `large_tank`
    /// measured 222 bytes a cell at 1 M cells and 230 at 8.4 M, its particles aside) and 56
    /// per particle (positions, their copies and bins). Particles are counted over the
    /// liquid regions' bounds; with `solver.narrow_band` only over the band (`auto` counted
    /// as its band where that is under half the regions' volume): each region's
    /// bounds less the bounds shrunk by the band and two cells on every side off the tank's
    /// walls, and each body's bounds grown by as much where they reach into those shrunk
    /// bounds. That counts at least the particles
    /// seeded (the regions' overlaps and the bodies' corners count twice), so a scene the
    /// machine can hold is not refused for particles the band never seeds.
    pub fn memory_estimate(&self, grid: &Grid) -> (f64, f64) {
        let cell = grid.dx.powi(3);
        let size = grid.size();
        let clip = |(lo, hi): (Vec3, Vec3)| (lo.max(Vec3::ZERO), hi.min(size));
        let volume =
            |(lo, hi): (Vec3, Vec3)| (hi - lo).max(Vec3::ZERO).to_array().iter().product::<f64>();
        let width = self.settings.solver.narrow_band.width();
        let margin = (width + 2) as f64 * grid.dx;
        let tol = 1e-9 * grid.dx;
        // Each region's bounds and those shrunk by the band (along its faces that are not
        // against a wall); without a band, nothing is shrunk.
        let regions: Vec<_> = self
            .liquid
            .iter()
            .map(|l| {
                let (lo, hi) = clip(l.bounds());
                if width == 0 {
                    return ((lo, hi), (lo, lo));
                }
                let inner_lo = Vec3::select(lo.cmpgt(Vec3::splat(tol)), lo + margin, lo);
                let inner_hi = Vec3::select(hi.cmplt(size - tol), hi - margin, hi);
                ((lo, hi), (inner_lo, inner_hi))
            })
            .collect();
        let liquid: f64 = regions.iter().map(|&(all, inner)| volume(all) - volume(inner)).sum();
        // The band around a body, where it reaches into a region's inside.
        let near_bodies: f64 = if width == 0 {
            0.0
        } else {
            self.bodies
                .iter()
                .map(|b| {
                    let (lo, hi) = b.bounds();
                    let (lo, hi) = (lo - margin, hi + margin);
                    regions.iter().map(|&(_, (a, c))| volume((lo.max(a), hi.min(c)))).sum::<f64>()
                })
                .sum()
        };
        // `auto` takes no band where less than its share of the liquid is deep: then the
        // particles fill the regions.
        let full: f64 = regions.iter().map(|&(all, _)| volume(all)).sum();
        let auto = self.settings.solver.narrow_band == NarrowBand::Auto;
        let (liquid, near_bodies) =
            if auto && liquid + near_bodies > (1.0 - NarrowBand::AUTO_DEEP_SHARE) * full {
                (full, 0.0)
            } else {
                (liquid, near_bodies)
            };
        let everywhere = size.to_array().iter().product::<f64>();
        let ppc = self.settings.solver.particles_per_cell as f64;
        // Up to a whole particle: a region's cells in f64 come out a hair under a whole count.
        let particles = ((liquid + near_bodies).min(everywhere) / cell * ppc).ceil();
        (250.0 * grid.num_cells() as f64 + 56.0 * particles, particles)
    }
}

/// Bytes of memory this process may still take: the smaller of the machine's available
/// memory and the cgroup's limit, when they can be read (Linux); None elsewhere.
pub(super) fn available_memory() -> Option<f64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok()?;
    let avail = meminfo
        .lines()
        .find_map(|l| l.strip_prefix("MemAvailable:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map(|kb| kb * 1024.0)?;
    let cgroup = std::fs::read_to_string("/sys/fs/cgroup/memory.max")
        .ok()
        .and_then(|s| s.trim().parse::<f64>().ok());
    Some(cgroup.map_or(avail, |c| c.min(avail)))
}
