//! Velocity correction (stage `correct_velocity`): extrapolate valid velocities into air, then give faces
//! inside solids the solid's velocity.
//!
//! Extrapolation runs a fixed number of Jacobi layers: each invalid face with at least one
//! valid neighbour (along the 6 lattice directions of its own component) takes their mean
//! and becomes valid for the next layer. Faces still invalid after the last layer are set to
//! zero. For fixed masks this is a fixed linear map C, so its transpose exists for the
//! backward pass (paper, eq. 10).

use crate::geometry::body::RigidBody;
use crate::geometry::fractions::{BodyFaces, DualFaces};
use crate::geometry::grid::{Grid, Lattice, Mac};
use crate::geometry::weights::FaceWeights;
use crate::math::par::{for_each_keyed_mut, MIN_LEN};
use crate::math::Vec3;
use rayon::prelude::*;

mod blend;
use blend::Start;
pub use blend::{surface_faces, SurfaceBlend, SurfaceFace, SurfaceFaces};

/// Smallest piece of a face list handed to rayon.
const CHUNK: usize = 4096;

/// The neighbours of sample `idx` along the 6 lattice directions, in the order −x, +x, −y,
/// +y, −z, +z, that `keep` accepts (at most 6).
#[inline]
fn neighbours(
    lat: &Lattice,
    idx: usize,
    keep: impl Fn(usize) -> bool,
    out: &mut [usize; 6],
) -> usize {
    let p = lat.ijk(idx);
    let mut n = 0;
    for a in 0..3 {
        for side in 0..2 {
            match lat.neighbour(idx, p, a, side) {
                Some(m) if keep(m) => {
                    out[n] = m;
                    n += 1;
                }
                _ => {}
            }
        }
    }
    n
}

/// Marks "never valid" in [`Layers::level`].
const NEVER: u8 = u8::MAX;

/// Which faces each extrapolation layer sets: a face set in layer l is a never-set face with
/// a neighbour set in layer l − 1 (or valid, for l = 0). Each front is found by one pass over
/// the lattice's levels, a z-slab at a time (whole-row tests the compiler vectorises), in
/// increasing index order.
struct Layers {
    /// 0 for a valid face, l + 1 for a face set in layer l, [`NEVER`] otherwise.
    level: Vec<u8>,
    /// Faces set in each layer, in increasing index order.
    fronts: Vec<Vec<usize>>,
}

impl Layers {
    fn new(valid0: &[u8], lat: &Lattice, layers: usize) -> Layers {
        assert!(layers < NEVER as usize - 1, "at most 253 extrapolation layers");
        let mut level: Vec<u8> = valid0
            .par_iter()
            .with_min_len(MIN_LEN)
            .map(|&v| if v != 0 { 0 } else { NEVER })
            .collect();
        let mut fronts: Vec<Vec<usize>> = Vec::with_capacity(layers);
        for l in 0..layers {
            // The first front by a pass over the lattice; each next one among the neighbours
            // of the last (the faces of level l), which is all it can be next to.
            let front = match fronts.last() {
                None => {
                    let front = next_to(&level, lat, |_, v| v == l as u8, |v| v == NEVER);
                    for_each_keyed_mut(&mut level, &front, |&m| m, |_, _, x| *x = l as u8 + 1);
                    front
                }
                Some(last) => {
                    mark_neighbours(last, lat, &mut level, NEVER, l as u8 + 1);
                    equal_to(&level, l as u8 + 1)
                }
            };
            fronts.push(front);
        }
        Layers { level, fronts }
    }

    /// Per layer l, the faces known before it next to a face it set, in increasing index
    /// order: those of level l itself with a neighbour of level l + 1 (a face of level
    /// v < l has none, as the fronts grow one face a layer: its neighbours of higher level
    /// were set in layer v, and are of level v + 1), found among the neighbours of the
    /// layer's front.
    fn targets(&self, lat: &Lattice) -> Vec<Vec<usize>> {
        // Marked in a copy of the levels (no level is NEVER − 1, see `Layers::new`): a target
        // of layer l goes from l to the mark while it is found, and back.
        const MARK: u8 = NEVER - 1;
        let mut marks = self.level.clone();
        (0..self.fronts.len())
            .map(|l| {
                mark_neighbours(&self.fronts[l], lat, &mut marks, l as u8, MARK);
                let found = equal_to(&marks, MARK);
                found.iter().for_each(|&m| marks[m] = l as u8);
                found
            })
            .collect()
    }

    /// Valid before layer `l`.
    #[inline]
    fn known_before(&self, idx: usize, l: usize) -> bool {
        (self.level[idx] as usize) <= l
    }
}

/// The samples whose own level `own` accepts with a lattice neighbour whose level `nb`
/// accepts (as `nb(own level, neighbour level)`), in increasing index order.
fn next_to(
    level: &[u8],
    lat: &Lattice,
    nb: impl Fn(u8, u8) -> bool + Sync,
    own: impl Fn(u8) -> bool + Sync,
) -> Vec<usize> {
    let [n0, n1, n2] = lat.n;
    let slab = lat.slab();
    let mark = |hit: &mut [bool], mine: &[u8], src: &[u8]| {
        hit.iter_mut().zip(mine).zip(src).for_each(|((h, &m), &v)| *h |= nb(m, v));
    };
    level
        .par_chunks(slab)
        .enumerate()
        .map(|(k, lv)| {
            let mut hit = vec![false; slab];
            for j in 0..n1 {
                let (row, h) = (&lv[j * n0..][..n0], &mut hit[j * n0..][..n0]);
                if n0 > 1 {
                    mark(&mut h[1..], &row[1..], &row[..n0 - 1]);
                    mark(&mut h[..n0 - 1], &row[..n0 - 1], &row[1..]);
                }
            }
            if n1 > 1 {
                mark(&mut hit[n0..], &lv[n0..], &lv[..slab - n0]);
                mark(&mut hit[..slab - n0], &lv[..slab - n0], &lv[n0..]);
            }
            if k > 0 {
                mark(&mut hit, lv, &level[(k - 1) * slab..][..slab]);
            }
            if k + 1 < n2 {
                mark(&mut hit, lv, &level[(k + 1) * slab..][..slab]);
            }
            // A plain loop: as an iterator chain flattened across the slabs, the hand-over of
            // each sample cost more than its test.
            let mut found = Vec::new();
            for (i, (&h, &v)) in hit.iter().zip(lv).enumerate() {
                if h && own(v) {
                    found.push(k * slab + i);
                }
            }
            found
        })
        .collect::<Vec<Vec<usize>>>()
        .concat()
}

