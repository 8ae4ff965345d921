//! Face weights in a byte a face.
//!
//! A face of the tank is open (weight 1) or closed (a wall, inside an obstacle or a body: 0),
//! except where a solid's surface cuts it. In f64 the weights are 25 MB at 1 M cells and
//! 200 MB at 8.4 M, nearly all of them exactly 0 or 1. [`FaceWeights`] keeps a byte a face
//! and lists the cut faces with their weights, gives back every weight bit for bit, and is
//! what every stage reads: the static solids' weights, a step's (those minus the bodies'
//! fractions, [`FaceWeights::subtract`]) and the density projection's (closed at the narrow
//! band's deep cells, [`FaceWeights::close_faces`]).

use crate::geometry::grid::Grid;
use crate::math::par::MIN_LEN;
use rayon::prelude::*;

/// The face index of the −side (`side = 0`) or +side (`side = 1`) face of cell `ijk` along
/// `axis`.
#[inline]
pub fn cell_face(grid: &Grid, axis: usize, ijk: [usize; 3], side: usize) -> usize {
    let mut f = ijk;
    f[axis] += side;
    grid.faces(axis).index(f[0], f[1], f[2])
}

/// The neighbouring cell of cell `c` (at `ijk`) across its −side or +side face of axis
/// `axis` and the face's weight, when the face is open (weight > 0) and the neighbour inside
/// the grid (`weights`: [`FaceWeights::axes`]). The pressure couples a cell to it, or sees air
/// there; the closing of air pockets connects air through it.
#[inline]
pub fn open_neighbour(
    grid: &Grid,
    weights: &[AxisWeights<'_>; 3],
    c: usize,
    ijk: [usize; 3],
    axis: usize,
    side: usize,
) -> Option<(usize, f64)> {
    let w = weights[axis].weight(cell_face(grid, axis, ijk, side));
    if w <= 0.0 {
        return None;
    }
    grid.cells().neighbour(c, ijk, axis, side).map(|n| (n, w))
}

/// What a face's byte says. A closed or open face's byte is its weight (0 or 1), which
/// [`AxisWeights::weight`] reads as it is.
const CLOSED: u8 = 0;
const OPEN: u8 = 1;
const CUT: u8 = 2;

/// The byte of weight `w`: [`CLOSED`] for +0.0 exactly, [`OPEN`] for 1.0, [`CUT`] otherwise
/// (−0.0 too, so that its sign comes back).
#[inline]
fn kind_of(w: f64) -> u8 {
    match w.to_bits() {
        b if b == 0f64.to_bits() => CLOSED,
        b if b == 1f64.to_bits() => OPEN,
        _ => CUT,
    }
}

/// The weights of one axis's faces.
#[derive(Clone, Debug, PartialEq)]
struct Axis {
    /// [`CLOSED`] (exactly +0.0), [`OPEN`] (exactly 1.0) or [`CUT`] (anything else).
    kind: Vec<u8>,
    /// The cut faces and their weights, in increasing face order.
    cut: Vec<(u32, f64)>,
    /// Per block of [`BLOCK`] faces, the number of cut faces before it: where a cut face's
    /// entry is, without a search (see [`Axis::cut_weight`]).
    rank: Vec<u32>,
}

/// The faces a [`Axis::rank`] entry covers.
const BLOCK: usize = 64;

impl Axis {
    fn new(w: &[f64]) -> Axis {
        let kind: Vec<u8> = w.par_iter().with_min_len(MIN_LEN).map(|&x| kind_of(x)).collect();
        let cut = kind
            .iter()
            .enumerate()
            .filter(|(_, &k)| k == CUT)
            .map(|(f, _)| (f as u32, w[f]))
            .collect();
        let mut axis = Axis { kind, cut, rank: Vec::new() };
        axis.rank();
        axis
    }

    /// Counts [`Axis::rank`] again from the list (after the bytes or the list changed).
    fn rank(&mut self) {
        let blocks = self.kind.len().div_ceil(BLOCK);
        self.rank.clear();
        self.rank.reserve(blocks);
        let mut before = 0;
        for b in 0..blocks {
            while self.cut.get(before).is_some_and(|c| (c.0 as usize) < b * BLOCK) {
                before += 1;
            }
            self.rank.push(before as u32);
        }
    }

    /// The weight of a face listed as cut: its entry is its block's rank plus the cut faces
    /// before it in the block (a count of at most 63 bytes, not a search of the list). Out of
    /// line, so that the bytes' test inlines into the stages' loops.
    #[cold]
    #[inline(never)]
    fn cut_weight(&self, f: usize) -> f64 {
        let b = f / BLOCK;
        let within = self.kind[b * BLOCK..f].iter().filter(|&&k| k == CUT).count();
        let (face, w) = self.cut[self.rank[b] as usize + within];
        debug_assert_eq!(face as usize, f, "a cut face is listed");
        w
    }

    /// This axis's weights as the stages read them.
    #[inline(always)]
    fn view(&self) -> AxisWeights<'_> {
        AxisWeights { kind: &self.kind, axis: self }
    }

    /// `w ← clamp(w − β, 0, 1)` on each face of `faces` (sorted by face, each once).
    fn subtract(&mut self, faces: &[(usize, f64)]) {
        debug_assert!(faces.windows(2).all(|p| p[0].0 < p[1].0), "faces sorted, each once");
        // Every new weight first: a weight is read through the bytes before it.
        let view = self.view();
        let new: Vec<(u32, f64)> = faces
            .iter()
            .map(|&(f, beta)| (f as u32, (view.weight(f) - beta).clamp(0.0, 1.0)))
            .collect();
        let mut changed = Vec::new();
        for (f, w) in new {
            let kind = kind_of(w);
            self.kind[f as usize] = kind;
            if kind == CUT {
                changed.push((f, w));
            }
        }
        // The new list: the old entries of the faces not touched, merged with the changed.
        let mut touched = faces.iter().map(|&(f, _)| f as u32).peekable();
        let kept = self.cut.iter().copied().filter(|&(f, _)| {
            while touched.next_if(|&t| t < f).is_some() {}
            touched.peek() != Some(&f)
        });
        let mut merged = Vec::with_capacity(self.cut.len() + changed.len());
        let mut changed = changed.into_iter().peekable();
        for old in kept {
            while let Some(new) = changed.next_if(|new| new.0 < old.0) {
                merged.push(new);
            }
            merged.push(old);
        }
        merged.extend(changed);
        self.cut = merged;
        self.rank();
    }
}

