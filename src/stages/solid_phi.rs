//! The liquid signed distance φ_L carried into the solids (part of the step's system).
//!
//! No particle sits inside a solid, so the particles' φ_L at a cell whose centre is in a
//! static solid or a body says nothing about the liquid there. Such a cell still matters when
//! a face of it is partly open: it is a pressure unknown (liquid) or a ghost-fluid air cell,
//! and the pressure it gets pushes on the body. Its φ is therefore carried in from the cells
//! around it, a layer at a time, as the mean of its face neighbours' φ that are outside the
//! solids or already set ([`SolidExtension`]).
//!
//! The free surface then meets a body where the liquid beside it lies: a ball floating at
//! rest has, inside it, the same flat surface as the water around it, and hydrostatic
//! pressure is an exact rest state of the step. The rule before this one marked every solid
//! cell next to a liquid cell as liquid (φ = −½·dx, Batty's codes do the same), which put a
//! false free surface up to a cell above the waterline inside every curved or tilted body
//! crossing the surface; the projection made a current out of it each step, and that
//! current, fed back through the body's bobbing, drove still water around a floating ball to
//! tens of joules (issue 33).
//!
//! A moving body's surface crosses cell centres, and a yes/no rule would make φ jump there
//! (by up to a cell: the particles' φ against the neighbours' mean), and with it the
//! ghost-fluid θ of the cell's faces and the body's path. So a cell counts as solid by a
//! degree s ∈ [0, 1]: 1 with its centre in a solid, falling to 0 over [`RAMP`] cells outside
//! a body (a static solid does not move and keeps the yes/no rule), and every choice the rule
//! makes is weighed continuously in s:
//!
//! - layer 0: E₀ = Σ w·φ / T₀ over the face neighbours, w = (1 − s_n)·(a + γ), with a the
//!   axis's weight across gravity (1 − ĝ_a²) and γ = max(0, 1 − Σ(1 − s_n)·a / 0.05) letting
//!   the neighbours along gravity count where (almost) none across it does; its share
//!   μ = min(1, T₀/0.05);
//! - layer 1: E₁ the same mean of the neighbours' E₀ with weights s_n·μ_n·(a + γ₁), its
//!   share ν = min(1, T₁/0.05);
//! - X = μ·E₀ + (1 − μ)·(ν·E₁ + (1 − ν)·φ), and the cell's φ becomes (1 − s)·φ + s·X.
//!
//! Where s is 0 or 1 (every static solid, every cell in a body, every cell over [`RAMP`]
//! cells from one) this is the yes/no rule, with the same bits: a cell with a neighbour
//! outside the solids is a mean of those (layer 0), one with a layer-0 neighbour a mean of
//! theirs (layer 1), deeper cells keep the particles' φ. The ramp lies outside the body so
//! that no cell inside one reads the particles' φ there (no particle is inside; a cell that
//! did read them turned to air under a rising box, and a ball at rest lost its rest state).
//! Where the particles' φ is level the ramp keeps it so (its mean across gravity is the same
//! level). The map is linear in φ for fixed s, and [`SolidExtension::transpose`] carries ∂L/∂φ
//! back to the cells it read and to s, hence to the bodies' poses.

use crate::geometry::body::RigidBody;
use crate::geometry::grid::{Grid, NONE};
use crate::math::par::MIN_LEN;
use crate::math::Twist;
use rayon::prelude::*;

/// How far (in cells) outside a body a cell centre lies before its φ is the particles' alone:
/// from there to the body's surface the extension takes over linearly.
pub const RAMP: f64 = 0.5;

/// A cell whose centre lies less than [`RAMP`] cells outside a body (and in no solid, nor
/// nearer another body): how solid it counts, and the body that says so.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PartialSolid {
    /// The cell.
    pub cell: u32,
    /// The body (index among the step's bodies).
    pub body: u32,
    /// Its degree of solidity, in (0, 1).
    pub s: f64,
}

/// The degree of solidity of a centre at signed distance `sdf` from a body's surface.
#[inline]
pub fn solidity(sdf: f64, dx: f64) -> f64 {
    (1.0 - sdf / (RAMP * dx)).clamp(0.0, 1.0)
}

