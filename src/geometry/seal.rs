//! The faces a moving thin body seals.
//!
//! A body thinner than a cell everywhere ([`RigidBody::seals`]) leaves most of a face's
//! control volume to the liquid (a quarter-cell plate, three quarters), so by its fractions
//! alone the liquid flows through it. Such a body also closes every face whose segment
//! between the two cell centres meets it, as a thin static solid does
//! ([`crate::geometry::fractions::seal_thin_solid`]): the closed faces are a cut of the grid
//! along the body, watertight at any orientation. The fluid weight `s` such a face had left is
//! taken from the liquid, and on a face the body *crosses* (one centre outside it) that
//! liquid moves with the body along the face's normal: its flux is `(β + s)·dx²·(v + ω × r)·e`
//! (J's column, so the face carries the body's normal velocity), and its mass `ρ·s·dx³` along
//! `e` joins the body's (the pressure stage's entrained liquid). Kept apart from β, the
//! volume fractions still hold exactly the body's volume: the buoyancy and the torque of a
//! hydrostatic pressure are those of β alone, since the entrained liquid's weight balances
//! the extra pressure force its faces take (see `docs/method.md`, "Moving thin bodies").

use crate::geometry::body::RigidBody;
use crate::geometry::fractions::BodyFaces;
use crate::geometry::grid::Grid;
use crate::geometry::weights::FaceWeights;
use crate::math::dual::Dual;
use crate::math::Vec3;
use parry3d_f64::query::Ray;
use rayon::prelude::*;

/// A face a body seals.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SealedFace {
    /// Face index on its axis's lattice.
    pub face: usize,
    /// The fluid weight the face had left, now closed.
    pub s: f64,
    /// Whether the body crosses the face's segment (one cell centre outside it): the
    /// liquid left on the face moves with the body. A face between two centres inside the
    /// body is closed and nothing more.
    pub crossed: bool,
}

/// The faces one body seals, per axis, in increasing face order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Seal {
    /// Per axis.
    pub faces: [Vec<SealedFace>; 3],
}

impl Seal {
    /// The faces of a sealing body: those of `faces` (its fractions) still open in `weights`
    /// whose segment between cell centres meets the body (a ray cast). Empty for a body
    /// that does not seal.
    pub fn new(grid: &Grid, body: &RigidBody, faces: &BodyFaces, weights: &FaceWeights) -> Seal {
        if !body.seals(grid.dx) {
            return Seal::default();
        }
        let pose = body.pose();
        let faces = std::array::from_fn(|axis| {
            let lat = grid.faces(axis);
            let dir = crate::math::unit(axis);
            faces.faces[axis]
                .par_iter()
                .filter_map(|&(f, _)| {
                    let w = weights.weight(axis, f);
                    if w <= 0.0 {
                        return None;
                    }
                    let [i, j, k] = lat.ijk(f);
                    let from: Vec3 = lat.position(i, j, k) - 0.5 * grid.dx * dir;
                    let inside_from = body.sdf(from) < 0.0;
                    let meets = inside_from
                        || body.shape.intersects_ray(&pose, &Ray::new(from, dir), grid.dx);
                    meets.then(|| {
                        let inside_to = body.sdf(from + grid.dx * dir) < 0.0;
                        SealedFace { face: f, s: w, crossed: !(inside_from && inside_to) }
                    })
                })
                .collect()
        });
        Seal { faces }
    }

    /// Whether the body seals nothing.
    pub fn is_empty(&self) -> bool {
        self.faces.iter().all(Vec::is_empty)
    }

    /// The weights to take off: each sealed face's `s`.
    pub fn closing(&self) -> [Vec<(usize, f64)>; 3] {
        self.faces.each_ref().map(|l| l.iter().map(|s| (s.face, s.s)).collect())
    }

    /// The faces of J's columns: the body's fractions β, with β + s on the faces it crosses
    /// (the whole open part of a face moves with it there).
    pub fn coupling(&self, beta: &BodyFaces) -> BodyFaces {
        if self.is_empty() {
            return beta.clone();
        }
        BodyFaces { faces: std::array::from_fn(|a| self.merge(a, &beta.faces[a], |b, s| b + s)) }
    }

    /// [`Seal::coupling`] of the fractions with their pose derivatives: on a crossed face
    /// β + s is the static weight (s = w_static − β), a constant of the pose.
    pub fn coupling_dual(&self, beta: &[Vec<(usize, Dual<6>)>; 3]) -> [Vec<(usize, Dual<6>)>; 3] {
        std::array::from_fn(|a| {
            self.merge(a, &beta[a], |b: Dual<6>, s| Dual::new(b.v + s, [0.0; 6]))
        })
    }

    /// `beta` of `axis` with `on_crossed(β, s)` on the crossed faces.
    fn merge<T: Copy>(
        &self,
        axis: usize,
        beta: &[(usize, T)],
        on_crossed: impl Fn(T, f64) -> T,
    ) -> Vec<(usize, T)> {
        let mut sealed = self.faces[axis].iter().filter(|s| s.crossed).peekable();
        beta.iter()
            .map(|&(f, b)| {
                while sealed.next_if(|s| s.face < f).is_some() {}
                match sealed.peek() {
                    Some(s) if s.face == f => (f, on_crossed(b, s.s)),
                    _ => (f, b),
                }
            })
            .collect()
    }
}
