//! The extrapolation with liquid–air faces blended in (`solver.surface_blend`).
//!
//! With the yes/no rule a face next to a liquid cell keeps its projected velocity and every
//! other face takes the mean of its neighbours known before its layer. As a cell turns from
//! liquid to air (φ_L crossing zero at its centre), its faces to air stop being projected
//! and take their neighbours' mean instead: the step jumps by the difference.
//!
//! Here every face carries a share m ∈ [0, 1] of what it knows and w = m·(its velocity).
//! A face whose liquid side meets air nearer than θ₁ (ghost-fluid fraction θ < θ₁) knows
//! only a share c = θ/θ₁ of its projected velocity (the corner at θ₁ rounded, see
//! [`SurfaceBlend`]); a face a body covers in part knows the body's part of it wholly and its
//! fluid part by that part's share (c on a liquid–air face,
//! 1 on one between liquid cells, 0 on one in air), so a face a body starts to cover starts
//! with a share near zero. Each layer updates, from the values before it, the faces it
//! reaches and those still known in part: with z = Σ m and s = Σ w over the face's lattice
//! neighbours and k = 1 − m,
//!
//! ```text
//!   z ≥ 1:  m' = 1,          w' = w + k·s/z   (the rest taken from the neighbours' mean)
//!   z < 1:  m' = m + k·z,    w' = w + k·s     (a share z of it, from neighbours known in part)
//! ```
//!
//! and after the last layer the velocity is w (a face known in part fades to zero with its
//! share). Every operation is continuous in the shares and the velocities, and a share → 0
//! is the face not known at all. With every share 0 or 1 it is the yes/no rule to the bit
//! (each face set by the mean of its known neighbours, in the same order).

use super::{neighbours, Layers, CHUNK};
use crate::geometry::fractions::BodyFaces;
use crate::geometry::grid::{Grid, Lattice, NONE};
use crate::geometry::weights::FaceWeights;
use crate::stages::pressure::{GhostFluid, PressureSystem};
use rayon::prelude::*;

/// How far (in t = θ/θ₁) either side of t = 1 [`SurfaceBlend::share`] rounds its corner.
pub const ROUNDING: f64 = 0.1;

/// How liquid–air faces blend from projected into extrapolated velocity: a face's share of
/// its projected velocity is c = min(1, t), t = θ/θ₁ with θ the unclamped ghost-fluid
/// fraction, its corner rounded: within `ROUNDING` of t = 1 a quartic joins the two with
/// continuous first and second derivatives (c = 1 − 3·ROUNDING/16 at t = 1). The corner
/// alone was a kink of the map, and a freshly seeded flat surface, which puts θ at exactly
/// ½ on its faces, sat on it at the default θ₁ = ½ (docs/gradients.md, "The blend's share
/// at the seeded surface").
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceBlend {
    /// θ₁, the fraction from which a face is wholly projected; 0 for the yes/no rule.
    pub theta: f64,
}

impl SurfaceBlend {
    /// The share of the projected velocity of a face from a liquid cell at `phi_liquid`
    /// (< 0) to an air cell at `phi_air` (≥ 0).
    #[inline]
    pub fn share(&self, phi_liquid: f64, phi_air: f64) -> f64 {
        rounded_min(GhostFluid::fraction(phi_liquid, phi_air) / self.theta).0
    }

    /// (∂c/∂φ_l, ∂c/∂φ_a) of [`SurfaceBlend::share`] (zero where it is 1).
    #[inline]
    pub fn share_gradient(&self, phi_liquid: f64, phi_air: f64) -> (f64, f64) {
        let (_, dc_dt) = rounded_min(GhostFluid::fraction(phi_liquid, phi_air) / self.theta);
        if dc_dt == 0.0 {
            return (0.0, 0.0);
        }
        let (dl, da) = GhostFluid::fraction_gradient(phi_liquid, phi_air);
        let k = dc_dt / self.theta;
        (dl * k, da * k)
    }
}