/// Sets `level` to `to` at the lattice neighbours of the samples `of` whose level is `from`:
/// the faces of a front and their neighbours only, not a pass over the lattice.
fn mark_neighbours(of: &[usize], lat: &Lattice, level: &mut [u8], from: u8, to: u8) {
    for &idx in of {
        let mut nb = [0usize; 6];
        let n = neighbours(lat, idx, |m| level[m] == from, &mut nb);
        for &m in &nb[..n] {
            level[m] = to;
        }
    }
}

/// The samples whose level is `v`, in increasing index order, in parallel over fixed chunks.
fn equal_to(level: &[u8], v: u8) -> Vec<usize> {
    level
        .par_chunks(MIN_LEN)
        .enumerate()
        .map(|(c, part)| {
            let mut found = Vec::new();
            for (i, &x) in part.iter().enumerate() {
                if x == v {
                    found.push(c * MIN_LEN + i);
                }
            }
            found
        })
        .collect::<Vec<Vec<usize>>>()
        .concat()
}

/// Extrapolates one component over `layers` layers and zeroes what stays invalid.
/// `valid` is updated to the final mask of extrapolated-or-valid samples.
pub fn extrapolate(field: &mut [f64], valid: &mut [u8], lat: &Lattice, layers: usize) {
    let lay = Layers::new(valid, lat, layers);
    extrapolate_layered(field, &lay, lat);
    valid.par_iter_mut().zip(lay.level.par_iter()).with_min_len(MIN_LEN).for_each(|(v, &lev)| {
        if lev != NEVER {
            *v = 1;
        }
    });
}

/// One layer of [`extrapolate`], then zero on the faces `closed` holds, for a field that is
/// zero on every face but its valid ones (`valid`, none of which `closed` holds), whose
/// indices `sources` lists in increasing order (as `key` reads an entry): the same bits as
/// `extrapolate(field, valid, lat, 1)` followed by zeroing the faces `closed` holds, with
/// only the sources' neighbours visited instead of passes over the lattice. A z-slab a task;
/// each open face of the front is written once, by its first valid neighbour in the order
/// of `neighbours` (a closed one is zero already).
pub fn extrapolate_one_layer<E: Sync>(
    field: &mut [f64],
    valid: &[u8],
    sources: &[E],
    key: impl Fn(&E) -> usize + Sync,
    lat: &Lattice,
    closed: impl Fn(usize) -> bool + Sync,
) {
    let slab = lat.slab().max(1);
    let slabs = field.len().div_ceil(slab);
    // Each slab's front, its faces' values computed from the sources (read only), then
    // written a slab a task.
    let src: &[f64] = field;
    let fronts: Vec<Vec<(usize, f64)>> = (0..slabs)
        .into_par_iter()
        .with_min_len(crate::math::par::min_pieces(slab))
        .map(|k| {
            let (first, last) = (k * slab, (k + 1) * slab);
            let at = |lo: usize| sources.partition_point(|e| key(e) < lo);
            let (below, from, to, above) =
                (at(first.saturating_sub(slab)), at(first), at(last), at(last + slab));
            let mut front = Vec::new();
            // Face m of the slab next to source p, not valid: set from its valid neighbours, by
            // the first, unless it is closed (zero already).
            let mut visit = |p: usize, m: usize| {
                if closed(m) {
                    return;
                }
                let mut nb = [0usize; 6];
                let n = neighbours(lat, m, |x| valid[x] != 0, &mut nb);
                if nb[0] == p {
                    let mean = nb[..n].iter().map(|&x| src[x]).sum::<f64>() / n as f64;
                    front.push((m - first, mean));
                }
            };
            // The sources of the slab below and above reach it along z only.
            for e in &sources[below..from] {
                let p = key(e);
                if valid[p + slab] == 0 {
                    visit(p, p + slab);
                }
            }
            for e in &sources[from..to] {
                let p = key(e);
                let ijk = lat.ijk(p);
                for a in 0..2 {
                    for side in 0..2 {
                        match lat.neighbour(p, ijk, a, side) {
                            Some(m) if valid[m] == 0 => visit(p, m),
                            _ => {}
                        }
                    }
                }
            }
            for e in &sources[to..above] {
                let p = key(e);
                if valid[p - slab] == 0 {
                    visit(p, p - slab);
                }
            }
            front
        })
        .collect();
    field
        .par_chunks_mut(slab)
        .zip(fronts)
        .with_min_len(crate::math::par::min_pieces(slab))
        .for_each(|(part, front)| front.into_iter().for_each(|(m, v)| part[m] = v));
}

/// [`extrapolate_one_layer`] with the liquid–air faces `surface` (sorted by face, none a
/// body covers) known in part, as [`SurfaceBlend`] weighs them: each starts with its share
/// c of its value, and the layer updates them and the faces it reaches from the shares and
/// values of their neighbours (see `blend.rs`); then zero on the faces `closed` holds. With
/// every share 1 (or none given) it is [`extrapolate_one_layer`] to the bit.
pub fn extrapolate_one_layer_blended(
    field: &mut [f64],
    valid: &[u8],
    surface: &[SurfaceFace],
    lat: &Lattice,
    closed: impl Fn(usize) -> bool + Sync,
) {
    let lay = Layers::new(valid, lat, 1);
    let starts = fluid_starts(surface, field);
    blend::extrapolate_blended(field, &lay, &starts, lat, None);
    zero_closed_layer(field, &lay, closed);
}

/// The transpose of [`extrapolate_one_layer_blended`] from the field it started from
/// (`input`): `adj`, ∂L/∂(the field after it), becomes ∂L/∂`input` on the valid faces and
/// zero elsewhere; returns ∂L/∂c of each face of `surface`.
pub fn extrapolate_one_layer_blended_adjoint(
    adj: &mut [f64],
    input: &[f64],
    valid: &[u8],
    surface: &[SurfaceFace],
    lat: &Lattice,
    closed: impl Fn(usize) -> bool + Sync,
) -> Vec<f64> {
    let lay = Layers::new(valid, lat, 1);
    zero_closed_layer(adj, &lay, closed);
    let starts = fluid_starts(surface, input);
    let mbar = blend::extrapolate_blended_adjoint(adj, input, &lay, &starts, lat);
    // w⁰ = c·u and m⁰ = c on a face a body does not cover: ∂/∂u = c·w̄, ∂/∂c = u·w̄ + m̄.
    surface
        .iter()
        .zip(mbar)
        .map(|(sf, m_bar)| {
            let f = sf.face as usize;
            let w_bar = adj[f];
            adj[f] = sf.share * w_bar;
            input[f] * w_bar + m_bar
        })
        .collect()
}

/// Where the faces `surface` (none a body covers: their value is their fluid velocity)
/// start the layers, from `field`.
fn fluid_starts(surface: &[SurfaceFace], field: &[f64]) -> Vec<Start> {
    surface.iter().map(|sf| sf.start(field[sf.face as usize], field[sf.face as usize])).collect()
}

