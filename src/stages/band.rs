//! Narrow-band marker particles (after Ferstl, Ando, Wojtan, Westermann & Thuerey 2016,
//! "Narrow Band FLIP for Liquid Simulations"), part of the `band` and `density` stages, with its adjoint.
//!
//! The free surface reads the particles within two cells of it (φ_L, see `surface.rs`), yet
//! a full-volume liquid carries eight per cell all the way down. With a band, particles live
//! only in cells within `width` cells (L∞) of anything that is not liquid: air, a static
//! solid, a body. The cells beyond, *deep* cells, are liquid by construction: their φ_L is
//! the value of a freshly seeded cell and their density that of its seeded sub-lattice
//! ([`Band::density`], a separable stencil), so the density projection and the liquid
//! volume see them as the full cells they are.
//!
//! Each step, before the particles move, [`update`] recomputes the deep cells from the last
//! step's φ_L and the bodies where they are, with the band widened by the cells the step's
//! fastest velocity crosses, so no surface reaches a deep cell within the step. A deep cell
//! that the surface or a solid comes near gets its seeded sub-lattice back. The liquid also
//! flows through the deep cells, and they trade particles with the band by the grid's flux:
//! each deep cell keeps the volume it owes the band (the net flux out through its faces to
//! band cells, less the particles it sent, plus the particles it took), and sends a particle
//! for each 1/m³ of a cell owed, on the band side of the face the most flows out of, or
//! takes the band particle nearest its inflow faces for each one it is owed. A particle
//! found in a deep cell is taken out and owed back; a cell that turns deep owes the band
//! its particles and is owed a full cell. The grid's velocity is divergence-free, so what
//! the deep cells send is what they take, and the particles' volume is kept to rounding
//! (measured: the dam break at 1/40 m cells keeps its particle count within 0.04% over 50
//! steps).
//!
//! A cell turns deep only two cells beyond the band (and back at the band's edge), so no
//! cell flickers between the two. The adjoints of both ([`BandChange::adjoint`]) carry the
//! kept particles' gradients back to their old indices; seeded particles start at fixed
//! sites, so their gradients end there.

use crate::geometry::grid::{Grid, Mac};
use crate::math::buffer::refill;
use crate::math::par::{copied, min_pieces};
use crate::math::Vec3;
use crate::stages::surface;
use rayon::prelude::*;

/// The cells the grid carries as full liquid, for a band of particles around them.
#[derive(Clone, Debug, PartialEq)]
pub struct Band {
    /// Per cell: deep (full liquid, no particles).
    pub deep: Vec<bool>,
    /// What the deep cells deposit on the cell centres, in full cells: the density their
    /// seeded sub-lattices would give (see `surface::particle_density`).
    pub density: Vec<f64>,
    /// φ_L of a deep cell: a freshly seeded cell's, `r` less than the distance from its
    /// centre to its nearest sub-lattice site.
    pub phi: f64,
    /// Per deep cell, the volume (m³) it owes the band: the net flux out of it so far, less
    /// the particles it sent, plus the particles it took in (within half a particle's volume
    /// of zero after an update, unless the band had no particle left to take, so a cell
    /// that leaves the deep set returns it rounded to whole particles without a bias).
    pub owed: Vec<f64>,
    /// Per deep cell, the particles it has sent (which site of a face the next one takes).
    pub sent: Vec<u32>,
}

impl Band {
    /// No deep cells on `grid`, for particles made into φ_L by `model`.
    pub fn empty(grid: &Grid, model: &surface::SurfaceModel) -> Band {
        Band {
            deep: vec![false; grid.num_cells()],
            density: vec![0.0; grid.num_cells()],
            phi: model.full_phi(grid.dx),
            owed: vec![0.0; grid.num_cells()],
            sent: vec![0; grid.num_cells()],
        }
    }