/// The bodies' ∂L/∂pose from ∂L/∂s of the partial cells (`sbar`, as
/// [`SolidExtension::transpose`] returns it), added into `pose`.
pub fn solidity_pose_adjoint(
    grid: &Grid,
    bodies: &[RigidBody],
    sbar: &[(PartialSolid, f64)],
    pose: &mut [Twist],
) {
    let cells = grid.cells();
    for (p, bar) in sbar {
        let [i, j, k] = cells.ijk(p.cell as usize);
        let d = bodies[p.body as usize].sdf_pose_dual(cells.position(i, j, k));
        for (acc, dd) in pose[p.body as usize].iter_mut().zip(d.d) {
            *acc -= bar * dd / (RAMP * grid.dx);
        }
    }
}

/// Per cell, whether the extension reads its φ (for `centre_in_solid` and the `partial`
/// cells of a [`crate::stages::system::Geometry`]): the cells it sets and their neighbours
/// (L∞, a superset of the face neighbours its layers read). See
/// [`crate::stages::surface::Reads`].
pub fn extension_reads(
    grid: &Grid,
    centre_in_solid: &[bool],
    partial: &[PartialSolid],
) -> Vec<bool> {
    let mut set = centre_in_solid.to_vec();
    for p in partial {
        set[p.cell as usize] = true;
    }
    crate::stages::surface::linf_distance(grid, &set, 2).into_par_iter().map(|d| d <= 1).collect()
}

/// What a step gives [`crate::stages::surface::liquid_sdf`] as its
/// [`crate::stages::surface::Reads::near_solids`]: [`extension_reads`] for the soft minimum
/// of `model`, None where φ_L's value is made in every cell (the nearest particle, whose
/// search deep in the liquid is short, or `everywhere`: `solver.surface_interior_values`).
pub fn value_reads(
    grid: &Grid,
    centre_in_solid: &[bool],
    partial: &[PartialSolid],
    model: &crate::stages::surface::SurfaceModel,
    everywhere: bool,
) -> Option<Vec<bool>> {
    (model.softness > 0.0 && !everywhere).then(|| extension_reads(grid, centre_in_solid, partial))
}

/// One cell the extension sets: its neighbours and the values of the forward pass that its
/// transpose reads.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Set {
    cell: u32,
    /// Face neighbours, in face order (−x, +x, −y, …); `NONE` beyond the grid.
    nbr: [u32; 6],
    /// The neighbours' degrees of solidity.
    s_nbr: [f64; 6],
    /// This cell's degree of solidity.
    s: f64,
    /// Layer 0: Σ(1 − s_n)·a, its total weight and share, and its mean.
    z0: f64,
    t0: f64,
    mu: f64,
    e0: f64,
    /// Layer 1: Σ s_n·μ_n·a, its total weight and share, and its mean.
    z1: f64,
    t1: f64,
    nu: f64,
    e1: f64,
    /// φ here before the extension.
    raw: f64,
}

impl Set {
    /// The value the cell is set to.
    fn value(&self) -> f64 {
        let x =
            self.mu * self.e0 + (1.0 - self.mu) * (self.nu * self.e1 + (1.0 - self.nu) * self.raw);
        (1.0 - self.s) * self.raw + self.s * x
    }
}

/// Where φ_L is carried into the solids, and how (see the module's documentation).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SolidExtension {
    /// The weight of each axis across gravity.
    across: [f64; 3],
    /// The cells set, in cell order.
    set: Vec<Set>,
    /// The cells partly in a body, in cell order.
    partial: Vec<PartialSolid>,
}

/// Below this total weight of neighbours across gravity, those along it count too (where
/// none across it does, fully). Small, so that a cell beside a body, whose neighbours across
/// gravity are partly solid, still reads the level beside it and not the cells above and
/// below (a capsule at rest stirred the liquid to 2.8e-3 J with γ = max(0, 1 − z)).
const ALONG_BELOW: f64 = 0.05;

/// Below this total weight a layer's mean gives way to the next layer's (μ, ν =
/// min(1, T/`SHARE_BELOW`)): small, so that a cell in a body reads the cells outside it
/// however little of them is outside, and the particles' φ only where nothing around is.
const SHARE_BELOW: f64 = 0.05;