/// min(1, t) with its corner rounded over [1 − `ROUNDING`, 1 + `ROUNDING`], and its
/// derivative in t: over the rounding, with s its fraction, g(s) = s − s³ + s⁴/2 leaves t
/// with slope 1 and no curvature and meets 1 with neither.
#[inline]
fn rounded_min(t: f64) -> (f64, f64) {
    if t <= 1.0 - ROUNDING {
        (t, 1.0)
    } else if t >= 1.0 + ROUNDING {
        (1.0, 0.0)
    } else {
        let s = (t - 1.0 + ROUNDING) / (2.0 * ROUNDING);
        let c = 1.0 - ROUNDING + 2.0 * ROUNDING * (s - s.powi(3) + 0.5 * s.powi(4));
        (c, (1.0 - s).powi(2) * (1.0 + 2.0 * s))
    }
}

/// A face that starts the extrapolation known in part: a liquid–air face whose θ is below
/// θ₁, or a face a body covers in part (not wholly) whose fluid part is not wholly known.
/// It starts with share m⁰ = 1 − (1 − c)·fluid/open and w⁰ = u − (1 − c)·fluid·u_fl, u its
/// value after the bodies' velocities were mixed in (w·u_fl + Σ β·u_b where a body covers
/// it, u_fl where none does) and u_fl its fluid velocity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceFace {
    /// Face index on its axis's lattice.
    pub face: u32,
    /// c, the share of its fluid velocity known: [`SurfaceBlend::share`] (about θ/θ₁, below
    /// one) on a liquid–air face, 1 on a face between liquid cells, 0 on a face in air.
    pub share: f64,
    /// The weight of the fluid velocity in its value: its fluid weight w where a body
    /// covers it, 1 where none does.
    pub fluid: f64,
    /// Its open area before the bodies (the static weight) where a body covers it, 1 where
    /// none does.
    pub open: f64,
    /// Whether the projection updated it (its fluid velocity is the projected one; else the
    /// mean its neighbours gave it, see `correct_with_bodies`).
    pub projected: bool,
    /// Whether a body covers it in part.
    pub covered: bool,
    /// The liquid cell its θ is measured from ([`NONE`] off a liquid–air face).
    pub liquid: u32,
    /// The air cell its θ is measured to ([`NONE`] off a liquid–air face).
    pub air: u32,
    /// (∂c/∂φ_L of the liquid cell, of the air cell).
    pub gradient: [f64; 2],
}

impl SurfaceFace {
    /// The share it starts the layers with, m⁰.
    #[inline]
    pub(super) fn start_share(&self) -> f64 {
        1.0 - (1.0 - self.share) * self.fluid / self.open
    }

    /// Where it starts the layers, from its value `u` and fluid velocity `u_fluid`.
    #[inline]
    pub(super) fn start(&self, u: f64, u_fluid: f64) -> Start {
        let w = u - (1.0 - self.share) * self.fluid * u_fluid;
        Start { face: self.face as usize, m: self.start_share(), w }
    }
}

/// Per axis, the faces known in part, sorted by face.
pub type SurfaceFaces = [Vec<SurfaceFace>; 3];