/// Zero on the faces of the first layer of `lay` that `closed` holds (none of the valid
/// faces is closed).
fn zero_closed_layer(field: &mut [f64], lay: &Layers, closed: impl Fn(usize) -> bool + Sync) {
    for &f in &lay.fronts[0] {
        if closed(f) {
            field[f] = 0.0;
        }
    }
}

/// [`extrapolate`] with its layers found (`lay`), the mask left as it is.
fn extrapolate_layered(field: &mut [f64], lay: &Layers, lat: &Lattice) {
    extrapolate_fronts(field, lay, lat);
    field.par_iter_mut().zip(lay.level.par_iter()).with_min_len(MIN_LEN).for_each(|(f, &lev)| {
        if lev == NEVER {
            *f = 0.0;
        }
    });
}

/// [`extrapolate_layered`] without zeroing what stays invalid (the faces `lay` leaves at
/// level [`NEVER`]): the layers' values only.
fn extrapolate_fronts(field: &mut [f64], lay: &Layers, lat: &Lattice) {
    for (l, front) in lay.fronts.iter().enumerate() {
        // A face of this front reads only faces known before the layer, never another face
        // of the front: compute them all, then write.
        let values: Vec<(usize, f64)> = front
            .par_iter()
            .with_min_len(CHUNK)
            .map(|&idx| {
                let mut nb = [0usize; 6];
                let n = neighbours(lat, idx, |m| lay.known_before(m, l), &mut nb);
                (idx, nb[..n].iter().map(|&m| field[m]).sum::<f64>() / n as f64)
            })
            .collect();
        for_each_keyed_mut(field, &values, |v| v.0, |_, v, x| *x = v.1);
    }
}

/// Extrapolates all three components and then sets every face `weights` closes (weight 0:
/// static solid or tank wall) to the solid's velocity, zero.
pub fn correct_velocity(
    u: &mut Mac,
    valid: &mut [Vec<u8>; 3],
    weights: &FaceWeights,
    grid: &Grid,
    layers: usize,
) {
    for a in 0..3 {
        extrapolate(&mut u.c[a], &mut valid[a], &grid.faces(a), layers);
        weights.zero_closed(a, &mut u.c[a]);
    }
}

/// Transpose of [`extrapolate`] for the projection's mask `valid0`: takes the adjoint of
/// the extrapolated field and returns (in place) the adjoint of the field before it.
pub fn extrapolate_adjoint(adj: &mut [f64], valid0: &[u8], lat: &Lattice, layers: usize) {
    extrapolate_adjoint_planned(adj, &AxisPlan::new(valid0, lat, layers), lat);
}

/// The layers of one component's extrapolation from its mask, and the faces each layer read
/// (its [`Layers::targets`]): all its transpose reads but the adjoint itself.
struct AxisPlan {
    lay: Layers,
    targets: Vec<Vec<usize>>,
}

impl AxisPlan {
    fn new(valid0: &[u8], lat: &Lattice, layers: usize) -> AxisPlan {
        AxisPlan::of(Layers::new(valid0, lat, layers), lat)
    }

    /// The plan of layers `lay` already found.
    fn of(lay: Layers, lat: &Lattice) -> AxisPlan {
        let targets = lay.targets(lat);
        AxisPlan { lay, targets }
    }
}

/// [`extrapolate_adjoint`] with its layers found.
fn extrapolate_adjoint_planned(adj: &mut [f64], plan: &AxisPlan, lat: &Lattice) {
    let AxisPlan { lay, targets } = plan;
    // Faces left invalid were set to zero: nothing flows back from them.
    adj.par_iter_mut().zip(lay.level.par_iter()).with_min_len(MIN_LEN).for_each(|(a, &lev)| {
        if lev == NEVER {
            *a = 0.0;
        }
    });
    for (l, front) in lay.fronts.iter().enumerate().rev() {
        // A face of the front was set to the mean of its n neighbours known before the
        // layer: each of them gets adj/n of it back, gathered per neighbour (in parallel,
        // each sum in the order of the directions), then the front's own values are spent.
        let known = |m: usize| lay.known_before(m, l);
        let share = |idx: usize| {
            let mut nb = [0usize; 6];
            adj[idx] / neighbours(lat, idx, known, &mut nb) as f64
        };
        // The faces known before the layer next to one set in it, in index order.
        let targets = &targets[l];
        let set_in_layer = |m: usize| lay.level[m] as usize == l + 1;
        let adds: Vec<(usize, f64)> = targets
            .par_iter()
            .with_min_len(CHUNK)
            .map(|&m| {
                let mut nb = [0usize; 6];
                let n = neighbours(lat, m, set_in_layer, &mut nb);
                (m, nb[..n].iter().map(|&idx| share(idx)).sum())
            })
            .collect();
        for_each_keyed_mut(adj, front, |&i| i, |_, _, a| *a = 0.0);
        for_each_keyed_mut(adj, &adds, |p| p.0, |_, p, a| *a += p.1);
    }
}

/// Transpose of [`correct_velocity`] (without the rigid faces, which the caller handles
/// first): zero on closed faces, then the extrapolation's transpose.
pub fn correct_velocity_adjoint(
    adj: &mut Mac,
    valid0: &[Vec<u8>; 3],
    weights: &FaceWeights,
    grid: &Grid,
    layers: usize,
) {
    for a in 0..3 {
        weights.zero_closed(a, &mut adj.c[a]);
        extrapolate_adjoint(&mut adj.c[a], &valid0[a], &grid.faces(a), layers);
    }
}

/// The faces bodies cover in part that the projection did not update (air on both sides),
/// per axis, sorted: (face, the fluid velocity there before the bodies' part was mixed in,
/// the mean of its lattice neighbours the projection updated or a body closes). The backward
/// pass reads those values for ∂u/∂β; the tape keeps them.
pub type AirBodyFaces = [Vec<(u32, f64)>; 3];

/// What the velocity correction reads of a step besides the field: the bodies (with their
/// velocities after the solve), the faces each covers, the face weights with the bodies and
/// without them (the static solids and walls), and the grid.
#[derive(Clone, Copy)]
pub struct Correction<'a> {
    /// The bodies.
    pub bodies: &'a [RigidBody],
    /// The faces each body covers, with their fractions β.
    pub faces: &'a [BodyFaces],
    /// The combined face weights.
    pub weights: &'a FaceWeights,
    /// The static face weights.
    pub static_weights: &'a FaceWeights,
    /// The grid.
    pub grid: &'a Grid,
}