/// A layer's share min(1, t/[`SHARE_BELOW`]) and its derivative in t.
#[inline]
fn share(t: f64) -> (f64, f64) {
    if t < SHARE_BELOW {
        (t / SHARE_BELOW, 1.0 / SHARE_BELOW)
    } else {
        (1.0, 0.0)
    }
}

/// Layer weight (a + γ) with γ = max(0, 1 − z/[`ALONG_BELOW`]): the neighbours along
/// gravity count where too little across it does.
#[inline]
fn gamma(z: f64) -> f64 {
    (1.0 - z / ALONG_BELOW).max(0.0)
}

/// dγ/dz.
#[inline]
fn gamma_slope(z: f64) -> f64 {
    if z < ALONG_BELOW {
        -1.0 / ALONG_BELOW
    } else {
        0.0
    }
}

impl SolidExtension {
    /// Carries `phi` (the particles' φ_L) into the cells `centre_in_solid` marks, `partial`
    /// (in cell order) saying which of those are partly solid; returns the extension, for
    /// its transpose.
    pub fn apply_new(
        grid: &Grid,
        centre_in_solid: &[bool],
        partial: &[PartialSolid],
        gravity: [f64; 3],
        phi: &mut [f64],
    ) -> SolidExtension {
        let g2: f64 = gravity.iter().map(|x| x * x).sum();
        // A neighbour along axis a weighs 1 − ĝ_a²: across gravity, where a liquid at rest is
        // level; along it only where nothing else is (or without gravity).
        let across: [f64; 3] =
            std::array::from_fn(
                |a| if g2 > 0.0 { 1.0 - gravity[a] * gravity[a] / g2 } else { 1.0 },
            );
        debug_assert!(partial.windows(2).all(|w| w[0].cell < w[1].cell));
        let cells = grid.cells();
        let mut solid: Vec<u32> = (0..centre_in_solid.len() as u32)
            .into_par_iter()
            .with_min_len(MIN_LEN)
            .filter(|&c| centre_in_solid[c as usize])
            .collect();
        if !partial.is_empty() {
            solid.extend(partial.iter().map(|p| p.cell));
            solid.sort_unstable();
        }
        let s_of = |c: usize| -> f64 {
            if centre_in_solid[c] {
                return 1.0;
            }
            match partial.binary_search_by_key(&(c as u32), |p| p.cell) {
                Ok(k) => partial[k].s,
                Err(_) => 0.0,
            }
        };
        let phi_in: &[f64] = phi;
        // Layer 0, from the cells outside the solids (by how much they are outside).
        let layer0: Vec<Set> = solid
            .par_iter()
            .with_min_len(MIN_LEN)
            .map(|&c| {
                let ci = c as usize;
                let ijk = cells.ijk(ci);
                let mut set = Set {
                    cell: c,
                    nbr: [NONE; 6],
                    s_nbr: [1.0; 6],
                    s: s_of(ci),
                    z0: 0.0,
                    t0: 0.0,
                    mu: 0.0,
                    e0: 0.0,
                    z1: 0.0,
                    t1: 0.0,
                    nu: 0.0,
                    e1: 0.0,
                    raw: phi_in[ci],
                };
                for f in 0..6 {
                    if let Some(nb) = cells.neighbour(ci, ijk, f / 2, f % 2) {
                        set.nbr[f] = nb as u32;
                        set.s_nbr[f] = s_of(nb);
                    }
                }
                let outside = set.s_nbr.map(|s| 1.0 - s);
                let l = Layer::new(outside, across, |f| phi_in[set.nbr[f] as usize]);
                (set.z0, set.t0, set.mu, set.e0) = (l.z, l.t, share(l.t).0, l.mean);
                set
            })
            .collect();
        let find = |c: u32| solid.binary_search(&c).ok();
        // Layer 1, from the layer-0 means of the cells around (by how much they have one).
        let mut set: Vec<Set> = layer0
            .par_iter()
            .with_min_len(MIN_LEN)
            .map(|&s0| {
                let mut set = s0;
                let kappa: [f64; 6] = std::array::from_fn(|f| {
                    let nb = set.nbr[f];
                    match (nb != NONE).then(|| find(nb)).flatten() {
                        Some(k) => set.s_nbr[f] * layer0[k].mu,
                        None => 0.0,
                    }
                });
                let l = Layer::new(kappa, across, |f| {
                    layer0[find(set.nbr[f]).expect("a solid cell")].e0
                });
                (set.z1, set.t1, set.nu, set.e1) = (l.z, l.t, share(l.t).0, l.mean);
                set
            })
            .filter(|s| s.mu > 0.0 || s.nu > 0.0)
            .collect();
        set.shrink_to_fit();
        for s in &set {
            phi[s.cell as usize] = s.value();
        }
        SolidExtension { across, set, partial: partial.to_vec() }
    }