/// The faces of `sys` known in part under `blend` (none when it is off): the liquid–air
/// faces (by `phi`, φ_L as the system was built from) whose share is below one, and the
/// faces `bodies` cover in part (combined weights `weights`, static ones `statics`) but
/// those between liquid cells.
pub fn surface_faces(
    sys: &PressureSystem,
    phi: &[f64],
    bodies: &[BodyFaces],
    weights: &FaceWeights,
    statics: &FaceWeights,
    blend: SurfaceBlend,
) -> SurfaceFaces {
    std::array::from_fn(|a| {
        if blend.theta <= 0.0 {
            return Vec::new();
        }
        let grid: &Grid = &sys.grid;
        let lat = grid.faces(a);
        let mut covered: Vec<u32> =
            bodies.iter().flat_map(|bf| bf.faces[a].iter().map(|&(f, _)| f as u32)).collect();
        covered.sort_unstable();
        covered.dedup();
        let part = |f: u32, is_covered: bool| {
            if is_covered {
                (weights.weight(a, f as usize), statics.weight(a, f as usize), true)
            } else {
                (1.0, 1.0, false)
            }
        };
        let projected = &sys.faces[a];
        // Both lists sorted by face: each chunk of the projected faces finds its place in
        // the covered ones once and walks them along, not a search a face
        // (docs/performance.md, "The smooth defaults").
        let mut out: Vec<SurfaceFace> = projected
            .par_chunks(CHUNK)
            .flat_map_iter(|chunk| {
                let mut at = covered.partition_point(|&c| c < chunk[0].face);
                let covered = &covered;
                chunk.iter().filter_map(move |pf| {
                    let (face, rm, rp) = (pf.face, pf.gradient.rm, pf.gradient.rp);
                    while at < covered.len() && covered[at] < face {
                        at += 1;
                    }
                    let is_covered = at < covered.len() && covered[at] == face;
                    let (share, liquid, air, gradient) = if (rm == NONE) != (rp == NONE) {
                        let (minus, plus) = grid.face_cells(a, lat.ijk(face as usize));
                        let (l, g) = if rm != NONE { (minus?, plus?) } else { (plus?, minus?) };
                        let (dl, da) = blend.share_gradient(phi[l], phi[g]);
                        (blend.share(phi[l], phi[g]), l as u32, g as u32, [dl, da])
                    } else {
                        (1.0, NONE, NONE, [0.0; 2])
                    };
                    let (fluid, open, covered) = part(face, is_covered);
                    let sf = SurfaceFace {
                        face,
                        share,
                        fluid,
                        open,
                        projected: true,
                        covered,
                        liquid,
                        air,
                        gradient,
                    };
                    (sf.start_share() < 1.0).then_some(sf)
                })
            })
            .collect();
        // The faces of air a body covers in part: their fluid part unknown.
        let before = out.len();
        for &f in &covered {
            let projected_face = projected.binary_search_by_key(&f, |pf| pf.face).is_ok();
            if projected_face || weights.closed(a, f as usize) {
                continue;
            }
            let (fluid, open, _) = part(f, true);
            out.push(SurfaceFace {
                face: f,
                share: 0.0,
                fluid,
                open,
                projected: false,
                covered: true,
                liquid: NONE,
                air: NONE,
                gradient: [0.0; 2],
            });
        }
        if out.len() > before {
            out.sort_unstable_by_key(|sf| sf.face);
        }
        out
    })
}

/// Where a face starts the layers: its share m⁰ and w⁰.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Start {
    pub face: usize,
    pub m: f64,
    pub w: f64,
}

/// One face's update in a layer: its share m before it and the sums z = Σ m, s = Σ w over
/// its lattice neighbours.
#[derive(Clone, Copy, Debug)]
pub(super) struct Update {
    face: usize,
    m: f64,
    z: f64,
    s: f64,
}

impl Update {
    /// (m after the layer, what the layer adds to w).
    #[inline]
    fn apply(&self) -> (f64, f64) {
        let k = 1.0 - self.m;
        if self.z >= 1.0 {
            (1.0, k * self.s / self.z)
        } else {
            (self.m + k * self.z, k * self.s)
        }
    }
}