/// The velocity correction with bodies, on `u` after the pressure update
/// (`projected`: the faces the update acted on):
///
/// 1. a face a body closes (combined weight `w` = 0) takes that body's rigid velocity
///    e·(v + ω × (p_f − x)) (the last body wins a face two close); a projected face bodies
///    cover in part stores the mixture w·u + Σ_b β_b·u_b, which keeps every liquid cell's
///    flux (fluid and body together) at zero;
/// 2. a face bodies cover in part that the projection did not update (air on both sides)
///    takes the same mixture with, for its fluid velocity, the mean of its lattice
///    neighbours that step 1 set (projected or closed; zero if none);
/// 3. with every face a body covers and every projected face known, extrapolation into air
///    and zero in static solids and walls ([`correct_velocity`]); the faces of `surface`
///    (`solver.surface_blend`, empty for the yes/no rule) known only in part (see
///    [`SurfaceBlend`]).
///
/// The mixture is continuous as w → 0 and as β → 0 (a nearly closed face otherwise kept the
/// full pressure update of its sliver of fluid and jumped to the body's velocity when it
/// closed), and whether a face is a source of the extrapolation does not change as a body
/// closes it. Step 2 is what keeps still water still around a body crossing the surface: such
/// a face used to keep its advected velocity with gravity added, never projected, which grew
/// by g·Δt a step and was carried into the liquid by the extrapolation and the next
/// advection (issue 33).
///
/// `layered`: step 3's layers found beforehand (for `projected`, `faces` and `layers`,
/// [`ExtrapolationLayers::new`], for example beside the solve), or None to find them here;
/// the same bits either way.
pub fn correct_with_bodies(
    u: &mut Mac,
    projected: &[Vec<u8>; 3],
    layered: Option<&ExtrapolationLayers>,
    surface: &SurfaceFaces,
    step: Correction,
    layers: usize,
) -> AirBodyFaces {
    let Correction { bodies, faces, static_weights, grid, .. } = step;
    let found;
    let lay = match layered {
        Some(lay) => lay,
        None => {
            found = ExtrapolationLayers::new(projected, faces, grid, layers);
            &found
        }
    };
    let spins = liquid_spins(bodies);
    // Each part reads and writes one component of `u` only: the three run side by side.
    let component = |a: usize, ua: &mut Vec<f64>| -> Vec<(u32, f64)> {
        let (air, fluid) = sources_and_fluid(a, ua, projected, step, &spins, &surface[a]);
        // As correct_velocity: what stays invalid and the closed faces zeroed in one pass.
        let (axis, lat) = (&lay.axes[a], grid.faces(a));
        if surface[a].is_empty() {
            extrapolate_fronts(ua, axis, &lat);
        } else {
            let starts = starts(&surface[a], ua, &fluid);
            blend::extrapolate_blended(ua, axis, &starts, &lat, None);
        }
        static_weights.zero_closed_or(a, ua, &axis.level, NEVER);
        air
    };
    let [ux, uy, uz] = &mut u.c;
    let (ax, (ay, az)) =
        rayon::join(|| component(0, ux), || rayon::join(|| component(1, uy), || component(2, uz)));
    [ax, ay, az]
}

/// [`body_sources`] on component `a` (`ua`), and the fluid velocity of each face of
/// `surface` (that axis's faces known in part): what the projection gave it, read before the
/// bodies' velocities are mixed in, or on a face of air the mean step 2 gives it.
fn sources_and_fluid(
    a: usize,
    ua: &mut [f64],
    projected: &[Vec<u8>; 3],
    step: Correction,
    spins: &[Vec3],
    surface: &[SurfaceFace],
) -> (Vec<(u32, f64)>, Vec<f64>) {
    let before: Vec<f64> = surface.iter().map(|sf| ua[sf.face as usize]).collect();
    let air = body_sources(a, ua, projected, step, spins);
    let fluid = surface
        .iter()
        .zip(before)
        .map(|(sf, b)| {
            if sf.projected {
                b
            } else {
                air.binary_search_by_key(&sf.face, |e| e.0).map_or(0.0, |i| air[i].1)
            }
        })
        .collect();
    (air, fluid)
}

/// Where the faces of `surface` start the blended layers, from the field after the bodies'
/// velocities were mixed in (`u`) and their fluid velocities.
fn starts(surface: &[SurfaceFace], u: &[f64], fluid: &[f64]) -> Vec<Start> {
    surface.iter().zip(fluid).map(|(sf, &v)| sf.start(u[sf.face as usize], v)).collect()
}

/// Each body's angular velocity as the liquid sees it (`RigidBody::liquid_velocity_at`, its
/// spin found once, not at every face).
fn liquid_spins(bodies: &[RigidBody]) -> Vec<Vec3> {
    bodies.iter().map(|b| b.spin().project(b.w)).collect()
}

/// Steps 1 and 2 of [`correct_with_bodies`] on component `a` of the field (`ua`): the
/// bodies' velocities mixed into the faces they cover, the air faces among them given their
/// neighbours' mean first; returns those (`spins`: [`liquid_spins`]).
fn body_sources(
    a: usize,
    ua: &mut [f64],
    projected: &[Vec<u8>; 3],
    step: Correction,
    spins: &[Vec3],
) -> Vec<(u32, f64)> {
    let Correction { bodies, faces, weights, grid, .. } = step;
    let set = |f: usize| projected[a][f] != 0 || weights.closed(a, f);
    let mix = |ua: &mut [f64], on: &dyn Fn(usize) -> bool| {
        mix_body_velocities(a, ua, bodies, spins, faces, weights, grid, on)
    };
    mix(ua, &set);
    let lat = grid.faces(a);
    let air: Vec<(u32, f64)> = air_faces(faces, a, |f| !set(f))
        .into_iter()
        .map(|f| {
            let mut nb = [0usize; 6];
            let n = neighbours(&lat, f, set, &mut nb);
            let mean =
                if n == 0 { 0.0 } else { nb[..n].iter().map(|&m| ua[m]).sum::<f64>() / n as f64 };
            (f as u32, mean)
        })
        .collect();
    for &(f, e) in &air {
        ua[f as usize] = e;
    }
    mix(ua, &|f| !set(f));
    air
}

/// The layers of [`correct_with_bodies`]'s extrapolation, per axis, from the faces the
/// projection updated and those the bodies cover: masks only, so the forward step finds
/// them beside its pressure solve.
pub struct ExtrapolationLayers {
    axes: Vec<Layers>,
}