/// The weights of one axis's faces, borrowed from a [`FaceWeights`].
#[derive(Clone, Copy, Debug)]
pub struct AxisWeights<'a> {
    kind: &'a [u8],
    axis: &'a Axis,
}

impl AxisWeights<'_> {
    /// The weight of face `f`.
    #[inline(always)]
    pub fn weight(&self, f: usize) -> f64 {
        // The closed and open bytes are their weights' values: one test, not a match.
        match self.kind[f] {
            CUT => self.axis.cut_weight(f),
            k => f64::from(k),
        }
    }

    /// Whether face `f` is open (weight > 0).
    #[inline(always)]
    pub fn open(&self, f: usize) -> bool {
        match self.kind[f] {
            OPEN => true,
            CLOSED => false,
            _ => self.axis.cut_weight(f) > 0.0,
        }
    }

    /// Whether face `f` is closed (weight ≤ 0).
    #[inline(always)]
    pub fn closed(&self, f: usize) -> bool {
        match self.kind[f] {
            CLOSED => true,
            OPEN => false,
            _ => self.axis.cut_weight(f) <= 0.0,
        }
    }
}

/// Face weights in a byte a face but on the cut faces (see the module doc).
#[derive(Clone, Debug, PartialEq)]
pub struct FaceWeights {
    axes: [Axis; 3],
}

impl FaceWeights {
    /// The weights `dense` (one vector per axis) in a byte a face.
    pub fn new(dense: &[Vec<f64>; 3]) -> FaceWeights {
        FaceWeights { axes: [0, 1, 2].map(|a| Axis::new(&dense[a])) }
    }

