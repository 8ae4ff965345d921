//! The checks a closed mesh passes beyond its edges: one fan of triangles at each vertex, no
//! two triangles that cross, nested shells that alternate in orientation. Each check's BVH
//! keeps its work near linear in the triangles.

use crate::math::Vec3;
use std::collections::HashMap;

/// The fans of a vertex from its link (each incident triangle's edge opposite it, a pair of
/// vertices): the fan of each link edge, numbered from 0 in order of first appearance, and
/// how many fans there are. A manifold vertex has one.
pub(crate) fn link_fans(link: &[(u32, u32)]) -> (Vec<usize>, usize) {
    let mut ids: Vec<u32> = link.iter().flat_map(|&(a, b)| [a, b]).collect();
    ids.sort_unstable();
    ids.dedup();
    let index = |x: u32| ids.binary_search(&x).expect("in the link");
    let mut sets = Sets::new(ids.len());
    for &(a, b) in link {
        sets.join(index(a), index(b));
    }
    let mut number = vec![usize::MAX; ids.len()];
    let mut fans = 0;
    let fan = link
        .iter()
        .map(|&(a, _)| {
            let root = sets.find(index(a));
            if number[root] == usize::MAX {
                number[root] = fans;
                fans += 1;
            }
            number[root]
        })
        .collect();
    (fan, fans)
}

/// A disjoint-set forest over `n` items.
pub(super) struct Sets(Vec<usize>);

impl Sets {
    pub(super) fn new(n: usize) -> Sets {
        Sets((0..n).collect())
    }
    pub(super) fn find(&mut self, mut i: usize) -> usize {
        while self.0[i] != i {
            self.0[i] = self.0[self.0[i]];
            i = self.0[i];
        }
        i
    }
    pub(super) fn join(&mut self, a: usize, b: usize) {
        let (a, b) = (self.find(a), self.find(b));
        self.0[a] = b;
    }
}

/// Every vertex's triangles form one fan: the edges opposite it (its link) make a single
/// cycle. Two cones touching at their tips pass the edge checks but not this one.
pub(super) fn check_vertex_fans(vertices: &[Vec3], tris: &[[u32; 3]]) -> Result<(), String> {
    let mut link: Vec<Vec<(u32, u32)>> = vec![Vec::new(); vertices.len()];
    for t in tris {
        for k in 0..3 {
            link[t[k] as usize].push((t[(k + 1) % 3], t[(k + 2) % 3]));
        }
    }
    let mut bad = 0;
    let mut first = None;
    for (v, edges) in link.iter().enumerate() {
        if link_fans(edges).1 > 1 {
            bad += 1;
            first.get_or_insert(v);
        }
    }
    match first {
        None => Ok(()),
        Some(v) => Err(format!(
            "has {bad} non-manifold vertex{} (vertex {} joins {} separate fans of triangles)",
            if bad == 1 { "" } else { "es" },
            v + 1,
            "two or more"
        )),
    }
}

/// The generalised winding number of closed `shell` at `p`: the solid angle its
/// triangles subtend, over 4π (±1 inside an outward / inward shell, 0 outside).
pub(super) fn winding(vertices: &[Vec3], shell: &[[u32; 3]], p: Vec3) -> f64 {
    let mut sum = 0.0;
    for t in shell {
        let [a, b, c] = t.map(|i| vertices[i as usize] - p);
        let (la, lb, lc) = (a.length(), b.length(), c.length());
        let num = a.dot(b.cross(c));
        let den = la * lb * lc + a.dot(b) * lc + b.dot(c) * la + c.dot(a) * lb;
        sum += 2.0 * num.atan2(den);
    }
    sum / (4.0 * std::f64::consts::PI)
}

/// A mesh of several shells (connected sets of triangles) must nest them with alternating
/// orientation: a shell inside an even number of others faces the same way as the whole,
/// one inside an odd number the other way (a hollow body's inner wall faces in). Two shells
/// nested with the same orientation, or a loose shell turned inside out, make parry's
/// inside/outside and the mass properties wrong.
pub(super) fn check_shells(vertices: &[Vec3], tris: &[[u32; 3]]) -> Result<(), String> {
    shell_nesting(vertices, tris).0
}