impl ExtrapolationLayers {
    /// The layers for the faces the projection updated (`projected`) and those `faces`
    /// cover, with `layers` extrapolation layers.
    pub fn new(
        projected: &[Vec<u8>; 3],
        faces: &[BodyFaces],
        grid: &Grid,
        layers: usize,
    ) -> ExtrapolationLayers {
        let mut valid = projected.clone();
        mark_body_faces(&mut valid, faces);
        let axes = (0..3).map(|a| Layers::new(&valid[a], &grid.faces(a), layers)).collect();
        ExtrapolationLayers { axes }
    }
}

/// The faces of `axis` some body covers that `keep` accepts, sorted, each once.
fn air_faces(faces: &[BodyFaces], axis: usize, keep: impl Fn(usize) -> bool) -> Vec<usize> {
    let mut out: Vec<usize> = faces
        .iter()
        .flat_map(|bf| bf.faces[axis].iter().map(|&(f, _)| f))
        .filter(|&f| keep(f))
        .collect();
    out.sort_unstable();
    out.dedup();
    out
}

/// Marks every face a body covers as known: the extrapolation reads the bodies' velocities
/// there and never overwrites them. Whether a face next to a moving body is a source then
/// does not depend on its fluid weight reaching exactly 0, which made the step jump.
fn mark_body_faces(valid: &mut [Vec<u8>; 3], faces: &[BodyFaces]) {
    for bf in faces {
        for a in 0..3 {
            for &(f, _) in &bf.faces[a] {
                valid[a][f] = 1;
            }
        }
    }
}

/// The bodies' part of the faces of `axis` that `on(face)` accepts, in `u`, that axis's
/// component: a closed face takes the rigid velocity, a face covered in part
/// w·u + Σ_b β_b·u_b (`spins`: each body's angular velocity as the liquid sees it,
/// `RigidBody::spin` projected).
#[allow(clippy::too_many_arguments)]
fn mix_body_velocities(
    axis: usize,
    u: &mut [f64],
    bodies: &[RigidBody],
    spins: &[Vec3],
    faces: &[BodyFaces],
    weights: &FaceWeights,
    grid: &Grid,
    on: &dyn Fn(usize) -> bool,
) {
    let mut touched = vec![false; grid.faces(axis).len()];
    let lat = grid.faces(axis);
    for ((b, bf), &w_liquid) in bodies.iter().zip(faces).zip(spins) {
        for &(f, beta) in bf.faces[axis].iter().filter(|&&(f, _)| on(f)) {
            let [i, j, k] = lat.ijk(f);
            let p = lat.position(i, j, k);
            let ub = crate::math::comp(b.v + w_liquid.cross(p - b.x), axis);
            let w = weights.weight(axis, f);
            if w <= 0.0 {
                u[f] = ub;
            } else {
                if !touched[f] {
                    u[f] *= w;
                    touched[f] = true;
                }
                u[f] += beta * ub;
            }
        }
    }
}

/// What [`correct_with_bodies_adjoint`] returns for one body.
#[derive(Clone, Debug, Default)]
pub struct BodyVelocityAdjoint {
    /// ∂L/∂[v; ω].
    pub vel: [f64; 6],
    /// ∂L/∂x through the torque arms p_f − x.
    pub x: crate::math::Vec3,
    /// ∂L/∂θ (world rotation) through the symmetry axis the liquid's share of the spin is
    /// taken across (see [`RigidBody::spin`]).
    pub q: crate::math::Vec3,
    /// (axis, face, ∂L/∂β_f) on the faces the body covers in part: `(u_b − u)·ū`.
    pub dbeta: Vec<(usize, usize, f64)>,
}

impl BodyVelocityAdjoint {
    /// ∂L/∂[δx; δθ] of the body's pose: through the torque arms, the spin's axis, and the
    /// fractions β of the faces it covers in part (`dual`, its dual fractions).
    pub fn pose(&self, dual: &DualFaces) -> crate::math::Twist {
        let mut out = crate::math::twist(self.x, self.q);
        let lookup: std::collections::HashMap<(usize, usize), [f64; 6]> =
            (0..3).flat_map(|a| dual[a].iter().map(move |(f, b)| ((a, *f), b.d))).collect();
        for &(a, f, c) in &self.dbeta {
            if let Some(d) = lookup.get(&(a, f)) {
                for k in 0..6 {
                    out[k] += c * d[k];
                }
            }
        }
        out
    }

    fn add(&mut self, o: BodyVelocityAdjoint) {
        for d in 0..6 {
            self.vel[d] += o.vel[d];
        }
        self.x += o.x;
        self.q += o.q;
        self.dbeta.extend(o.dbeta);
    }
}

/// Adjoint of [`correct_with_bodies`], in place on `ubar` (the adjoint of the corrected
/// field becomes that of the field after the pressure update): `u_projected(axis, face)` is
/// the field after the update on the projected faces the bodies cover (for ∂/∂β), `air` what
/// the forward step returned. Returns each body's part.
pub fn correct_with_bodies_adjoint(
    ubar: &mut Mac,
    u_projected: impl Fn(usize, usize) -> f64,
    air: &AirBodyFaces,
    projected: &[Vec<u8>; 3],
    step: Correction,
    layers: usize,
) -> Vec<BodyVelocityAdjoint> {
    let plan = CorrectionPlan::new(projected.clone(), step.faces, step.grid, layers);
    correct_with_bodies_adjoint_planned(ubar, u_projected, air, &plan, step).bodies
}

/// What [`correct_with_bodies_adjoint`] reads of the step but the adjoint and the fields: the
/// faces the projection updated, and per axis the layers of the extrapolation from those and
/// the faces the bodies cover. Masks only, so the backward pass builds it ahead of the
/// step's adjoints.
pub struct CorrectionPlan {
    projected: [Vec<u8>; 3],
    axes: Vec<AxisPlan>,
    /// The faces known in part (`solver.surface_blend`), their fluid velocities and the
    /// field the extrapolation started from, when there are any.
    blended: Option<Blended>,
}

/// What the blended layers' transpose reads: per axis the faces known in part and their
/// fluid velocities, and the field after the bodies' velocities were mixed in.
struct Blended {
    surface: SurfaceFaces,
    fluid: [Vec<f64>; 3],
    sources: Mac,
}

impl CorrectionPlan {
    /// The plan for the faces the projection updated (`projected`) and those `faces` cover,
    /// with `layers` extrapolation layers.
    pub fn new(
        projected: [Vec<u8>; 3],
        faces: &[BodyFaces],
        grid: &Grid,
        layers: usize,
    ) -> CorrectionPlan {
        let ExtrapolationLayers { axes } =
            ExtrapolationLayers::new(&projected, faces, grid, layers);
        let axes = axes
            .into_iter()
            .enumerate()
            .map(|(a, lay)| AxisPlan::of(lay, &grid.faces(a)))
            .collect();
        CorrectionPlan { projected, axes, blended: None }
    }