/// The blended layers on `field` (one component, its known faces those of level 0 in `lay`,
/// `starts` those known in part, sorted), in place; with `trace`, each layer's updates.
pub(super) fn extrapolate_blended(
    field: &mut [f64],
    lay: &Layers,
    starts: &[Start],
    lat: &Lattice,
    mut trace: Option<&mut Vec<Vec<Update>>>,
) {
    let level = &lay.level;
    let mut m: Vec<f64> = level.par_iter().map(|&l| if l == 0 { 1.0 } else { 0.0 }).collect();
    field.par_iter_mut().zip(level.par_iter()).for_each(|(x, &l)| {
        if l != 0 {
            *x = 0.0;
        }
    });
    let mut partial: Vec<usize> = Vec::with_capacity(starts.len());
    for st in starts {
        (m[st.face], field[st.face]) = (st.m, st.w);
        partial.push(st.face);
    }
    for front in &lay.fronts {
        let set = merge(&partial, front);
        let (m_now, w_now) = (&m, &*field);
        let updates: Vec<Update> = set
            .par_iter()
            .with_min_len(CHUNK)
            .map(|&face| {
                let mut nb = [0usize; 6];
                let n = neighbours(lat, face, |_| true, &mut nb);
                let (z, s) =
                    nb[..n].iter().fold((0.0, 0.0), |(z, s), &x| (z + m_now[x], s + w_now[x]));
                Update { face, m: m_now[face], z, s }
            })
            .collect();
        partial.clear();
        for up in &updates {
            let (m_new, dw) = up.apply();
            m[up.face] = m_new;
            field[up.face] += dw;
            if m_new < 1.0 {
                partial.push(up.face);
            }
        }
        if let Some(t) = trace.as_deref_mut() {
            t.push(updates);
        }
    }
}

/// Two sorted lists of distinct faces merged, sorted.
fn merge(a: &[usize], b: &[usize]) -> Vec<usize> {
    let mut out = Vec::with_capacity(a.len() + b.len());
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        if a[i] < b[j] {
            out.push(a[i]);
            i += 1;
        } else {
            out.push(b[j]);
            j += 1;
        }
    }
    out.extend_from_slice(&a[i..]);
    out.extend_from_slice(&b[j..]);
    out
}

/// One update's transpose: ∂L/∂m of its face before the layer, and what it adds to ∂L/∂w
/// and ∂L/∂m of each of its n lattice neighbours (face, to w, to m).
type UpdateAdjoint = (f64, [(usize, f64, f64); 6], usize);

/// The transpose of [`extrapolate_blended`] from the field it started from (`input`, with
/// `starts`): `adj`, ∂L/∂(the extrapolated field), becomes ∂L/∂`input` in place on the
/// faces of level 0 (∂L/∂w⁰ on those of `starts`) and zero elsewhere; returns ∂L/∂m⁰ of
/// each start.
pub(super) fn extrapolate_blended_adjoint(
    adj: &mut [f64],
    input: &[f64],
    lay: &Layers,
    starts: &[Start],
    lat: &Lattice,
) -> Vec<f64> {
    let mut replay = input.to_vec();
    let mut trace = Vec::with_capacity(lay.fronts.len());
    extrapolate_blended(&mut replay, lay, starts, lat, Some(&mut trace));
    // Nothing flows back from a face never reached (zero whatever it read): no update reads
    // its adjoint, and the last pass zeroes it with every face not of level 0.
    let level = &lay.level;
    // ∂L/∂m, zero after the last layer (nothing reads the shares).
    let mut mbar = vec![0.0; adj.len()];
    for updates in trace.iter().rev() {
        // A layer reads the values before it only: every update's adjoint from the values
        // after it, then written.
        let (adj_now, mbar_now) = (&*adj, &mbar);
        let parts: Vec<UpdateAdjoint> = updates
            .par_iter()
            .with_min_len(CHUNK)
            .map(|up| {
                let (a, b) = (adj_now[up.face], mbar_now[up.face]);
                let k = 1.0 - up.m;
                // ∂w'/∂m, ∂m'/∂m, ∂w'/∂w_nb, ∂w'/∂m_nb, ∂m'/∂m_nb (∂w'/∂w = 1).
                let (wm, mm, wwn, wmn, mmn) = if up.z >= 1.0 {
                    let z = up.z;
                    (-up.s / z, 0.0, k / z, -k * up.s / (z * z), 0.0)
                } else {
                    (-up.s, 1.0 - up.z, k, 0.0, k)
                };
                let mut nb = [0usize; 6];
                let n = neighbours(lat, up.face, |_| true, &mut nb);
                let mut out = [(0usize, 0.0, 0.0); 6];
                for (o, &x) in out.iter_mut().zip(&nb[..n]) {
                    *o = (x, a * wwn, a * wmn + b * mmn);
                }
                (a * wm + b * mm, out, n)
            })
            .collect();
        for (up, (own, ..)) in updates.iter().zip(&parts) {
            mbar[up.face] = *own;
        }
        for (_, out, n) in &parts {
            for &(x, dw, dm) in &out[..*n] {
                adj[x] += dw;
                mbar[x] += dm;
            }
        }
    }
    adj.par_iter_mut().zip(level.par_iter()).for_each(|(a, &l)| {
        if l != 0 {
            *a = 0.0;
        }
    });
    starts.iter().map(|st| mbar[st.face]).collect()
}