/// [`check_shells`], and the work it took: the triangles whose solid angle it summed.
///
/// A shell's depth is the number of other shells whose winding number at one of its
/// vertices is ±1. A closed shell's winding number is 0 outside its bounding box, so only
/// the shells whose box holds the vertex are summed over: a BVH of the shells' boxes
/// (parry's) finds them, and disjoint shells cost one pass over the triangles in all
/// instead of one per pair of shells.
pub(super) fn shell_nesting(vertices: &[Vec3], tris: &[[u32; 3]]) -> (Result<(), String>, usize) {
    use parry3d_f64::bounding_volume::Aabb;
    use parry3d_f64::partitioning::{Bvh, BvhBuildStrategy};
    let mut sets = Sets::new(vertices.len());
    for t in tris {
        sets.join(t[0] as usize, t[1] as usize);
        sets.join(t[1] as usize, t[2] as usize);
    }
    // Shells numbered in order of their first triangle.
    let mut number: HashMap<usize, usize> = HashMap::new();
    let mut shells: Vec<Vec<[u32; 3]>> = Vec::new();
    for t in tris {
        let root = sets.find(t[0] as usize);
        let k = *number.entry(root).or_insert_with(|| {
            shells.push(Vec::new());
            shells.len() - 1
        });
        shells[k].push(*t);
    }
    if shells.len() < 2 {
        return (Ok(()), 0);
    }
    let signed = |s: &[[u32; 3]]| -> f64 {
        s.iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| vertices[i as usize]);
                a.dot(b.cross(c))
            })
            .sum::<f64>()
            / 6.0
    };
    let volumes: Vec<f64> = shells.iter().map(|s| signed(s)).collect();
    let outermost = (0..shells.len())
        .max_by(|&a, &b| volumes[a].abs().total_cmp(&volumes[b].abs()))
        .expect("two shells");
    let whole = volumes[outermost].signum();
    let boxes: Vec<Aabb> = shells
        .iter()
        .map(|s| Aabb::from_points(s.iter().flatten().map(|&i| vertices[i as usize])))
        .collect();
    let bvh = Bvh::from_leaves(BvhBuildStrategy::Binned, &boxes);
    let mut work = 0;
    for (i, shell) in shells.iter().enumerate() {
        let p = vertices[shell[0][0] as usize];
        let at = Aabb::new(p, p);
        let mut depth = 0;
        for j in bvh.intersect_aabb(&at).map(|j| j as usize).filter(|&j| j != i) {
            work += shells[j].len();
            if winding(vertices, &shells[j], p).abs() > 0.5 {
                depth += 1;
            }
        }
        let expected = if depth % 2 == 0 { whole } else { -whole };
        if volumes[i].signum() != expected {
            let message = format!(
                "has {} shells and shell {} (inside {depth} other{}) faces the wrong way: \
                 nested shells must alternate in orientation",
                shells.len(),
                i + 1,
                plural(depth)
            );
            return (Err(message), work);
        }
    }
    (Ok(()), work)
}

/// No two triangles that share no vertex may intersect.
pub(super) fn check_self_intersections(vertices: &[Vec3], tris: &[[u32; 3]]) -> Result<(), String> {
    match first_crossing(vertices, tris).0 {
        None => Ok(()),
        Some((i, j)) => Err(format!("intersects itself (triangles {} and {} cross)", i + 1, j + 1)),
    }
}

/// The first pair of triangles (i < j, by i then j) that share no vertex and intersect, and
/// the work it took: the pairs whose bounding boxes touch, each tested. A BVH of the
/// triangles' boxes (parry's) finds each triangle's candidates; parry's intersection test
/// decides. The triangles are taken in parallel, and the first pair in order is kept.
pub(super) fn first_crossing(
    vertices: &[Vec3],
    tris: &[[u32; 3]],
) -> (Option<(usize, usize)>, usize) {
    use parry3d_f64::bounding_volume::Aabb;
    use parry3d_f64::partitioning::{Bvh, BvhBuildStrategy};
    use parry3d_f64::shape::Triangle;
    use rayon::prelude::*;
    use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};
    let shapes: Vec<Triangle> = tris
        .iter()
        .map(|t| {
            Triangle::new(vertices[t[0] as usize], vertices[t[1] as usize], vertices[t[2] as usize])
        })
        .collect();
    let boxes: Vec<Aabb> = shapes.iter().map(Triangle::local_aabb).collect();
    let bvh = Bvh::from_leaves(BvhBuildStrategy::Binned, &boxes);
    let identity = crate::math::Pose::IDENTITY;
    let work = AtomicUsize::new(0);
    let first = (0..tris.len())
        .into_par_iter()
        .with_min_len(crate::math::par::MIN_LEN)
        .find_map_first(|i| {
            let mut candidates: Vec<usize> = bvh
                .intersect_aabb(&boxes[i])
                .map(|j| j as usize)
                .filter(|&j| j > i && !tris[i].iter().any(|v| tris[j].contains(v)))
                .collect();
            work.fetch_add(candidates.len(), Relaxed);
            candidates.sort_unstable();
            candidates
                .into_iter()
                .find(|&j| {
                    parry3d_f64::query::intersection_test(
                        &identity, &shapes[i], &identity, &shapes[j],
                    )
                    .is_ok_and(|hit| hit.intersecting)
                })
                .map(|j| (i, j))
        });
    (first, work.into_inner())
}

pub(super) fn plural(n: usize) -> &'static str {
    if n == 1 {
        ""
    } else {
        "s"
    }
}