    /// φ before [`SolidExtension::apply_new`] extended it into `phi`.
    pub fn raw(&self, phi: &[f64]) -> Vec<f64> {
        let mut raw = phi.to_vec();
        for s in &self.set {
            raw[s.cell as usize] = s.raw;
        }
        raw
    }

    /// The cells set, in cell order.
    pub fn cells(&self) -> impl Iterator<Item = usize> + '_ {
        self.set.iter().map(|s| s.cell as usize)
    }

    /// The transpose of [`SolidExtension::apply_new`] at the φ it made (`phi`, extended):
    /// `phi_bar` of the extended φ becomes, in place, that of φ before it; returns ∂L/∂s of
    /// the partly solid cells it reaches (for [`solidity_pose_adjoint`]).
    pub fn transpose(&self, phi: &[f64], phi_bar: &mut [f64]) -> Vec<(PartialSolid, f64)> {
        let n = self.set.len();
        let find = |c: u32| self.set.binary_search_by_key(&c, |s| s.cell).ok();
        let raw = |c: u32| find(c).map_or(phi[c as usize], |k| self.set[k].raw);
        let mut sbar = vec![0.0; self.partial.len()];
        let mut add_s = |c: u32, x: f64| {
            if let Ok(k) = self.partial.binary_search_by_key(&c, |p| p.cell) {
                sbar[k] += x;
            }
        };
        let (mut e0b, mut mub, mut e1b, mut nub) =
            (vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        // φ = (1 − s)·raw + s·X, X = μ·E₀ + (1 − μ)·(ν·E₁ + (1 − ν)·raw).
        let fb: Vec<f64> =
            self.set.iter().map(|s| std::mem::take(&mut phi_bar[s.cell as usize])).collect();
        for (r, s) in self.set.iter().enumerate() {
            let b = fb[r];
            if b == 0.0 {
                continue;
            }
            let inner = s.nu * s.e1 + (1.0 - s.nu) * s.raw;
            let x = s.mu * s.e0 + (1.0 - s.mu) * inner;
            phi_bar[s.cell as usize] += (1.0 - s.s) * b + s.s * (1.0 - s.mu) * (1.0 - s.nu) * b;
            add_s(s.cell, (x - s.raw) * b);
            let xb = s.s * b;
            e0b[r] += s.mu * xb;
            mub[r] += (s.e0 - inner) * xb;
            e1b[r] += (1.0 - s.mu) * s.nu * xb;
            nub[r] += (1.0 - s.mu) * (s.e1 - s.raw) * xb;
        }
        // Layer 1 (k = κ = s_n·μ_n of the neighbours' E₀), then layer 0 (k = 1 − s_n of
        // their φ).
        for (r, s) in self.set.iter().enumerate() {
            if s.t1 <= 0.0 || (e1b[r] == 0.0 && nub[r] == 0.0) {
                continue;
            }
            let nbk: [Option<usize>; 6] =
                std::array::from_fn(|f| (s.nbr[f] != NONE).then(|| find(s.nbr[f])).flatten());
            let kappa =
                std::array::from_fn(|f| nbk[f].map_or(0.0, |k| s.s_nbr[f] * self.set[k].mu));
            let vals = std::array::from_fn(|f| nbk[f].map_or(0.0, |k| self.set[k].e0));
            let layer = Layer { k: kappa, z: s.z1, t: s.t1, mean: s.e1 };
            let (vb, kb) = layer.adjoint(self.across, &vals, e1b[r], nub[r]);
            for f in (0..6).filter(|&f| kappa[f] > 0.0) {
                let k = nbk[f].expect("a set cell");
                e0b[k] += vb[f];
                add_s(s.nbr[f], self.set[k].mu * kb[f]);
                mub[k] += s.s_nbr[f] * kb[f];
            }
        }
        for (r, s) in self.set.iter().enumerate() {
            if s.t0 <= 0.0 || (e0b[r] == 0.0 && mub[r] == 0.0) {
                continue;
            }
            let outside = s.s_nbr.map(|x| 1.0 - x);
            let vals = std::array::from_fn(|f| if outside[f] > 0.0 { raw(s.nbr[f]) } else { 0.0 });
            let layer = Layer { k: outside, z: s.z0, t: s.t0, mean: s.e0 };
            let (vb, kb) = layer.adjoint(self.across, &vals, e0b[r], mub[r]);
            for f in (0..6).filter(|&f| outside[f] > 0.0) {
                phi_bar[s.nbr[f] as usize] += vb[f];
                add_s(s.nbr[f], -kb[f]);
            }
        }
        self.partial.iter().zip(sbar).filter(|(_, b)| *b != 0.0).map(|(p, b)| (*p, b)).collect()
    }
}