    /// The band whose deep cells are `deep`.
    pub fn with_deep(grid: &Grid, deep: Vec<bool>, model: &surface::SurfaceModel) -> Band {
        let mut band = Band::empty(grid, model);
        band.density = full_density(grid, &deep, model.per_axis);
        band.deep = deep;
        band
    }

    /// The deep cells as φ_L reads them.
    pub fn deep(&self) -> surface::Deep<'_> {
        surface::Deep { cells: &self.deep, phi: self.phi }
    }

    /// A copy of the band for [`update`] to change while this one is kept (a step that may
    /// be rolled back): the per-cell arrays the update reads, each copied in parallel, and
    /// not [`Band::density`], which the update makes anew.
    pub(crate) fn for_update(&self) -> Band {
        let (deep, owed, sent) = (copied(&self.deep), copied(&self.owed), copied(&self.sent));
        Band { deep, density: Vec::new(), phi: self.phi, owed, sent }
    }

    /// Deep cells.
    pub fn deep_cells(&self) -> usize {
        self.deep.iter().filter(|&&d| d).count()
    }
}

/// What one [`update`] did to the particle list: the kept particles, in their order, then
/// `added` new ones.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BandChange {
    /// Particles before the update.
    pub before: usize,
    /// The old index of each kept particle.
    pub kept: Vec<u32>,
    /// Particles seeded at the end of the list.
    pub added: usize,
}

impl BandChange {
    /// ∂L/∂(particles before the update) from ∂L/∂(particles after it): each kept
    /// particle's gradient at its old index, zero for the ones taken out; the added ones sit
    /// at fixed sites and carry nothing back.
    pub fn adjoint(&self, after: &[Vec3]) -> Vec<Vec3> {
        let mut out = vec![Vec3::ZERO; self.before];
        for (&k, g) in self.kept.iter().zip(after) {
            out[k as usize] = *g;
        }
        out
    }
}

/// The 1D deposit of a seeded cell's `m` sub-lattice rows on [the cell below, itself, the
/// cell above], in full cells: each site's linear weights on the two nearest centres.
fn stencil(m: usize) -> [f64; 3] {
    let mut s = [0.0; 3];
    for t in surface::sub_offsets(m) {
        if t < 0.5 {
            s[0] += 0.5 - t;
            s[1] += t + 0.5;
        } else {
            s[1] += 1.5 - t;
            s[2] += t - 0.5;
        }
    }
    s.map(|w| w / m as f64)
}

/// What `deep` cells deposit on the cell centres (see [`Band::density`]), with a weight that
/// would land past a tank wall folded back onto its mirror cell, as for the particles.
pub fn full_density(grid: &Grid, deep: &[bool], m: usize) -> Vec<f64> {
    let mut out = Vec::new();
    full_density_into(grid, deep, m, &mut out);
    out
}

/// [`full_density`] into `out`, its memory kept (see [`crate::math::buffer::clear_for`]):
/// the deposit is separable, one pass an axis, and the passes take turns between `out` and
/// one scratch array.
fn full_density_into(grid: &Grid, deep: &[bool], m: usize, out: &mut Vec<f64>) {
    let w = stencil(m);
    let len = grid.num_cells();
    let mut scratch = vec![0.0; len];
    refill(out, len, 0.0);
    deposit_along(grid, &w, 0, deep, |&d| if d { 1.0 } else { 0.0 }, out);
    deposit_along(grid, &w, 1, out, |&x| x, &mut scratch);
    deposit_along(grid, &w, 2, &scratch, |&x| x, out);
}