#[cfg(test)]
mod tests {
    use super::super::extrapolate_fronts;
    use super::*;

    fn lattice() -> Lattice {
        Lattice { n: [7, 6, 5], off: [0.0; 3], dx: 1.0 }
    }

    /// The share of a liquid–air face's projected velocity against central differences in
    /// both φ, and smooth through θ₁: at θ = θ₁ = ½, which a freshly seeded flat surface
    /// puts on its faces, and at the ends of the rounding, its one-sided differences agree
    /// (the corner of min(1, θ/θ₁) had slopes 0 and 1/θ₁ there).
    #[test]
    fn the_share_matches_its_gradient_and_is_smooth_through_theta_one() {
        let blend = SurfaceBlend { theta: 0.5 };
        let h = 1e-7;
        for theta in [0.05, 0.2, 0.37, 0.45, 0.49, 0.5, 0.51, 0.55, 0.8] {
            // φ_l = −θ, φ_a = 1 − θ: the fraction θ.
            let (l, a) = (-theta, 1.0 - theta);
            let (dl, da) = blend.share_gradient(l, a);
            let fd_l = (blend.share(l + h, a) - blend.share(l - h, a)) / (2.0 * h);
            let fd_a = (blend.share(l, a + h) - blend.share(l, a - h)) / (2.0 * h);
            assert!((dl - fd_l).abs() < 1e-6, "θ {theta}: ∂c/∂φ_l {dl} against {fd_l}");
            assert!((da - fd_a).abs() < 1e-6, "θ {theta}: ∂c/∂φ_a {da} against {fd_a}");
            let c = blend.share(l, a);
            let right = (blend.share(l, a + h) - c) / h;
            let left = (c - blend.share(l, a - h)) / h;
            assert!((right - left).abs() < 1e-5, "θ {theta}: slopes {left} and {right}");
        }
        // θ/θ₁ below the rounding, 1 above it, 1 − 3·ROUNDING/16 at θ₁.
        assert!((blend.share(-0.1, 0.9) - 0.2).abs() < 1e-12);
        assert_eq!(blend.share(-0.6, 0.4), 1.0);
        assert!((blend.share(-0.5, 0.5) - (1.0 - 3.0 * ROUNDING / 16.0)).abs() < 1e-12);
    }

    /// A mask with scattered known faces and a block of them (fronts that meet), values, and
    /// the known faces at the block's edge known in part.
    fn case(lat: &Lattice) -> (Vec<u8>, Vec<f64>, Vec<Start>) {
        let valid: Vec<u8> = (0..lat.len())
            .map(|f| {
                let [i, j, k] = lat.ijk(f);
                u8::from((f * 37) % 11 == 0 || (i + j < 4 && k > 1))
            })
            .collect();
        let value: Vec<f64> =
            (0..lat.len()).map(|f| ((f * 7919) % 97) as f64 / 48.0 - 1.0).collect();
        let starts = (0..lat.len())
            .filter(|&f| {
                let [i, j, k] = lat.ijk(f);
                valid[f] != 0 && (i + j == 3 || (f * 37) % 11 == 0) && k != 3
            })
            .enumerate()
            .map(|(n, face)| {
                // Irrational steps: no two shares sum to a whole number (the layers' kink
                // at z = 1).
                let m = 0.03 + 0.9 * (n as f64 * 0.618_033_988_7).fract();
                Start { face, m, w: m * value[face] }
            })
            .collect();
        (valid, value, starts)
    }