    /// The weights of the faces normal to `axis`: what a loop over one axis's faces reads
    /// (its bytes found once, not once a face).
    #[inline(always)]
    pub fn axis(&self, axis: usize) -> AxisWeights<'_> {
        self.axes[axis].view()
    }

    /// [`FaceWeights::axis`] of the three axes.
    #[inline(always)]
    pub fn axes(&self) -> [AxisWeights<'_>; 3] {
        [self.axis(0), self.axis(1), self.axis(2)]
    }

    /// The weight of face `f` normal to `axis`.
    #[inline(always)]
    pub fn weight(&self, axis: usize, f: usize) -> f64 {
        self.axis(axis).weight(f)
    }

    /// Whether face `f` normal to `axis` is open (weight > 0).
    #[inline(always)]
    pub fn open(&self, axis: usize, f: usize) -> bool {
        self.axis(axis).open(f)
    }

    /// Whether face `f` normal to `axis` is closed (weight ≤ 0): what the velocity correction
    /// zeroes and its transpose lets nothing through.
    #[inline(always)]
    pub fn closed(&self, axis: usize, f: usize) -> bool {
        self.axis(axis).closed(f)
    }

    /// Sets `field` (a value per face normal to `axis`) to zero on every closed face: a
    /// pass over the bytes that needs no branch a face, then the cut faces of weight ≤ 0.
    pub fn zero_closed(&self, axis: usize, field: &mut [f64]) {
        let ax = &self.axes[axis];
        assert_eq!(field.len(), ax.kind.len(), "a value per face");
        field.par_chunks_mut(MIN_LEN).zip(ax.kind.par_chunks(MIN_LEN)).for_each(|(x, k)| {
            for (x, &k) in x.iter_mut().zip(k) {
                *x = if k == CLOSED { 0.0 } else { *x };
            }
        });
        for &(f, w) in &ax.cut {
            if w <= 0.0 {
                field[f as usize] = 0.0;
            }
        }
    }

    /// [`FaceWeights::zero_closed`] that also zeroes, in the same pass, every face whose
    /// byte in `marks` (one a face) is `mark`.
    pub fn zero_closed_or(&self, axis: usize, field: &mut [f64], marks: &[u8], mark: u8) {
        let ax = &self.axes[axis];
        assert_eq!(field.len(), ax.kind.len(), "a value per face");
        assert_eq!(marks.len(), ax.kind.len(), "a mark per face");
        let (kind, marks) = (ax.kind.par_chunks(MIN_LEN), marks.par_chunks(MIN_LEN));
        field.par_chunks_mut(MIN_LEN).zip(kind).zip(marks).for_each(|((x, k), m)| {
            for ((x, &k), &m) in x.iter_mut().zip(k).zip(m) {
                *x = if k == CLOSED || m == mark { 0.0 } else { *x };
            }
        });
        for &(f, w) in &ax.cut {
            if w <= 0.0 {
                field[f as usize] = 0.0;
            }
        }
    }

    /// The number of faces normal to `axis`.
    pub fn len(&self, axis: usize) -> usize {
        self.axes[axis].kind.len()
    }

    /// The faces normal to `axis` that are neither 0 nor 1, with their weights, in
    /// increasing face order.
    pub fn cut(&self, axis: usize) -> impl Iterator<Item = (usize, f64)> + '_ {
        self.axes[axis].cut.iter().map(|&(f, w)| (f as usize, w))
    }

    /// Overwrites these weights with `other`'s, in this value's memory.
    pub fn copy_from(&mut self, other: &FaceWeights) {
        for (ax, o) in self.axes.iter_mut().zip(&other.axes) {
            ax.kind.clone_from(&o.kind);
            ax.cut.clone_from(&o.cut);
            ax.rank.clone_from(&o.rank);
        }
    }

    /// `w ← clamp(w − β, 0, 1)` on each face of `faces[axis]` (a body's fractions, sorted by
    /// face, each face once): the weights the liquid sees beside a body.
    pub fn subtract(&mut self, faces: &[Vec<(usize, f64)>; 3]) {
        for (ax, list) in self.axes.iter_mut().zip(faces) {
            ax.subtract(list);
        }
    }

    /// These weights with every face `close` picks closed. `close(axis, kind)` gets each
    /// axis's bytes (the face lattice's, in its order) and sets those of the faces to close
    /// to the byte it is handed.
    pub fn close_faces(&self, close: impl Fn(usize, &mut [u8], u8)) -> FaceWeights {
        let mut out = self.clone();
        for (a, ax) in out.axes.iter_mut().enumerate() {
            close(a, &mut ax.kind, CLOSED);
            let kind = &ax.kind;
            ax.cut.retain(|&(f, _)| kind[f as usize] == CUT);
            ax.rank();
        }
        out
    }

    /// Every weight, one vector per axis.
    pub fn to_dense(&self) -> [Vec<f64>; 3] {
        self.axes.each_ref().map(|ax| {
            let mut out: Vec<f64> = ax
                .kind
                .par_iter()
                .with_min_len(MIN_LEN)
                .map(|&k| if k == OPEN { 1.0 } else { 0.0 })
                .collect();
            for &(f, w) in &ax.cut {
                out[f as usize] = w;
            }
            out
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The special weights a face can have: −0.0, tiny, just under one.
    const SPECIAL: [f64; 9] = [0.0, 1.0, -0.0, 0.5, 1e-300, 1.0 - f64::EPSILON, 0.25, 1.0, 0.0];

    fn same_bits(s: &FaceWeights, dense: &[Vec<f64>; 3]) {
        for a in 0..3 {
            assert_eq!(s.len(a), dense[a].len());
            for (f, &w) in dense[a].iter().enumerate() {
                assert_eq!(s.weight(a, f).to_bits(), w.to_bits(), "axis {a} face {f}");
                assert_eq!(s.closed(a, f), w <= 0.0, "axis {a} face {f}");
                assert_eq!(s.open(a, f), w > 0.0, "axis {a} face {f}");
            }
        }
        for a in 0..3 {
            let mut field = vec![1.5; dense[a].len()];
            s.zero_closed(a, &mut field);
            for (f, &w) in dense[a].iter().enumerate() {
                assert_eq!(field[f] == 0.0, w <= 0.0, "axis {a} face {f} zeroed where closed");
            }
        }
        let back = s.to_dense();
        for a in 0..3 {
            assert!(back[a].iter().zip(&dense[a]).all(|(x, y)| x.to_bits() == y.to_bits()));
            let listed: Vec<usize> = s.cut(a).map(|(f, _)| f).collect();
            let cut: Vec<usize> =
                (0..dense[a].len()).filter(|&f| kind_of(dense[a][f]) == CUT).collect();
            assert_eq!(listed, cut, "axis {a}: exactly the faces neither +0 nor 1 are listed");
        }
    }

    /// Every weight comes back bit for bit, whatever it is, and a face is closed exactly
    /// where the dense weight is at most zero.
    #[test]
    fn weights_come_back_bit_for_bit() {
        let dense = [0, 1, 2].map(|a| {
            (0..40_000).map(|f| SPECIAL[(f * 7 + a * 3 + f / 11) % SPECIAL.len()]).collect()
        });
        let s = FaceWeights::new(&dense);
        same_bits(&s, &dense);
        let cut = s.cut(0).count();
        assert!(cut > 0 && cut < dense[0].len());
    }

    proptest! {
        /// Subtracting bodies' fractions gives the bits the dense `clamp(w − β, 0, 1)` does,
        /// body after body, and closing faces closes those and no other (300 faces an
        /// axis: five blocks of the rank).
        #[test]
        fn subtract_and_close_match_the_dense_weights(
            start in proptest::collection::vec(0usize..SPECIAL.len(), 300),
            bodies in proptest::collection::vec(
                proptest::collection::btree_map(0usize..300, 0.0f64..=1.0, 0..150), 1..4),
            snap in proptest::collection::vec(any::<bool>(), 300),
            shut in proptest::collection::vec(any::<bool>(), 300),
        ) {
            let mut dense = [0, 1, 2].map(|a| {
                start.iter().map(|&i| SPECIAL[(i + a) % SPECIAL.len()]).collect::<Vec<f64>>()
            });
            let mut s = FaceWeights::new(&dense);
            let mut copy = FaceWeights::new(&[vec![0.5; 3], vec![], vec![1.0]]);
            copy.copy_from(&s);
            prop_assert_eq!(&copy, &s);
            for body in &bodies {
                // Fractions snapped to 0 or 1 on some faces, as a body's are.
                let list: Vec<(usize, f64)> = body
                    .iter()
                    .map(|(&f, &b)| (f, if snap[f] { b.round() } else { b }))
                    .collect();
                for w in dense.iter_mut() {
                    for &(f, beta) in &list {
                        w[f] = (w[f] - beta).clamp(0.0, 1.0);
                    }
                }
                s.subtract(&[list.clone(), list.clone(), list]);
            }
            same_bits(&s, &dense);
            let closed = s.close_faces(|_, kind, to| {
                for (k, &c) in kind.iter_mut().zip(&shut) {
                    if c {
                        *k = to;
                    }
                }
            });
            for w in dense.iter_mut() {
                for (w, &c) in w.iter_mut().zip(&shut) {
                    if c {
                        *w = 0.0;
                    }
                }
            }
            same_bits(&closed, &dense);
        }
    }
}