/// One axis of [`full_density`]: each cell's share of `value(src)` along `axis`, own and the
/// two neighbours', into `out`, a row of cells at a time (loops the compiler vectorises).
fn deposit_along<T: Sync>(
    grid: &Grid,
    w: &[f64; 3],
    axis: usize,
    src: &[T],
    value: impl Fn(&T) -> f64 + Sync,
    out: &mut [f64],
) {
    let n = grid.n;
    let slab = n[0] * n[1];
    // `o[i]` from the row's own cells and, along `axis`, the rows of the cells below and
    // above (their upper and lower weights): at a wall the cell's own outer share folds
    // back onto it.
    let fold = |o: &mut [f64], own: &[T], below: Option<&[T]>, above: Option<&[T]>| {
        for (i, o) in o.iter_mut().enumerate() {
            let s = value(&own[i]);
            let mut v = w[1] * s;
            v += below.map_or(w[0] * s, |b| w[2] * value(&b[i]));
            v += above.map_or(w[2] * s, |a| w[0] * value(&a[i]));
            *o = v;
        }
    };
    let n0 = n[0];
    let rows = out.par_chunks_mut(slab).enumerate();
    rows.with_min_len(min_pieces(slab)).for_each(|(k, o)| {
        for (j, o) in o.chunks_mut(n0).enumerate() {
            let row = |j: usize, k: usize| &src[grid.cell(0, j, k)..][..n0];
            let own = row(j, k);
            match axis {
                0 if n0 == 1 => fold(o, own, None, None),
                0 => {
                    fold(&mut o[..1], &own[..1], None, Some(&own[1..2]));
                    let m = n0 - 1;
                    fold(&mut o[1..m], &own[1..m], Some(&own[..m - 1]), Some(&own[2..]));
                    fold(&mut o[m..], &own[m..], Some(&own[m - 1..m]), None);
                }
                1 => {
                    let below = (j > 0).then(|| row(j - 1, k));
                    fold(o, own, below, (j + 1 < n[1]).then(|| row(j + 1, k)));
                }
                _ => {
                    let below = (k > 0).then(|| row(j, k - 1));
                    fold(o, own, below, (k + 1 < n[2]).then(|| row(j, k + 1)));
                }
            }
        }
    });
}

/// The deep cells for a band `width` cells wide around the `outside` cells: more than
/// `width + 1` cells (L∞) from them, or more than `width` for the cells deep before (`was`).
pub fn deep_cells(grid: &Grid, outside: &[bool], width: usize, was: Option<&[bool]>) -> Vec<bool> {
    let cap = (width + 2).min(u8::MAX as usize) as u8;
    let d = surface::linf_distance(grid, outside, cap);
    (0..d.len())
        .into_par_iter()
        .map(|c| d[c] as usize > width + usize::from(!was.is_some_and(|w| w[c])))
        .collect()
}