    fn blended(value: &[f64], lay: &Layers, starts: &[Start], lat: &Lattice) -> Vec<f64> {
        let mut out = value.to_vec();
        extrapolate_blended(&mut out, lay, starts, lat, None);
        out
    }

    /// Without faces known in part, the yes/no rule to the bit.
    #[test]
    fn whole_shares_are_the_yes_no_rule() {
        let lat = lattice();
        let (valid, value, _) = case(&lat);
        let lay = Layers::new(&valid, &lat, 3);
        let mut old = value.clone();
        extrapolate_fronts(&mut old, &lay, &lat);
        let never = |l: &u8| *l == super::super::NEVER;
        old.iter_mut().zip(&lay.level).filter(|(_, l)| never(l)).for_each(|(x, _)| *x = 0.0);
        let new = blended(&value, &lay, &[], &lat);
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<u64>>();
        assert_eq!(bits(&new), bits(&old));
    }

    /// A share going to zero is the face not known at all: the largest difference from the
    /// layers without the face (which reach one layer less far from it) shrinks with the
    /// share, a thousandfold from 1e-9 to 1e-12.
    #[test]
    fn a_share_near_zero_is_the_face_unknown() {
        let lat = lattice();
        let (valid, value, starts) = case(&lat);
        let f = starts[3].face;
        let mut valid_without = valid.clone();
        valid_without[f] = 0;
        let rest: Vec<Start> = starts.iter().copied().filter(|s| s.face != f).collect();
        let without = blended(&value, &Layers::new(&valid_without, &lat, 3), &rest, &lat);
        let gap = |m: f64| {
            let mut faint = starts.clone();
            faint[3] = Start { face: f, m, w: m * value[f] };
            let with = blended(&value, &Layers::new(&valid, &lat, 3), &faint, &lat);
            with.iter().zip(&without).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max)
        };
        let (near, nearer) = (gap(1e-9), gap(1e-12));
        assert!(near < 1e-7 && nearer < 2e-3 * near, "{near}, {nearer}");
        let whole = blended(&value, &Layers::new(&valid, &lat, 3), &starts, &lat);
        let moved = whole.iter().zip(&without).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        assert!(moved > 0.1, "the face's share matters: {moved}");
    }

    /// The transpose against central differences of the layers in each start's share, and
    /// the dot-product test in the values (the field and the starts' w⁰).
    #[test]
    fn transpose_matches_central_differences() {
        let lat = lattice();
        let (valid, value, starts) = case(&lat);
        assert!(starts.len() > 10, "{} faces known in part", starts.len());
        let lay = Layers::new(&valid, &lat, 3);
        let weight: Vec<f64> = (0..lat.len()).map(|f| ((f * 31) % 17) as f64 / 8.0 - 1.0).collect();
        let loss = |v: &[f64], s: &[Start]| -> f64 {
            blended(v, &lay, s, &lat).iter().zip(&weight).map(|(a, b)| a * b).sum()
        };
        let mut adj = weight.clone();
        let mbar = extrapolate_blended_adjoint(&mut adj, &value, &lay, &starts, &lat);
        // Linear in the values and the starts' w⁰ for fixed shares: the dot-product test.
        let lin = loss(&value, &starts);
        let mut input = value.clone();
        starts.iter().for_each(|st| input[st.face] = st.w);
        let dot: f64 = adj.iter().zip(&input).map(|(a, b)| a * b).sum();
        assert!((lin - dot).abs() <= 1e-12 * lin.abs().max(1.0), "{lin} vs {dot}");
        let h = 1e-6;
        let mut worst: f64 = 0.0;
        for (i, st) in starts.iter().enumerate() {
            let at = |d: f64| {
                let mut s = starts.clone();
                s[i].m = st.m + d;
                loss(&value, &s)
            };
            let fd = (at(h) - at(-h)) / (2.0 * h);
            worst = worst.max((fd - mbar[i]).abs() / fd.abs().max(1.0));
        }
        assert!(worst < 1e-7, "shares: {worst}");
        assert!(mbar.iter().filter(|c| c.abs() > 1e-3).count() > starts.len() / 2);
    }
}