    /// The plan with the faces known in part (`surface`, see [`SurfaceBlend`]), given the
    /// field after the pressure update (`updated`) and the bodies as the correction saw them
    /// (their velocities after the solve): the extrapolation's transpose reads the field it
    /// started from.
    pub fn blended(
        mut self,
        surface: SurfaceFaces,
        mut updated: Mac,
        step: Correction,
    ) -> CorrectionPlan {
        if surface.iter().any(|s| !s.is_empty()) {
            let spins = liquid_spins(step.bodies);
            let fluid = std::array::from_fn(|a| {
                let ua = &mut updated.c[a];
                sources_and_fluid(a, ua, &self.projected, step, &spins, &surface[a]).1
            });
            self.blended = Some(Blended { surface, fluid, sources: updated });
        }
        self
    }
}

/// What [`correct_with_bodies_adjoint_planned`] returns besides the adjoint of the field.
pub struct CorrectionAdjoint {
    /// Each body's part.
    pub bodies: Vec<BodyVelocityAdjoint>,
    /// (cell, ∂L/∂φ_L) through the shares of the faces known in part (empty without them).
    pub phi: Vec<(usize, f64)>,
}

/// [`correct_with_bodies_adjoint`] with its masks and layers found (`plan`).
pub fn correct_with_bodies_adjoint_planned(
    ubar: &mut Mac,
    u_projected: impl Fn(usize, usize) -> f64,
    air: &AirBodyFaces,
    plan: &CorrectionPlan,
    step: Correction,
) -> CorrectionAdjoint {
    let Correction { bodies, faces, weights, static_weights, grid } = step;
    let projected = &plan.projected;
    let set = |a: usize, f: usize| projected[a][f] != 0 || weights.closed(a, f);
    // 3ᵀ: as correct_velocity_adjoint; the blended layers' transpose where faces were known
    // in part, then each start's w⁰ and m⁰ back to its fluid velocity (`fluid_bar`, added
    // below where that velocity is the field's), its share c (to φ_L of the two cells its θ
    // was measured between) and the bodies' fractions β (through its fluid weight).
    let mut phi = Vec::new();
    let mut fluid_bar: [Vec<(usize, bool, f64)>; 3] = Default::default();
    let mut beta_bar: [std::collections::HashMap<usize, f64>; 3] = Default::default();
    for a in 0..3 {
        static_weights.zero_closed(a, &mut ubar.c[a]);
        let lat = grid.faces(a);
        match &plan.blended {
            Some(b) if !b.surface[a].is_empty() => {
                let (surface, fluid) = (&b.surface[a], &b.fluid[a]);
                let starts = starts(surface, &b.sources.c[a], fluid);
                let adj = &mut ubar.c[a];
                let lay = &plan.axes[a].lay;
                let mbar =
                    blend::extrapolate_blended_adjoint(adj, &b.sources.c[a], lay, &starts, &lat);
                for ((sf, &u_fl), m_bar) in surface.iter().zip(fluid).zip(mbar) {
                    let f = sf.face as usize;
                    let w_bar = adj[f];
                    let unknown = 1.0 - sf.share;
                    fluid_bar[a].push((f, sf.projected, -unknown * sf.fluid * w_bar));
                    let c_bar = sf.fluid * u_fl * w_bar + m_bar * sf.fluid / sf.open;
                    if sf.liquid != crate::geometry::grid::NONE {
                        phi.push((sf.liquid as usize, c_bar * sf.gradient[0]));
                        phi.push((sf.air as usize, c_bar * sf.gradient[1]));
                    }
                    if sf.covered {
                        // fluid = open − Σβ: ∂w⁰/∂β = (1 − c)·u_fl, ∂m⁰/∂β = (1 − c)/open.
                        let g = unknown * (u_fl * w_bar + m_bar / sf.open);
                        beta_bar[a].insert(f, g);
                    }
                }
            }
            _ => extrapolate_adjoint_planned(&mut ubar.c[a], &plan.axes[a], &lat),
        }
    }
    // 2ᵀ: the mixture, then each air face's mean back to the faces it read.
    let extrapolated = |a: usize, f: usize| {
        let list = &air[a];
        list.binary_search_by_key(&(f as u32), |e| e.0).map_or(0.0, |i| list[i].1)
    };
    let mut out =
        mix_body_velocities_adjoint(ubar, extrapolated, bodies, faces, weights, grid, |a, f| {
            !set(a, f)
        });
    for (a, list) in fluid_bar.iter().enumerate() {
        for &(f, _, g) in list.iter().filter(|e| !e.1) {
            ubar.c[a][f] += g;
        }
    }
    for (a, list) in air.iter().enumerate() {
        let lat = grid.faces(a);
        for &(f, _) in list {
            let f = f as usize;
            let g = std::mem::take(&mut ubar.c[a][f]);
            let mut nb = [0usize; 6];
            let n = neighbours(&lat, f, |m| set(a, m), &mut nb);
            for &m in &nb[..n] {
                ubar.c[a][m] += g / n as f64;
            }
        }
    }
    // 1ᵀ.
    let first = mix_body_velocities_adjoint(ubar, u_projected, bodies, faces, weights, grid, set);
    for (o, f) in out.iter_mut().zip(first) {
        o.add(f);
    }
    for (a, list) in fluid_bar.iter().enumerate() {
        for &(f, _, g) in list.iter().filter(|e| e.1) {
            ubar.c[a][f] += g;
        }
    }
    for (o, bf) in out.iter_mut().zip(faces) {
        for (a, bars) in beta_bar.iter().enumerate() {
            let on = bf.faces[a].iter().filter_map(|&(f, _)| bars.get(&f).map(|&g| (a, f, g)));
            o.dbeta.extend(on);
        }
    }
    CorrectionAdjoint { bodies: out, phi }
}