/// Brings the band up to date before a step of `dt` through the field `u`: `outside` marks
/// the cells that are not liquid (air in the last φ_L, or a solid's centre), `width` the
/// band's width in cells for this step. The cells that left the deep set get their `m³`
/// sub-lattice sites, particles in cells that turned deep are taken out, and each deep cell
/// trades particles with the band as the grid's flux through its faces says (see
/// [`Band::owed`]). New particles sit where `admit` accepts them (outside the solids). The
/// particles' `bins`, when the caller has them, are not made again. See the module doc.
#[allow(clippy::too_many_arguments)]
pub fn update(
    particles: &mut Vec<Vec3>,
    bins: Option<surface::Bins>,
    band: &mut Band,
    outside: &[bool],
    width: usize,
    u: &Mac,
    dt: f64,
    grid: &Grid,
    m: usize,
    admit: impl Fn(Vec3) -> bool + Sync,
) -> BandChange {
    let deep = deep_cells(grid, outside, width, Some(&band.deep));
    let bins = bins.unwrap_or_else(|| surface::Bins::new(particles, grid));
    let off = surface::sub_offsets(m);
    let dx = grid.dx;
    let unit = dx.powi(3) / (m * m * m) as f64;
    // Only deep cells and those that just left the deep set trade, and of the deep cells
    // only those that were deep before, next to the band or with particles in them: one amid
    // deep cells with none in it keeps what it owes and has sent (no face to the band, no
    // particle to take out), so it is skipped, not traded to the same state.
    let cells = grid.cells();
    let quiet = |c: usize| {
        band.deep[c] && bins.cell(c).is_empty() && {
            let ijk = cells.ijk(c);
            (0..6).all(|f| cells.neighbour(c, ijk, f / 2, f % 2).is_none_or(|n| deep[n]))
        }
    };
    let trading: Vec<usize> = (0..deep.len())
        .into_par_iter()
        .with_min_len(crate::math::par::MIN_LEN)
        .filter(|&c| if deep[c] { !quiet(c) } else { band.deep[c] })
        .collect();
    let work: Vec<Trade> = trading
        .par_iter()
        .map(|&c| trade(c, band, &deep, &bins, particles, u, dt, grid, &off, unit, &admit))
        .collect();
    // The particles' trades and their compaction beside the deep cells' deposit, which
    // reads the new deep cells only (neither keeps two threads busy alone).
    let (owed_of, sent_of, density) = (&mut band.owed, &mut band.sent, &mut band.density);
    let deep_ref = &deep;
    let ((before, kept, added), ()) = rayon::join(
        || {
            let deep = deep_ref;
            // Deletions: everything in a deep cell, and what the deep cells take in, in cell
            // order (a particle two cells would take goes to the first; the other keeps its
            // debt).
            let mut gone = vec![false; particles.len()];
            for c in (0..deep.len()).filter(|&c| deep[c]) {
                bins.cell(c).iter().for_each(|&p| gone[p as usize] = true);
            }
            let before = particles.len();
            let mut added = 0;
            let mut seeded = Vec::new();
            for (&c, t) in trading.iter().zip(work) {
                let mut owed = t.owed;
                for p in t.take {
                    if owed > -0.5 * unit {
                        break;
                    }
                    if !gone[p as usize] {
                        gone[p as usize] = true;
                        owed += unit;
                    }
                }
                owed_of[c] = owed;
                sent_of[c] = t.sent;
                added += t.add.len();
                seeded.extend(t.add);
            }
            let kept: Vec<u32> =
                (0..before as u32).into_par_iter().filter(|&p| !gone[p as usize]).collect();
            // In place (the kept indices increase, so each moves down or stays): a second
            // vector of the particles would double their memory at the step's peak. Those
            // before the first one gone stay where they are.
            let first_gone = gone.iter().position(|&g| g).unwrap_or(before);
            for (i, &p) in kept.iter().enumerate().skip(first_gone) {
                particles[i] = particles[p as usize];
            }
            particles.truncate(kept.len());
            particles.reserve_exact(seeded.len());
            particles.extend(seeded);
            (before, kept, added)
        },
        || full_density_into(grid, deep_ref, m, density),
    );
    band.deep = deep;
    BandChange { before, kept, added }
}

/// What one cell trades with the band in an [`update`].
struct Trade {
    /// The volume it owes the band afterwards (before the particles `take` are taken).
    owed: f64,
    /// Its [`Band::sent`] afterwards.
    sent: u32,
    /// Particles it adds.
    add: Vec<Vec3>,
    /// Band particles it would take in, nearest first.
    take: Vec<u32>,
}

