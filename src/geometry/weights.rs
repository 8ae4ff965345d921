//! The static solids' face weights in a byte a face.
//!
//! A face of the tank is open (weight 1) or closed (a wall, or inside an obstacle: 0), except
//! where an obstacle's surface cuts it. A dense copy of the weights in f64 sits through every
//! step (every step's combined weights start from it): 25 MB at 1 M cells, 200 MB at 8.4 M.
//! [`StaticWeights`] keeps a byte a face and lists the cut faces with their weights, and
//! gives back every weight bit for bit.

use crate::math::par::MIN_LEN;
use rayon::prelude::*;

/// What a face's byte says.
const CLOSED: u8 = 0;
const OPEN: u8 = 1;
const CUT: u8 = 2;

/// The weights of one axis's faces.
#[derive(Clone, Debug, PartialEq)]
struct Axis {
    /// [`CLOSED`] (exactly +0.0), [`OPEN`] (exactly 1.0) or [`CUT`] (anything else).
    kind: Vec<u8>,
    /// The cut faces and their weights, in increasing face order.
    cut: Vec<(u32, f64)>,
}

impl Axis {
    fn new(w: &[f64]) -> Axis {
        let kind: Vec<u8> = w
            .par_iter()
            .with_min_len(MIN_LEN)
            .map(|x| match x.to_bits() {
                b if b == 0f64.to_bits() => CLOSED,
                b if b == 1f64.to_bits() => OPEN,
                _ => CUT,
            })
            .collect();
        let cut = kind
            .iter()
            .enumerate()
            .filter(|(_, &k)| k == CUT)
            .map(|(f, _)| (f as u32, w[f]))
            .collect();
        Axis { kind, cut }
    }

    fn weight(&self, f: usize) -> f64 {
        match self.kind[f] {
            CLOSED => 0.0,
            OPEN => 1.0,
            _ => {
                let at = self.cut.binary_search_by_key(&(f as u32), |c| c.0);
                self.cut[at.expect("a cut face is listed")].1
            }
        }
    }
}

/// Face weights that are 0 or 1 but on a few faces (see the module doc).
#[derive(Clone, Debug, PartialEq)]
pub struct StaticWeights {
    axes: [Axis; 3],
}

impl StaticWeights {
    /// The weights `dense` (one vector per axis) in a byte a face.
    pub fn new(dense: &[Vec<f64>; 3]) -> StaticWeights {
        StaticWeights { axes: [0, 1, 2].map(|a| Axis::new(&dense[a])) }
    }

    /// The weight of face `f` normal to `axis`.
    #[inline]
    pub fn weight(&self, axis: usize, f: usize) -> f64 {
        self.axes[axis].weight(f)
    }

    /// Writes every weight over `out` (one vector per axis, of the lattices' lengths).
    pub fn write_into(&self, out: &mut [Vec<f64>; 3]) {
        for (o, ax) in out.iter_mut().zip(&self.axes) {
            assert_eq!(o.len(), ax.kind.len(), "a vector per face");
            o.par_iter_mut().with_min_len(MIN_LEN).zip(&ax.kind).for_each(|(o, &k)| {
                *o = if k == OPEN { 1.0 } else { 0.0 };
            });
            for &(f, w) in &ax.cut {
                o[f as usize] = w;
            }
        }
    }

    /// Every weight, one vector per axis.
    pub fn to_dense(&self) -> [Vec<f64>; 3] {
        let mut out = [0, 1, 2].map(|a| vec![0.0; self.axes[a].kind.len()]);
        self.write_into(&mut out);
        out
    }
}

/// Which faces are closed (weight ≤ 0): what the velocity correction zeroes and its
/// transpose lets nothing through.
pub trait ClosedFaces: Sync {
    /// Whether face `f` normal to `axis` is closed.
    fn closed(&self, axis: usize, f: usize) -> bool;
}

impl ClosedFaces for [Vec<f64>; 3] {
    #[inline]
    fn closed(&self, axis: usize, f: usize) -> bool {
        self[axis][f] <= 0.0
    }
}

impl ClosedFaces for StaticWeights {
    #[inline]
    fn closed(&self, axis: usize, f: usize) -> bool {
        match self.axes[axis].kind[f] {
            CLOSED => true,
            OPEN => false,
            _ => self.axes[axis].weight(f) <= 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every weight comes back bit for bit, whatever it is (−0.0, tiny, just under one),
    /// and a face is closed exactly where the dense weight is at most zero.
    #[test]
    fn weights_come_back_bit_for_bit() {
        let special = [0.0, 1.0, -0.0, 0.5, 1e-300, 1.0 - f64::EPSILON, 0.25, 1.0, 0.0];
        let dense = [0, 1, 2].map(|a| {
            (0..40_000).map(|f| special[(f * 7 + a * 3 + f / 11) % special.len()]).collect()
        });
        let s = StaticWeights::new(&dense);
        for a in 0..3 {
            for (f, w) in dense[a].iter().enumerate() {
                assert_eq!(s.weight(a, f).to_bits(), w.to_bits(), "axis {a} face {f}");
                assert_eq!(s.closed(a, f), dense.closed(a, f), "axis {a} face {f}");
            }
        }
        let back = s.to_dense();
        for a in 0..3 {
            assert!(back[a].iter().zip(&dense[a]).all(|(x, y)| x.to_bits() == y.to_bits()));
        }
        // Only the faces neither 0 nor 1 are listed.
        let cut = dense[0].iter().filter(|w| w.to_bits() != 0 && **w != 1.0).count();
        assert_eq!(s.axes[0].cut.len(), cut);
        assert!(cut > 0 && cut < dense[0].len());
    }
}
