//! An open surface thickened into a closed shell: two sheets offset along the vertex
//! normals, joined along the boundary.

use crate::math::Vec3;
use std::collections::HashMap;

/// A triangle mesh: vertices and triangles.
pub(super) type Surface = (Vec<Vec3>, Vec<[u32; 3]>);

/// The closed surface of an open one thickened by `thickness`: vertices offset by ±t/2 along
/// their area-weighted normals, the − sheet wound the other way, each boundary edge joined
/// by a quad. None when the surface has no boundary edge (it is closed). Errors: an edge in
/// more than two triangles, or wound the same way by two.
pub(super) fn shell_mesh(
    vertices: &[Vec3],
    tris: &[[u32; 3]],
    thickness: f64,
) -> Result<Option<Surface>, String> {
    let mut directed: HashMap<(u32, u32), u32> = HashMap::new();
    let mut undirected: HashMap<(u32, u32), u32> = HashMap::new();
    for t in tris {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            *directed.entry((a, b)).or_insert(0) += 1;
            *undirected.entry((a.min(b), a.max(b))).or_insert(0) += 1;
        }
    }
    if undirected.values().any(|&n| n > 2) {
        return Err("is not a surface: an edge is shared by more than two triangles".into());
    }
    if directed.values().any(|&n| n > 1) {
        return Err("has inconsistent orientation: neighbouring triangles must wind the \
                    same way"
            .into());
    }
    let mut boundary: Vec<(u32, u32)> =
        directed.keys().copied().filter(|&(a, b)| !directed.contains_key(&(b, a))).collect();
    if boundary.is_empty() {
        return Ok(None);
    }
    boundary.sort_unstable();
    let n = vertices.len();
    let mut normals = vec![Vec3::ZERO; n];
    for t in tris {
        let [a, b, c] = t.map(|i| vertices[i as usize]);
        let area_normal = (b - a).cross(c - a);
        for &i in t {
            normals[i as usize] += area_normal;
        }
    }
    let h = 0.5 * thickness;
    let mut out: Vec<Vec3> = Vec::with_capacity(2 * n);
    out.extend(vertices.iter().zip(&normals).map(|(v, m)| *v + h * m.normalize_or_zero()));
    out.extend(vertices.iter().zip(&normals).map(|(v, m)| *v - h * m.normalize_or_zero()));
    let m = n as u32;
    let mut faces: Vec<[u32; 3]> = Vec::with_capacity(2 * tris.len() + 2 * boundary.len());
    faces.extend(tris.iter().copied());
    faces.extend(tris.iter().map(|&[a, b, c]| [m + a, m + c, m + b]));
    for (a, b) in boundary {
        faces.push([b, a, m + a]);
        faces.push([b, m + a, m + b]);
    }
    Ok(Some((out, faces)))
}
