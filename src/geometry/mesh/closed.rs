//! A closed, consistently oriented triangle mesh ([`ClosedMesh`]): identical vertices merged,
//! every edge in two triangles wound opposite ways, the checks of `check.rs` passed, and the
//! volume it encloses.

use super::check::{check_self_intersections, check_shells, check_vertex_fans, plural};
use crate::math::Vec3;
use std::collections::HashMap;

/// A mesh whose enclosed volume is at most this fraction of its bounding-box volume
/// is degenerate.
const MIN_RELATIVE_VOLUME: f64 = 1e-9;

/// A validated closed, consistently oriented triangle mesh.
#[derive(Debug)]
pub(super) struct ClosedMesh {
    /// Vertices, each referenced by some triangle, all distinct.
    pub(super) vertices: Vec<Vec3>,
    /// Triangles, all wound the same way.
    pub(super) triangles: Vec<[u32; 3]>,
    /// Signed enclosed volume: positive when the triangles are counter-clockwise seen from
    /// outside, negative when the mesh is inside-out. Never close to zero.
    pub(super) volume: f64,
}

impl ClosedMesh {
    /// Merges identical vertices, drops triangles with a repeated vertex, and checks the
    /// topology, the orientation and the volume. The error completes a sentence starting
    /// with the mesh's name ("is not closed: ...").
    pub(super) fn new(positions: &[Vec3], triangles: &[[u32; 3]]) -> Result<ClosedMesh, String> {
        let (vertices, tris) = merge_vertices(positions, triangles)?;
        let corners = |t: &[u32; 3]| t.map(|i| vertices[i as usize]);
        if let Some(n) = tris.iter().position(|t| {
            let [a, b, c] = corners(t);
            (b - a).cross(c - a) == Vec3::ZERO
        }) {
            return Err(format!("has a zero-area triangle (number {}, corners collinear)", n + 1));
        }

        // Every undirected edge in exactly two triangles, every directed edge once: the
        // edges as (low, high, whether written low to high), sorted, so that the copies of
        // an undirected edge are a run.
        let mut edges: Vec<(u32, u32, bool)> = tris
            .iter()
            .flat_map(|t| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])])
            .map(|(a, b)| (a.min(b), a.max(b), a < b))
            .collect();
        {
            use rayon::slice::ParallelSliceMut;
            edges.par_sort_unstable();
        }
        let (mut boundary, mut non_manifold, mut twice) = (0, 0, 0);
        for run in edges.chunk_by(|x, y| (x.0, x.1) == (y.0, y.1)) {
            boundary += (run.len() == 1) as usize;
            non_manifold += (run.len() > 2) as usize;
            let forward = run.iter().filter(|e| e.2).count();
            twice += (forward > 1) as usize + (run.len() - forward > 1) as usize;
        }
        if boundary > 0 || non_manifold > 0 {
            let mut parts = Vec::new();
            if boundary > 0 {
                parts.push(format!(
                    "{boundary} boundary edge{} (in one triangle only)",
                    plural(boundary)
                ));
            }
            if non_manifold > 0 {
                parts.push(format!(
                    "{non_manifold} edge{} shared by more than two triangles",
                    plural(non_manifold)
                ));
            }
            // An open surface (a sail, a hull without a deck) can be a body's shell.
            let shell = if boundary > 0 {
                "; an open surface loads as a shell: give the body a `shell_thickness` (m) in a \
                 scene, or load it with `load_obj_or_shell` in Rust; or close the mesh"
            } else {
                ""
            };
            return Err(format!(
                "is not closed: {}; every edge must be shared by exactly two triangles{shell}",
                parts.join(" and ")
            ));
        }
        if twice > 0 {
            return Err(format!(
                "has inconsistent orientation: {twice} directed edge{} appear{} twice \
                 (neighbouring triangles must wind the same way)",
                plural(twice),
                if twice == 1 { "s" } else { "" }
            ));
        }

        check_vertex_fans(&vertices, &tris)?;
        check_self_intersections(&vertices, &tris)?;
        check_shells(&vertices, &tris)?;

        // Enclosed volume, about the bounding-box centre for accuracy.
        let (lo, hi) = vertices
            .iter()
            .fold((Vec3::splat(f64::INFINITY), Vec3::splat(f64::NEG_INFINITY)), |(lo, hi), &p| {
                (lo.min(p), hi.max(p))
            });
        let centre = (lo + hi) * 0.5;
        let volume = tris
            .iter()
            .map(|t| {
                let [a, b, c] = corners(t).map(|p| p - centre);
                a.dot(b.cross(c))
            })
            .sum::<f64>()
            / 6.0;
        let extent = (hi - lo).max_element();
        if volume.abs() <= MIN_RELATIVE_VOLUME * extent.powi(3) {
            return Err("encloses no volume: it is flat or its shells cancel out".into());
        }
        Ok(ClosedMesh { vertices, triangles: tris, volume })
    }

    /// Reverses every triangle of an inside-out mesh, so that all face outward.
    pub(super) fn outward(mut self) -> ClosedMesh {
        if self.volume < 0.0 {
            for t in &mut self.triangles {
                t.swap(1, 2);
            }
            self.volume = -self.volume;
        }
        self
    }
}

/// Merges vertices with identical coordinates and drops triangles with a repeated vertex:
/// the mesh's vertices (each used by a triangle) and triangles. Errors (completing a sentence
/// starting with the mesh's name): a non-finite or missing vertex, no triangles.
pub(super) fn merge_vertices(
    positions: &[Vec3],
    triangles: &[[u32; 3]],
) -> Result<(Vec<Vec3>, Vec<[u32; 3]>), String> {
    if let Some(i) = positions.iter().position(|p| !p.is_finite()) {
        return Err(format!("has a non-finite vertex (number {})", i + 1));
    }

    // Merge vertices by exact coordinates (+0.0 folds -0.0 into 0.0); keep only those
    // that triangles use.
    let mut ids: HashMap<[u64; 3], u32> = HashMap::new();
    let mut remap = vec![u32::MAX; positions.len()];
    let mut vertices = Vec::new();
    let mut tris = Vec::with_capacity(triangles.len());
    for tri in triangles {
        let mut t = [0u32; 3];
        for (k, &i) in tri.iter().enumerate() {
            let Some(&p) = positions.get(i as usize) else {
                return Err(format!("has a triangle using missing vertex {}", i + 1));
            };
            if remap[i as usize] == u32::MAX {
                let key = (p + Vec3::ZERO).to_array().map(f64::to_bits);
                remap[i as usize] = *ids.entry(key).or_insert_with(|| {
                    vertices.push(p);
                    (vertices.len() - 1) as u32
                });
            }
            t[k] = remap[i as usize];
        }
        if t[0] != t[1] && t[1] != t[2] && t[2] != t[0] {
            tris.push(t);
        }
    }
    if tris.is_empty() {
        return Err("contains no triangles".into());
    }

    Ok((vertices, tris))
}