/// One layer's mean of a cell: m = Σ w·v / T over the face neighbours with the weights
/// w = k·(a + γ(z)) (k = 0 beyond the grid), z = Σ k·a, T = Σ w (m = 0 where T is), and its
/// share from T.
struct Layer {
    k: [f64; 6],
    z: f64,
    t: f64,
    mean: f64,
}

impl Layer {
    /// The mean of the neighbours' values `v(face)`, read only where their weight is positive.
    fn new(k: [f64; 6], across: [f64; 3], v: impl Fn(usize) -> f64) -> Layer {
        let z: f64 = (0..6).map(|f| k[f] * across[f / 2]).sum();
        let g = gamma(z);
        let w: [f64; 6] =
            std::array::from_fn(|f| if k[f] > 0.0 { k[f] * (across[f / 2] + g) } else { 0.0 });
        let t: f64 = w.iter().sum();
        let mean = if t > 0.0 {
            (0..6).filter(|&f| w[f] > 0.0).map(|f| w[f] / t * v(f)).sum()
        } else {
            0.0
        };
        Layer { k, z, t, mean }
    }

    /// Given ∂L/∂m (`mean_bar`) and ∂L/∂share (`share_bar`), ∂L/∂v and ∂L/∂k per face for
    /// the neighbours' values `v`.
    fn adjoint(
        &self,
        across: [f64; 3],
        v: &[f64; 6],
        mean_bar: f64,
        share_bar: f64,
    ) -> ([f64; 6], [f64; 6]) {
        let tb = share(self.t).1 * share_bar;
        let g = gamma(self.z);
        let (mut vb, mut kb) = ([0.0; 6], [0.0; 6]);
        let mut gb = 0.0;
        for f in (0..6).filter(|&f| self.k[f] > 0.0) {
            let a = across[f / 2] + g;
            vb[f] = self.k[f] * a / self.t * mean_bar;
            let wb = (v[f] - self.mean) / self.t * mean_bar + tb;
            kb[f] = a * wb;
            gb += self.k[f] * wb;
        }
        let zb = gamma_slope(self.z) * gb;
        for f in (0..6).filter(|&f| self.k[f] > 0.0) {
            kb[f] += across[f / 2] * zb;
        }
        (vb, kb)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::grid::Grid;
    use crate::math::Vec3;

    const R: f64 = 0.32;

    /// A ball of radius `R` about `centre` on a 10³ grid: the cells whose centre is in it and
    /// those partly so.
    fn ball(centre: Vec3) -> (Grid, Vec<bool>, Vec<PartialSolid>) {
        let grid = Grid { n: [10, 10, 10], dx: 0.1 };
        let cells = grid.cells();
        let sdf = |c: usize| {
            let [i, j, k] = cells.ijk(c);
            (cells.position(i, j, k) - centre).length() - R
        };
        let solid = (0..grid.num_cells()).map(|c| sdf(c) < 0.0).collect();
        let partial = (0..grid.num_cells())
            .map(|c| (c, solidity(sdf(c), grid.dx)))
            .filter(|&(_, s)| s > 0.0 && s < 1.0)
            .map(|(c, s)| PartialSolid { cell: c as u32, body: 0, s })
            .collect();
        (grid, solid, partial)
    }

    fn noise(n: usize, seed: u64) -> Vec<f64> {
        let mut rng = seed;
        (0..n)
            .map(|_| {
                rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (rng >> 11) as f64 / (1u64 << 53) as f64 - 0.5
            })
            .collect()
    }

    fn height(grid: &Grid, c: usize) -> f64 {
        let cells = grid.cells();
        let [i, j, k] = cells.ijk(c);
        cells.position(i, j, k).y
    }

    /// A flat free surface crosses a ball: inside the ball the extension puts it at the
    /// same height (to round-off) wherever a cell reads only neighbours at its own height, and
    /// never makes a cell above the surface liquid. Without the ramp (every solid cell fully
    /// solid) and with it (the particles' φ there is the same flat surface).
    #[test]
    fn flat_surface_continues_through_a_ball() {
        let (grid, solid, partial) = ball(Vec3::new(0.5, 0.5, 0.5));
        assert!(!partial.is_empty());
        let h = 0.52;
        for partial in [&[][..], &partial[..]] {
            let mut phi: Vec<f64> = (0..grid.num_cells())
                .map(|c| if solid[c] { 1.0 } else { height(&grid, c) - h })
                .collect();
            if !partial.is_empty() {
                partial
                    .iter()
                    .for_each(|p| phi[p.cell as usize] = height(&grid, p.cell as usize) - h);
            }
            let ext =
                SolidExtension::apply_new(&grid, &solid, partial, [0.0, -9.81, 0.0], &mut phi);
            assert!(ext.cells().count() > 0);
            for c in ext.cells() {
                let y = height(&grid, c);
                assert_eq!(phi[c] < 0.0, y < h, "cell at height {y}: φ {}", phi[c]);
            }
        }
    }

    /// Without partly solid cells the extension is linear in φ: ⟨E·a, b⟩ = ⟨a, Eᵀ·b⟩ for
    /// random a and b.
    #[test]
    fn transpose_is_the_transpose() {
        let (grid, solid, _) = ball(Vec3::new(0.5, 0.5, 0.5));
        let n = grid.num_cells();
        let (a, b) = (noise(n, 1), noise(n, 2));
        let mut ea = a.clone();
        let ext = SolidExtension::apply_new(&grid, &solid, &[], [0.0, -9.81, 0.0], &mut ea);
        let mut etb = b.clone();
        assert!(ext.transpose(&ea, &mut etb).is_empty());
        let lhs: f64 = ea.iter().zip(&b).map(|(x, y)| x * y).sum();
        let rhs: f64 = a.iter().zip(&etb).map(|(x, y)| x * y).sum();
        assert!((lhs - rhs).abs() < 1e-12 * lhs.abs().max(1.0), "{lhs} vs {rhs}");
    }

    /// ⟨b, E(φ, s)⟩ with its transpose's ∂/∂φ and ∂/∂s against central differences (1e-6),
    /// with partly solid cells of every kind (layer 0, layer 1, read by others), and gravity
    /// along an axis and tilted.
    #[test]
    fn transpose_matches_central_differences_in_phi_and_solidity() {
        for gravity in [[0.0, -9.81, 0.0], [3.0, -9.0, 1.0]] {
            let (grid, solid, partial) = ball(Vec3::new(0.47, 0.52, 0.49));
            let n = grid.num_cells();
            let (phi0, b) = (noise(n, 3), noise(n, 4));
            let loss = |phi: &[f64], partial: &[PartialSolid]| -> f64 {
                let mut p = phi.to_vec();
                SolidExtension::apply_new(&grid, &solid, partial, gravity, &mut p);
                p.iter().zip(&b).map(|(x, y)| x * y).sum()
            };
            let mut ext_phi = phi0.clone();
            let ext = SolidExtension::apply_new(&grid, &solid, &partial, gravity, &mut ext_phi);
            let mut phi_bar = b.clone();
            let sbar = ext.transpose(&ext_phi, &mut phi_bar);
            let h = 1e-6;
            let (mut checked, mut reached) = (0, 0);
            for c in ext.cells().chain(partial.iter().map(|p| p.cell as usize + 1)).take(400) {
                let (mut up, mut down) = (phi0.clone(), phi0.clone());
                up[c] += h;
                down[c] -= h;
                let fd = (loss(&up, &partial) - loss(&down, &partial)) / (2.0 * h);
                assert!(
                    (fd - phi_bar[c]).abs() < 1e-8,
                    "∂/∂φ at cell {c}: {} against fd {fd}",
                    phi_bar[c]
                );
                checked += 1;
            }
            // (Away from the ramp's ends, where s is clamped.)
            for (k, p) in partial.iter().enumerate().filter(|(_, p)| p.s > 1e-4 && p.s < 1.0 - 1e-4)
            {
                let (mut up, mut down) = (partial.clone(), partial.clone());
                up[k].s += h;
                down[k].s -= h;
                let fd = (loss(&phi0, &up) - loss(&phi0, &down)) / (2.0 * h);
                let adj = sbar.iter().find(|(q, _)| q.cell == p.cell).map_or(0.0, |(_, x)| *x);
                assert!(
                    (fd - adj).abs() < 1e-8,
                    "∂/∂s at cell {} (s {}, gravity {gravity:?}): {adj} against fd {fd}",
                    p.cell,
                    p.s
                );
                reached += usize::from(fd.abs() > 1e-3);
            }
            assert!(checked > 100 && reached > 20, "{checked} φ and {reached} s derivatives");
        }
    }

    /// As a ball moves, φ changes continuously: where a cell centre crosses the ball's
    /// surface or the ramp's outer end, φ's largest change shrinks with the ball's move
    /// (tenfold for a tenfold smaller move); with the yes/no rule a centre entering the ball
    /// moves its φ by up to a cell at once, however small the move.
    #[test]
    fn phi_is_continuous_as_a_ball_moves() {
        let grid = Grid { n: [10, 10, 10], dx: 0.1 };
        let cells = grid.cells();
        let phi0: Vec<f64> = noise(grid.num_cells(), 5).iter().map(|x| 0.2 * x).collect();
        let extended = |x: f64, ramp: bool| {
            let (grid, solid, partial) = ball(Vec3::new(x, 0.5, 0.5));
            let mut phi = phi0.clone();
            let partial = if ramp { partial } else { Vec::new() };
            SolidExtension::apply_new(&grid, &solid, &partial, [0.0, -9.81, 0.0], &mut phi);
            phi
        };
        // Where the ball's surface (or the ramp's end) crosses a centre as the ball's centre
        // moves along x over 0.45–0.55.
        let crossings = |r: f64| -> Vec<f64> {
            (0..grid.num_cells())
                .flat_map(|c| {
                    let [i, j, k] = cells.ijk(c);
                    let p = cells.position(i, j, k);
                    let r2 = r * r - (p.y - 0.5).powi(2) - (p.z - 0.5).powi(2);
                    let dx = if r2 > 0.0 { r2.sqrt() } else { f64::NAN };
                    [p.x - dx, p.x + dx]
                })
                .filter(|x| (0.45..0.55).contains(x))
                .collect()
        };
        let (surface, ramp_end) = (crossings(R), crossings(R + RAMP * grid.dx));
        assert!(
            surface.len() > 20 && ramp_end.len() > 20,
            "{} and {}",
            surface.len(),
            ramp_end.len()
        );
        let largest_jump = |ramp: bool, h: f64| {
            let at = if ramp { [&surface, &ramp_end] } else { [&surface, &surface] };
            at.into_iter()
                .flatten()
                .map(|&x| {
                    let (a, b) = (extended(x - h, ramp), extended(x + h, ramp));
                    a.iter().zip(&b).map(|(p, q)| (p - q).abs()).fold(0.0, f64::max)
                })
                .fold(0.0, f64::max)
        };
        let (coarse, fine) = (largest_jump(true, 1e-8), largest_jump(true, 1e-9));
        assert!(fine > 0.0 && fine < 0.15 * coarse, "with the ramp: {coarse} and {fine}");
        // The steepest slope: the thresholds (1/0.05 each) on the ramp's 1/(RAMP·dx), over
        // the φ differences of ±0.1 here; the yes/no rule's jump is over a thousand times it.
        assert!(coarse < 1e-4, "with the ramp: {coarse}");
        let (coarse, fine) = (largest_jump(false, 1e-8), largest_jump(false, 1e-9));
        assert!(fine > 1e-2 && fine > 0.5 * coarse, "the yes/no rule jumps: {coarse} and {fine}");
    }
}