/// Adjoint of [`mix_body_velocities`] on the faces `on` accepts, in place on `ubar`:
/// `u_old(axis, face)` is the field before (read on those faces only, for ∂/∂β). Closed
/// faces pass nothing back to the fluid.
fn mix_body_velocities_adjoint(
    ubar: &mut Mac,
    u_old: impl Fn(usize, usize) -> f64,
    bodies: &[RigidBody],
    faces: &[BodyFaces],
    weights: &FaceWeights,
    grid: &Grid,
    on: impl Fn(usize, usize) -> bool,
) -> Vec<BodyVelocityAdjoint> {
    let mut out = vec![BodyVelocityAdjoint::default(); bodies.len()];
    let mut claimed = [0, 1, 2].map(|a| vec![false; grid.faces(a).len()]);
    let mut scaled = [0, 1, 2].map(|a| vec![false; grid.faces(a).len()]);
    // What reaches each face a body covers, before any of them is written.
    let incoming: Vec<[Vec<f64>; 3]> = faces
        .iter()
        .map(|bf| [0, 1, 2].map(|a| bf.faces[a].iter().map(|&(f, _)| ubar.c[a][f]).collect()))
        .collect();
    for i in (0..bodies.len()).rev() {
        let b = &bodies[i];
        for a in 0..3 {
            let lat = grid.faces(a);
            let e = crate::math::unit(a);
            let spin = b.spin();
            let w_liquid = spin.project(b.w);
            for (&(f, beta), &g) in faces[i].faces[a].iter().zip(&incoming[i][a]) {
                if !on(a, f) {
                    continue;
                }
                let closed = weights.closed(a, f);
                if closed && claimed[a][f] {
                    continue;
                }
                let coef = if closed { 1.0 } else { beta };
                let [ii, jj, kk] = lat.ijk(f);
                let r = lat.position(ii, jj, kk) - b.x;
                // u_b = e·(v + (P·ω) × r) = e·v + (P·(r × e))·ω.
                let t = spin.project(r.cross(e));
                for d in 0..3 {
                    out[i].vel[d] += coef * g * crate::math::comp(e, d);
                    out[i].vel[3 + d] += coef * g * crate::math::comp(t, d);
                }
                out[i].x += coef * g * w_liquid.cross(e);
                out[i].q += coef * g * spin.rotation_gradient(b.w, r.cross(e));
                if closed {
                    claimed[a][f] = true;
                    ubar.c[a][f] = 0.0;
                } else {
                    let p = lat.position(ii, jj, kk);
                    let ub = crate::math::comp(b.v + w_liquid.cross(p - b.x), a);
                    out[i].dbeta.push((a, f, (ub - u_old(a, f)) * g));
                    if !scaled[a][f] {
                        ubar.c[a][f] = weights.weight(a, f) * g;
                        scaled[a][f] = true;
                    }
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A field of values in [−1, 1) that differ from face to face, one for each `seed`.
    fn field(grid: &Grid, seed: usize) -> Mac {
        let mut m = Mac::zeros(grid);
        for a in 0..3 {
            for (f, x) in m.c[a].iter_mut().enumerate() {
                *x = ((f * 7919 + a * 13 + seed) % 97) as f64 / 48.0 - 1.0;
            }
        }
        m
    }

    #[test]
    fn adjoint_is_the_transpose() {
        // C is linear for fixed masks: ⟨C x, y⟩ = ⟨x, Cᵀ y⟩.
        let grid = Grid { n: [6, 5, 4], dx: 0.1 };
        let mut weights = [0, 1, 2].map(|a| vec![1.0; grid.faces(a).len()]);
        weights[1][7] = 0.0;
        weights[0][20] = 0.0;
        let weights = FaceWeights::new(&weights);
        let valid = [0, 1, 2].map(|a| {
            (0..grid.faces(a).len()).map(|f| u8::from((f * 37 + a) % 5 == 0)).collect::<Vec<u8>>()
        });
        let (x, y) = (field(&grid, 1), field(&grid, 2));
        let mut cx = x.clone();
        let mut v = valid.clone();
        correct_velocity(&mut cx, &mut v, &weights, &grid, 3);
        let mut cty = y.clone();
        correct_velocity_adjoint(&mut cty, &valid, &weights, &grid, 3);
        let (l, r) = (cx.dot(&y), x.dot(&cty));
        assert!((l - r).abs() <= 1e-12 * l.abs().max(r.abs()), "{l} vs {r}");
    }

    /// One layer from the valid faces' neighbours is one layer of `extrapolate` followed by
    /// zero on the closed faces, to the bit, on every axis of a grid whose valid faces are
    /// scattered and in blocks (fronts that meet, faces with one to six valid neighbours,
    /// the lattice's ends), with closed faces among the front's and elsewhere.
    #[test]
    fn one_layer_from_the_sources_is_extrapolate_then_closed() {
        let grid = Grid { n: [7, 6, 5], dx: 0.1 };
        for a in 0..3 {
            let lat = grid.faces(a);
            let valid: Vec<u8> = (0..lat.len())
                .map(|f| {
                    let [i, j, k] = lat.ijk(f);
                    u8::from((f * 37 + a) % 7 == 0 || (i + j < 4 && k > 2))
                })
                .collect();
            let value = |f: usize| ((f * 7919 + a * 13) % 97) as f64 / 48.0 - 1.0;
            let closed = |f: usize| (f * 13 + a) % 5 == 0 && valid[f] == 0;
            let on_valid = |f: usize| if valid[f] != 0 { value(f) } else { 0.0 };
            let mut by_passes: Vec<f64> = (0..lat.len()).map(on_valid).collect();
            extrapolate(&mut by_passes, &mut valid.clone(), &lat, 1);
            (0..lat.len()).filter(|&f| closed(f)).for_each(|f| by_passes[f] = 0.0);
            let sources: Vec<u32> =
                (0..lat.len() as u32).filter(|&f| valid[f as usize] != 0).collect();
            let mut sparse: Vec<f64> = (0..lat.len()).map(on_valid).collect();
            extrapolate_one_layer(&mut sparse, &valid, &sources, |&f| f as usize, &lat, closed);
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<u64>>();
            assert_eq!(bits(&sparse), bits(&by_passes), "axis {a}");
            let set = (0..lat.len()).filter(|&f| valid[f] == 0 && sparse[f] != 0.0).count();
            assert!(set > 20, "axis {a}: the layer sets {set} faces");
        }
    }

    /// The correction with bodies is linear in the field and the bodies' velocities for fixed
    /// masks and fractions: ⟨C(u, V), ȳ⟩ = ⟨u, Cᵀȳ⟩ + Σ_b V_b·V̄_b, with a tilted box (which
    /// turns the liquid) and a ball (which does not) covering faces in part, closing others,
    /// and both projected and air faces among them.
    #[test]
    fn correction_with_bodies_is_the_transpose() {
        use crate::math::{Pose, Rotation, SharedShape, Vec3};
        let grid = Grid { n: [9, 8, 7], dx: 0.1 };
        let pose = |x: Vec3, q: Rotation| Pose::from_parts(x, q);
        let tilt = Rotation::from_scaled_axis(Vec3::new(0.3, 0.5, -0.2));
        let mut bodies = vec![
            RigidBody::with_density(
                "box".into(),
                SharedShape::cuboid(0.17, 0.12, 0.14),
                pose(Vec3::new(0.33, 0.41, 0.36), tilt),
                700.0,
            ),
            RigidBody::with_density(
                "ball".into(),
                SharedShape::ball(0.16),
                pose(Vec3::new(0.61, 0.37, 0.33), Rotation::IDENTITY),
                500.0,
            ),
        ];
        bodies[0].v = Vec3::new(0.3, -0.2, 0.1);
        bodies[0].w = Vec3::new(0.4, 0.7, -0.5);
        bodies[1].v = Vec3::new(-0.1, 0.25, 0.2);
        bodies[1].w = Vec3::new(1.0, -2.0, 0.5);
        assert_eq!(bodies[0].spin(), crate::geometry::spin::Spin::Whole);
        assert_eq!(bodies[1].spin(), crate::geometry::spin::Spin::None);
        let faces: Vec<BodyFaces> = bodies.iter().map(|b| b.face_fractions(&grid)).collect();
        let mut w = crate::geometry::fractions::face_weights(&grid, &[]);
        for bf in &faces {
            for a in 0..3 {
                for &(f, beta) in &bf.faces[a] {
                    w[a][f] = (w[a][f] - beta).max(0.0);
                }
            }
        }
        let statics = FaceWeights::new(&crate::geometry::fractions::face_weights(&grid, &[]));
        let weights = FaceWeights::new(&w);
        // The lower half projected (liquid below y = 0.4), every face a body covers in part
        // above it an air face.
        let projected = [0, 1, 2].map(|a| {
            let lat = grid.faces(a);
            (0..lat.len())
                .map(|f| {
                    let [i, j, k] = lat.ijk(f);
                    u8::from(lat.position(i, j, k).y < 0.4)
                })
                .collect::<Vec<u8>>()
        });
        let kinds = |on: &dyn Fn(usize, usize) -> bool| -> usize {
            (0..3)
                .map(|a| {
                    faces
                        .iter()
                        .flat_map(|bf| bf.faces[a].iter())
                        .filter(|&&(f, _)| on(a, f))
                        .count()
                })
                .sum()
        };
        assert!(kinds(&|a, f| projected[a][f] != 0 && !weights.closed(a, f)) > 10);
        assert!(kinds(&|a, f| projected[a][f] == 0 && !weights.closed(a, f)) > 10);
        assert!(kinds(&|a, f| weights.closed(a, f)) > 10);
        let (x, y) = (field(&grid, 1), field(&grid, 2));
        let mut cx = x.clone();
        let none = SurfaceFaces::default();
        let step = Correction {
            bodies: &bodies,
            faces: &faces,
            weights: &weights,
            static_weights: &statics,
            grid: &grid,
        };
        let air = correct_with_bodies(&mut cx, &projected, None, &none, step, 3);
        let mut cty = y.clone();
        let u_old = |a: usize, f: usize| x.c[a][f];
        let bva = correct_with_bodies_adjoint(&mut cty, u_old, &air, &projected, step, 3);
        let gen = |b: &RigidBody| crate::math::twist(b.v, b.w);
        let l = cx.dot(&y);
        let r = x.dot(&cty)
            + bodies
                .iter()
                .zip(&bva)
                .map(|(b, g)| (0..6).map(|d| gen(b)[d] * g.vel[d]).sum::<f64>())
                .sum::<f64>();
        assert!((l - r).abs() <= 1e-12 * l.abs().max(r.abs()), "{l} vs {r}");
        // The ball's spin reaches nothing.
        assert!(bva[1].vel[3..].iter().all(|&g| g == 0.0));
    }

    /// Each layer's front (the first by a pass over the lattice, the others among the last
    /// front's neighbours) is every never-set face with a lattice neighbour known just before
    /// it, found by brute force over the lattice's (i, j, k), on lattices with a side of 1.
    #[test]
    fn fronts_are_the_faces_next_to_the_last_layer() {
        for n in [[7, 5, 4], [1, 6, 3], [5, 1, 1], [3, 4, 1]] {
            let lat = Lattice { n, off: [0.0; 3], dx: 1.0 };
            let valid: Vec<u8> = (0..lat.len()).map(|f| u8::from((f * 37) % 11 == 0)).collect();
            let lay = Layers::new(&valid, &lat, 4);
            let mut known: Vec<bool> = valid.iter().map(|&v| v != 0).collect();
            for front in &lay.fronts {
                let expect: Vec<usize> = (0..lat.len())
                    .filter(|&f| !known[f])
                    .filter(|&f| {
                        let p = lat.ijk(f);
                        (0..3).any(|a| {
                            [-1i64, 1].into_iter().any(|d| {
                                let q = p[a] as i64 + d;
                                let mut r = p;
                                r[a] = q.max(0) as usize;
                                (0..n[a] as i64).contains(&q) && known[lat.index(r[0], r[1], r[2])]
                            })
                        })
                    })
                    .collect();
                assert_eq!(front, &expect, "lattice {n:?}");
                expect.iter().for_each(|&f| known[f] = true);
            }
        }
    }

    /// The adjoint's targets of each layer, found among the neighbours of its front, are the
    /// faces known before the layer with a neighbour it set, found by brute force (and thus
    /// the faces of that layer's own level).
    #[test]
    fn targets_are_the_known_faces_next_to_each_layer() {
        for n in [[7, 5, 4], [1, 6, 3], [5, 1, 1], [3, 4, 1], [9, 8, 7]] {
            let lat = Lattice { n, off: [0.0; 3], dx: 1.0 };
            for (seed, layers) in [(11, 4), (23, 1), (5, 3), (61, 6)] {
                let valid: Vec<u8> =
                    (0..lat.len()).map(|f| u8::from((f * 37) % seed == 0)).collect();
                let lay = Layers::new(&valid, &lat, layers);
                let targets = lay.targets(&lat);
                assert_eq!(targets.len(), layers);
                for (l, got) in targets.iter().enumerate() {
                    let expect: Vec<usize> = (0..lat.len())
                        .filter(|&f| lay.known_before(f, l))
                        .filter(|&f| {
                            let mut nb = [0usize; 6];
                            let set = |m: usize| lay.level[m] as usize == l + 1;
                            neighbours(&lat, f, set, &mut nb) > 0
                        })
                        .collect();
                    assert_eq!(got, &expect, "lattice {n:?}, 1 in {seed} valid, layer {l}");
                }
            }
        }
    }

    #[test]
    fn extrapolation_spreads_one_layer_per_pass_and_keeps_valid_values() {
        let lat = Lattice { n: [6, 1, 1], off: [0.0; 3], dx: 1.0 };
        let mut f = vec![0.0, 2.0, 9.0, 9.0, 9.0, 9.0];
        let mut v = vec![0, 1, 0, 0, 0, 0];
        extrapolate(&mut f, &mut v, &lat, 2);
        assert_eq!(f, vec![2.0, 2.0, 2.0, 2.0, 0.0, 0.0]);
        assert_eq!(v, vec![1, 1, 1, 1, 0, 0]);
    }
}