/// One cell's part of [`update`]: a cell that left the deep set is seeded; a deep cell adds
/// the net flux out of it in the step to what it owes the band, and the unit of every
/// particle in it (taken out: the band lost it), then sends a particle for each unit owed
/// (on the band side of the face the most flows out of, or in through), or names the band
/// particles nearest its inflow faces for each unit it is owed.
#[allow(clippy::too_many_arguments)]
fn trade(
    c: usize,
    band: &Band,
    deep: &[bool],
    bins: &surface::Bins,
    particles: &[Vec3],
    u: &Mac,
    dt: f64,
    grid: &Grid,
    off: &[f64],
    unit: f64,
    admit: &(impl Fn(Vec3) -> bool + Sync),
) -> Trade {
    let dx = grid.dx;
    let m = off.len();
    let ijk = grid.cells().ijk(c);
    let corner = |a: f64, b: f64, e: f64| {
        Vec3::new((ijk[0] as f64 + a) * dx, (ijk[1] as f64 + b) * dx, (ijk[2] as f64 + e) * dx)
    };
    let none = Trade { owed: 0.0, sent: 0, add: Vec::new(), take: Vec::new() };
    if !deep[c] {
        if !band.deep[c] {
            return none;
        }
        // Its sub-lattice, less what it still owed (or more, up to full).
        let ppc = m * m * m;
        let owed = (band.owed[c] / unit).round();
        let count = (ppc as f64 + owed).clamp(0.0, 2.0 * ppc as f64) as usize;
        let add: Vec<Vec3> = surface::sites(grid, ijk, off).filter(|x| admit(*x)).collect();
        // Fewer: spread over the sites; more: the extra a quarter of a site's spacing off.
        let shift = Vec3::splat(0.25 * dx / m as f64);
        let add: Vec<Vec3> = if count <= add.len() {
            let stride = add.len() as f64 / count.max(1) as f64;
            (0..count).map(|s| add[(s as f64 * stride) as usize]).collect()
        } else {
            let extra = add.iter().map(|x| *x + shift).filter(|x| admit(*x));
            add.iter().copied().chain(extra).take(count).collect()
        };
        return Trade { add, ..none };
    }
    // Net flux out through the faces to band cells; the faces the most flows out of and in
    // through.
    let mut net = 0.0;
    let mut out_face = (0.0, 0usize, 0i64);
    let mut in_faces = Vec::new();
    let mut any_face = (0usize, 0i64);
    for a in 0..3 {
        for s in 0..2 {
            let Some(nc) = grid.cells().neighbour(c, ijk, a, s).filter(|&n| !deep[n]) else {
                continue;
            };
            let side = 2 * s as i64 - 1;
            let mut f = ijk;
            f[a] += s;
            let flux = side as f64 * u.c[a][grid.faces(a).index(f[0], f[1], f[2])] * dt * dx * dx;
            if any_face.1 == 0 {
                any_face = (a, side);
            }
            net += flux;
            if flux > out_face.0 {
                out_face = (flux, a, side);
            }
            if flux < 0.0 {
                in_faces.push((flux, a, side, nc));
            }
        }
    }
    // Particles that flowed in since the last update, taken out: the band lost them.
    // A cell that just turned deep owes the band its particles' volume and is owed a full
    // cell: it takes what its particles lacked from the band, or sends back their excess.
    let inside = bins.cell(c).len();
    let start = if band.deep[c] { band.owed[c] } else { -unit * (m * m * m) as f64 };
    let mut owed = start + net + unit * inside as f64;
    let mut sent = band.sent[c];
    let mut add = Vec::new();
    if owed >= 0.5 * unit {
        // Out through the face the most flows out of (or, with none, back through the one
        // the most flowed in through, or any face to the band).
        let inflow = in_faces.iter().min_by(|x, y| x.0.total_cmp(&y.0));
        let (a, side) = match (out_face.0 > 0.0, inflow) {
            (true, _) => (out_face.1, out_face.2),
            (false, Some(f)) => (f.1, f.2),
            (false, None) => any_face,
        };
        // A site `admit` refuses (in a solid) is skipped and the volume stays owed; after
        // m² refusals in a row the rest waits for a later update.
        let mut refused = 0;
        while owed >= 0.5 * unit && side != 0 && refused < m * m {
            // In the first layer of the neighbour's sub-lattice, cycling through the face's
            // m² sites.
            let s = sent as usize % (m * m);
            sent = sent.wrapping_add(1);
            let (t0, t1) = (off[s % m], off[s / m]);
            let depth = if side > 0 { 1.0 + off[0] } else { -off[0] };
            let x = match a {
                0 => corner(depth, t0, t1),
                1 => corner(t0, depth, t1),
                _ => corner(t0, t1, depth),
            };
            if admit(x) {
                add.push(x);
                owed -= unit;
                refused = 0;
            } else {
                refused += 1;
            }
        }
    }
    let mut take = Vec::new();
    if owed <= -0.5 * unit {
        // The band particles across the inflow faces, nearest the cell first.
        let centre = grid.cells().position(ijk[0], ijk[1], ijk[2]);
        let mut near: Vec<(f64, u32)> = in_faces
            .iter()
            .flat_map(|f| bins.cell(f.3).iter())
            .map(|&p| ((particles[p as usize] - centre).abs().max_element(), p))
            .collect();
        near.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
        take = near.into_iter().map(|(_, p)| p).collect();
    }
    Trade { owed, sent, add, take }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::shape::Solid;

    fn grid() -> Grid {
        Grid { n: [12, 10, 8], dx: 0.1 }
    }

    /// A pool filling rows 0..=6 of [`grid`], freshly seeded, and the air above it.
    fn pool() -> (Grid, Vec<Vec3>, Vec<bool>) {
        let g = grid();
        let region = Solid::aabb(Vec3::ZERO, Vec3::new(1.2, 0.7, 0.8));
        let sdf = crate::geometry::fractions::NodeSdf::new(&g, &[]);
        let pos = surface::seed(&g, &[region], 8, &sdf, None);
        let outside = (0..g.num_cells()).map(|c| g.cells().ijk(c)[1] >= 7).collect();
        (g, pos, outside)
    }

    /// The separable depth is the brute-force L∞ distance to the outside cells.
    #[test]
    fn depth_is_the_linf_distance() {
        let g = grid();
        let outside: Vec<bool> = (0..g.num_cells()).map(|c| (c * 7919) % 23 == 0).collect();
        let d = surface::linf_distance(&g, &outside, 5);
        let cells = g.cells();
        for c in 0..g.num_cells() {
            let a = cells.ijk(c);
            let mut best = 5usize;
            for o in (0..g.num_cells()).filter(|&o| outside[o]) {
                let b = cells.ijk(o);
                let l = (0..3).map(|x| a[x].abs_diff(b[x])).max().unwrap();
                best = best.min(l);
            }
            assert_eq!(d[c] as usize, best, "cell {a:?}");
        }
    }

    /// A deep cell deposits what its seeded sub-lattice would, walls folded in.
    #[test]
    fn full_density_is_the_seeded_deposit() {
        let g = grid();
        for m in 1..=3 {
            let region = Solid::aabb(Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.5, 0.3, 0.8));
            let sdf = crate::geometry::fractions::NodeSdf::new(&g, &[]);
            let pos = surface::seed(&g, &[region], m * m * m, &sdf, None);
            let real = surface::particle_density(&pos, &g, m * m * m, None);
            let deep: Vec<bool> = (0..g.num_cells())
                .map(|c| {
                    let [i, j, _] = g.cells().ijk(c);
                    i < 5 && j < 3
                })
                .collect();
            let full = full_density(&g, &deep, m);
            for c in 0..g.num_cells() {
                assert!(
                    (real[c] - full[c]).abs() < 1e-12,
                    "m {m} cell {c}: {} {}",
                    real[c],
                    full[c]
                );
            }
        }
    }

    /// Still liquid: the update takes out the deep particles, and a second update changes
    /// nothing; with the grid's deposit the density is the full liquid's; the adjoint puts
    /// each kept particle's gradient at its old index. Given the particles' bins, the update
    /// is the same.
    #[test]
    fn update_takes_out_the_deep_particles_and_then_rests() {
        let (g, mut pos, outside) = pool();
        let all = pos.clone();
        let mut band = Band::empty(&g, &surface::SurfaceModel::nearest(0.0631, 2));
        let still = Mac::zeros(&g);
        let (mut binned, mut band_binned) = (pos.clone(), band.clone());
        let bins = Some(surface::Bins::new(&binned, &g));
        let given =
            update(&mut binned, bins, &mut band_binned, &outside, 2, &still, 0.01, &g, 2, |_| true);
        let change = update(&mut pos, None, &mut band, &outside, 2, &still, 0.01, &g, 2, |_| true);
        assert_eq!((&given, &binned, &band_binned), (&change, &pos, &band));
        // Rows 0..=3 are 4 or more cells from the air at row 7 (more than width + 1).
        let row = 12 * 8;
        assert_eq!(band.deep_cells(), 4 * row);
        assert_eq!(pos.len(), all.len() - 8 * 4 * row);
        assert_eq!(change.added, 0);
        let again = update(&mut pos, None, &mut band, &outside, 2, &still, 0.01, &g, 2, |_| true);
        assert_eq!((again.added, again.kept.len()), (0, pos.len()));
        let mixed = surface::particle_density(&pos, &g, 8, Some(&band.density));
        let real = surface::particle_density(&all, &g, 8, None);
        for c in 0..g.num_cells() {
            assert!((mixed[c] - real[c]).abs() < 1e-12);
        }
        let grads: Vec<Vec3> = (0..pos.len()).map(|i| Vec3::splat(i as f64 + 1.0)).collect();
        let back = change.adjoint(&grads);
        for (i, &k) in change.kept.iter().enumerate() {
            assert_eq!(back[k as usize], grads[i]);
            assert_eq!(all[k as usize], pos[i]);
        }
    }

    /// The deep cells trade particles with the band as the flux through their faces says:
    /// one particle's volume out of each top cell per step sends one, the same in takes the
    /// nearest, a particle that flowed in is taken out and owed back; and a deep cell the
    /// air comes near gets its sub-lattice back.
    #[test]
    fn update_trades_with_the_band_as_the_flux_says() {
        let (g, mut pos, outside) = pool();
        let mut band = Band::empty(&g, &surface::SurfaceModel::nearest(0.0631, 2));
        let dt = 0.01;
        let mut flow = Mac::zeros(&g);
        update(&mut pos, None, &mut band, &outside, 2, &flow, dt, &g, 2, |_| true);
        let row = 12 * 8;
        let n0 = pos.len();
        // Up: a unit of volume (dx³/8) through each top deep cell's upper face per step.
        flow.c[1].iter_mut().for_each(|v| *v = g.dx / (8.0 * dt));
        let change = update(&mut pos, None, &mut band, &outside, 2, &flow, dt, &g, 2, |_| true);
        assert_eq!(change.added, row);
        assert_eq!(pos.len(), n0 + row);
        let sent = &pos[n0..];
        assert!(sent.iter().all(|x| (x.y - 0.425).abs() < 1e-12), "in row 4's first layer");
        // Down: each top deep cell takes one particle of row 4 back, the nearest.
        flow.c[1].iter_mut().for_each(|v| *v = -g.dx / (8.0 * dt));
        let change = update(&mut pos, None, &mut band, &outside, 2, &flow, dt, &g, 2, |_| true);
        assert_eq!((change.added, pos.len()), (0, n0));
        assert!(band.owed.iter().all(|o| o.abs() < 1e-15));
        // A particle that flowed into a deep cell is taken out, and sent back when still.
        let still = Mac::zeros(&g);
        pos[0].y = 0.35;
        let change = update(&mut pos, None, &mut band, &outside, 2, &still, dt, &g, 2, |_| true);
        assert!(!change.kept.contains(&0));
        assert_eq!((change.added, pos.len()), (1, n0));
        // The air comes down to row 4: rows 2 and 3 (within the width of it) leave the deep
        // set and are seeded; rows 0 and 1 stay.
        let lower: Vec<bool> = (0..g.num_cells()).map(|c| g.cells().ijk(c)[1] >= 4).collect();
        let change = update(&mut pos, None, &mut band, &lower, 2, &still, dt, &g, 2, |_| true);
        assert_eq!(band.deep_cells(), 2 * row);
        assert_eq!(change.added, 8 * 2 * row);
    }
}
