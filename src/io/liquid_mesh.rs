//! The liquid's surface as a closed triangle mesh (feature `surface`): Naive Surface Nets
//! (`fast-surface-nets`) on the liquid signed distance, clipped by the solids and closed at
//! the tank walls.
//!
//! The distance is sampled `samples` times per cell along each axis over the box of cells
//! that holds the liquid: the step's φ_L (the particles' distance minus their radius),
//! interpolated, then max(φ, −φ_solid) for every body and obstacle, so no surface lies inside
//! a solid. Two samples of padding close the mesh: past a wall, minus the sample inside (the
//! surface crosses on the wall, and the vertices of the cubes across it move onto it); past
//! the liquid's box, air. Surface nets leave two defects that a closed mesh cannot have, and
//! both are repaired: a lattice face with liquid on one diagonal and air on the other would
//! join two cubes by an edge in four triangles (its mean decides which sign wins, and a corner
//! moves across zero), and two sheets meeting in one cube share its vertex (it is split
//! into one per fan). The triangles face out of the liquid.
//!
//! The enclosed volume follows φ_L, not the particles: where the liquid thins to a sheet one
//! cell deep, φ_L (and the pressure solve's liquid cells) holds more than the particles'
//! volume, and so does the mesh.

use crate::geometry::mesh::{link_fans, placed_surface};
use crate::math::Vec3;
use crate::world::Simulation;
use fast_surface_nets::ndshape::{RuntimeShape, Shape};
use fast_surface_nets::{surface_nets, SurfaceNetsBuffer};
use rayon::prelude::*;

pub use crate::geometry::mesh::TriangleMesh;

/// Each body's surface where it is now, in world coordinates.
pub fn body_surfaces(sim: &Simulation) -> Vec<TriangleMesh> {
    sim.bodies().iter().map(|b| placed_surface(&b.shape, &b.pose())).collect()
}

/// The liquid surface of `sim` now, with `samples` distance samples per cell along each axis
/// (1 or more; 2 is the default of `output.surface_samples`).
///
/// The distance is the step's φ_L at cell centres (the particles' distance minus their
/// radius, which puts a freshly seeded flat surface exactly on its cell face), interpolated
/// trilinearly to the finer lattice. Outside the tank, a sample next to liquid takes minus the
/// value inside it, so the surface crosses exactly on the wall. With the soft surface the
/// step makes φ_L's values two cells deep only after
/// [`Simulation::set_interior_values`] (the CLI sets it when it writes meshes): without, a
/// cell more than a cell deep beside a diagonal neighbour of air holds the deep value, and
/// the mesh there moves by a fraction of a cell.
pub fn liquid_surface(sim: &Simulation, samples: usize) -> TriangleMesh {
    let grid = *sim.grid();
    let r = samples.max(1);
    let h = grid.dx / r as f64;
    // The step's φ_L when there was a step (extended into the solids, which the clipping
    // below undoes), else the particles' now.
    let phi = if sim.steps_taken() > 0 { sim.liquid_phi().to_vec() } else { sim.particle_phi() };
    // The lattice covers the liquid's cells and one more on each side (air, or a wall).
    let Some((lo, hi)) = liquid_bounds(&phi, grid.n) else {
        return TriangleMesh::default();
    };
    let wall = [0, 1, 2].map(|a| [lo[a] == 0, hi[a] + 1 == grid.n[a]]);
    // Samples at the centres of a lattice r times finer over those cells, padded by two
    // samples (the surface nets make no faces on the last layer): lattice index i on axis a
    // is at ((i − 2 + origin) + ½)·h.
    let origin = lo.map(|l| (r * l) as f64 - 1.5);
    let n = [0, 1, 2].map(|a| (r * (hi[a] + 1 - lo[a]) + 4) as u32);
    let shape = RuntimeShape::<u32, 3>::new(n);
    let node_sdf = &sim.statics().node_sdf;
    let obstacles = node_sdf.has_solids();
    let point =
        |ijk: [u32; 3]| Vec3::from_array([0, 1, 2].map(|a| (ijk[a] as f64 + origin[a]) * h));
    // Cells away from the surface (all of their 3³ neighbours of one kind) are liquid or air
    // through and through: their samples need no interpolation.
    let mixed = mixed_cells(&phi, grid.n);
    // Per axis and lattice index: the sample's cell, and its trilinear cells and weight in
    // the cell-centred φ (the lattice is axis-aligned, so the interpolation separates).
    let tables: [Vec<(usize, usize, usize, f64)>; 3] = [0, 1, 2].map(|a| {
        let top = (grid.n[a] - 1) as f64;
        (0..n[a] as usize)
            .map(|i| {
                let cell = i.saturating_sub(2) / r + lo[a];
                let g = ((i as f64 + origin[a]) * h / grid.dx - 0.5).clamp(0.0, top);
                let i0 = (g as usize).min(grid.n[a].saturating_sub(2));
                let i1 = (i0 + 1).min(grid.n[a] - 1);
                (cell.min(grid.n[a] - 1), i0, i1, g - i0 as f64)
            })
            .collect()
    });
    let (n0, n01) = (grid.n[0], grid.n[0] * grid.n[1]);
    let value = |ijk: [u32; 3]| {
        let [tx, ty, tz] = [0, 1, 2].map(|a| tables[a][ijk[a] as usize]);
        let c = tx.0 + n0 * ty.0 + n01 * tz.0;
        if !(mixed[c] || obstacles) {
            return if phi[c] < 0.0 { -h } else { h };
        }
        // Trilinear, as `Lattice::sample` computes it.
        let row = |j: usize, k: usize| {
            let b = j * n0 + k * n01;
            phi[b + tx.1] * (1.0 - tx.3) + phi[b + tx.2] * tx.3
        };
        let plane = |k: usize| row(ty.1, k) * (1.0 - ty.3) + row(ty.2, k) * ty.3;
        let v = plane(tz.1) * (1.0 - tz.3) + plane(tz.2) * tz.3;
        if obstacles {
            v.max(-node_sdf.sample(&grid, point(ijk)))
        } else {
            v
        }
    };
    let slab = (n[0] * n[1]) as usize;
    let mut sdf = vec![0f32; shape.usize()];
    sdf.par_chunks_mut(slab).enumerate().for_each(|(k, plane)| {
        for j in 0..n[1] {
            for i in 0..n[0] {
                let ijk = [i, j, k as u32];
                let outside = [0, 1, 2].map(|a| ijk[a] < 2 || ijk[a] + 2 >= n[a]);
                let v = match outside.iter().filter(|&&o| o).count() {
                    0 => value(ijk),
                    // The sample just past a wall, beside liquid: minus the one inside it, so
                    // the surface crosses on the wall.
                    1 => {
                        let a = outside.iter().position(|&o| o).expect("one axis outside");
                        let (near, far_side) = (ijk[a] == 1, ijk[a] == n[a] - 2);
                        if (near && wall[a][0]) || (far_side && wall[a][1]) {
                            let mut q = ijk;
                            q[a] = if near { 2 } else { n[a] - 3 };
                            let v = value(q);
                            if v < 0.0 {
                                -v
                            } else {
                                h
                            }
                        } else {
                            h
                        }
                    }
                    _ => h,
                };
                plane[(i + n[0] * j) as usize] = v as f32;
            }
        }
    });
    // Clip by the bodies, over their bounds only.
    for b in sim.bodies() {
        let (blo, bhi) = b.bounds();
        let (blo, bhi) = (blo.to_array(), bhi.to_array());
        let range = [0, 1, 2].map(|a| {
            let first = (blo[a] / h - origin[a]).floor().max(2.0) as u32;
            let last = ((bhi[a] / h - origin[a]).ceil().max(0.0) as u32 + 1).min(n[a] - 2);
            first..last
        });
        for k in range[2].clone() {
            for j in range[1].clone() {
                for i in range[0].clone() {
                    let s = &mut sdf[shape.linearize([i, j, k]) as usize];
                    *s = s.max(-b.sdf(point([i, j, k])) as f32);
                }
            }
        }
    }
    resolve_saddles(&mut sdf, n, h as f32);
    let mut buffer = SurfaceNetsBuffer::default();
    surface_nets(&sdf, &shape, [0; 3], n.map(|x| x - 1), &mut buffer);
    // A vertex in a cube that straddles a wall (its samples 1 and 2 along an axis, the wall
    // halfway) moves onto the wall: surface nets would put it at the mean of its crossings,
    // cutting the tank's edges and corners off the liquid.
    let vertices: Vec<Vec3> = buffer
        .positions
        .iter()
        .map(|p| {
            Vec3::from_array([0, 1, 2].map(|a| {
                let x = p[a] as f64;
                let on_wall = if x < 2.0 && wall[a][0] {
                    Some(1.5)
                } else if x > (n[a] - 3) as f64 && wall[a][1] {
                    Some(n[a] as f64 - 2.5)
                } else {
                    None
                };
                (on_wall.unwrap_or(x) + origin[a]) * h
            }))
        })
        .collect();
    let mut mesh = TriangleMesh {
        vertices,
        triangles: buffer.indices.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect(),
    };
    let strides = [1usize, n[0] as usize, (n[0] * n[1]) as usize];
    let sheets: Vec<bool> = buffer
        .surface_strides
        .iter()
        .map(|&p| {
            let mask = (0..8).fold(0u8, |m, c| {
                let q = p as usize + (0..3).map(|a| ((c >> a) & 1) * strides[a]).sum::<usize>();
                m | (u8::from(sdf[q] < 0.0) << c)
            });
            MANY_SHEETS[mask as usize]
        })
        .collect();
    split_fans(&mut mesh, &sheets);
    if mesh.volume() < 0.0 {
        for t in &mut mesh.triangles {
            t.swap(1, 2);
        }
    }
    mesh
}

/// The smallest box of cells holding every liquid cell (φ < 0) and one more cell on each
/// side, within the grid; none without liquid.
fn liquid_bounds(phi: &[f64], n: [usize; 3]) -> Option<([usize; 3], [usize; 3])> {
    let (mut lo, mut hi) = ([usize::MAX; 3], [0; 3]);
    for (c, _) in phi.iter().enumerate().filter(|(_, &p)| p < 0.0) {
        let ijk = [c % n[0], (c / n[0]) % n[1], c / (n[0] * n[1])];
        for a in 0..3 {
            lo[a] = lo[a].min(ijk[a]);
            hi[a] = hi[a].max(ijk[a]);
        }
    }
    (lo[0] != usize::MAX)
        .then(|| (lo.map(|l| l.saturating_sub(1)), [0, 1, 2].map(|a| (hi[a] + 1).min(n[a] - 1))))
}

/// Whether each cell or one of its 26 neighbours differs from it in sign: bit 1 marks liquid
/// and bit 2 air in the neighbourhood, spread one cell along x, then y, then z.
fn mixed_cells(phi: &[f64], n: [usize; 3]) -> Vec<bool> {
    let mut kind: Vec<u8> = phi.iter().map(|&p| if p < 0.0 { 1 } else { 2 }).collect();
    let stride = [1, n[0], n[0] * n[1]];
    for a in 0..3 {
        let before = kind.clone();
        for (c, k) in kind.iter_mut().enumerate() {
            let i = (c / stride[a]) % n[a];
            if i > 0 {
                *k |= before[c - stride[a]];
            }
            if i + 1 < n[a] {
                *k |= before[c + stride[a]];
            }
        }
    }
    kind.into_iter().map(|k| k == 3).collect()
}

/// Removes the lattice faces whose corners alternate in sign (liquid on one diagonal, air on
/// the other). Surface nets would join the two cubes beside such a face by an edge in four
/// triangles; here the face's centre value (the mean of its corners, the bilinear
/// interpolant there) decides whether the liquid joins across it, and the corner of the other
/// sign nearest zero moves across, to a tenth of its distance on the other side, which moves
/// the surface by less than that corner's distance. A move can make a neighbouring face
/// alternate, so the faces around each moved corner are looked at again until none does.
fn resolve_saddles(sdf: &mut [f32], n: [u32; 3], h: f32) {
    let n = n.map(|x| x as usize);
    let stride = [1, n[0], n[0] * n[1]];
    // The face spanned by axes AXES[f] at lattice point p has corners p, p + a, p + a + b,
    // p + b.
    const AXES: [(usize, usize); 3] = [(0, 1), (1, 2), (2, 0)];
    let corners = |p: usize, f: usize| {
        let (a, b) = AXES[f];
        [p, p + stride[a], p + stride[a] + stride[b], p + stride[b]]
    };
    let alternates = |sdf: &[f32], p: usize, f: usize| {
        let s = corners(p, f).map(|i| sdf[i] < 0.0);
        s[0] == s[2] && s[1] == s[3] && s[0] != s[1]
    };
    // One scan of every face, then only the faces around the corners that moved.
    let mut found: Vec<(usize, usize)> = {
        let sdf = &*sdf;
        (0..n[2] - 1)
            .into_par_iter()
            .flat_map_iter(|k| {
                let mut out = Vec::new();
                for j in 0..n[1] - 1 {
                    let row = stride[1] * j + stride[2] * k;
                    for p in row..row + n[0] - 1 {
                        let s0 = sdf[p] < 0.0;
                        let sx = sdf[p + stride[0]] < 0.0;
                        let sy = sdf[p + stride[1]] < 0.0;
                        let sz = sdf[p + stride[2]] < 0.0;
                        let alt = |a: bool, b: bool, ab: usize| {
                            a == b && a != s0 && (sdf[ab] < 0.0) == s0
                        };
                        if alt(sx, sy, p + stride[0] + stride[1]) {
                            out.push((p, 0));
                        }
                        if alt(sy, sz, p + stride[1] + stride[2]) {
                            out.push((p, 1));
                        }
                        if alt(sz, sx, p + stride[2] + stride[0]) {
                            out.push((p, 2));
                        }
                    }
                }
                out
            })
            .collect()
    };
    // A corner moves at most once, so the repair ends: a face whose losing corners have all
    // moved keeps the sign of its mean by moving a corner of the other sign instead.
    let mut moved = std::collections::HashSet::new();
    while !found.is_empty() {
        let mut next = Vec::new();
        for (p, f) in std::mem::take(&mut found) {
            if !alternates(sdf, p, f) {
                continue;
            }
            let c = corners(p, f);
            let liquid_joins = c.iter().map(|&i| sdf[i]).sum::<f32>() < 0.0;
            // The unmoved corner of the losing sign nearest zero, else of the other sign.
            let pick = |losing: bool| {
                c.iter()
                    .copied()
                    .filter(|i| ((sdf[*i] < 0.0) != liquid_joins) == losing && !moved.contains(i))
                    .min_by(|&x, &y| sdf[x].abs().total_cmp(&sdf[y].abs()))
            };
            let Some(m) = pick(true).or_else(|| pick(false)) else {
                continue;
            };
            // A tenth of its distance across: not onto zero, where the cubes around the
            // corner would all put their vertex on it, one point.
            let across = (0.1 * sdf[m].abs()).max(1e-4 * h);
            sdf[m] = if sdf[m] < 0.0 { across } else { -across };
            moved.insert(m);
            // The twelve faces with m as a corner.
            let ijk = [m % n[0], (m / n[0]) % n[1], m / stride[2]];
            for (g, &(a, b)) in AXES.iter().enumerate() {
                for (da, db) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    if ijk[a] >= da
                        && ijk[b] >= db
                        && ijk[a] - da + 1 < n[a]
                        && ijk[b] - db + 1 < n[b]
                    {
                        next.push((m - da * stride[a] - db * stride[b], g));
                    }
                }
            }
        }
        next.sort_unstable();
        next.dedup();
        found = next;
    }
}

/// Per cube corner sign pattern (bit c: corner c = x + 2y + 4z is liquid): whether the
/// surface may cross the cube in more than one sheet, that is whether the liquid corners or
/// the air corners fall apart into two or more groups joined by cube edges (a face with
/// alternating corners always splits one of the two). Otherwise its vertex has one fan.
const MANY_SHEETS: [bool; 256] = {
    let mut table = [false; 256];
    let mut mask = 0;
    while mask < 256 {
        let mut sign = 0;
        while sign < 2 {
            // Corners of this sign, joined through edges (corners one bit apart).
            let set = if sign == 0 { mask } else { !mask & 0xff };
            let mut seen = 0;
            let mut groups = 0;
            let mut c = 0;
            while c < 8 {
                if set & (1 << c) != 0 && seen & (1 << c) == 0 {
                    groups += 1;
                    let mut front = 1 << c;
                    seen |= front;
                    while front != 0 {
                        let mut next = 0;
                        let mut d = 0;
                        while d < 8 {
                            if front & (1 << d) != 0 {
                                let mut a = 0;
                                while a < 3 {
                                    let e = d ^ (1 << a);
                                    if set & (1 << e) != 0 && seen & (1 << e) == 0 {
                                        seen |= 1 << e;
                                        next |= 1 << e;
                                    }
                                    a += 1;
                                }
                            }
                            d += 1;
                        }
                        front = next;
                    }
                }
                c += 1;
            }
            if groups > 1 {
                table[mask] = true;
            }
            sign += 1;
        }
        mask += 1;
    }
    table
};

/// Gives each fan of triangles around a vertex its own vertex: surface nets put one vertex in
/// each lattice cube, so two sheets of liquid meeting in one cube (at its opposite corners)
/// share a vertex. The copies move a hundredth of the way towards their fan's centre, so no
/// two fans touch. Only the vertices `candidate` marks are looked at (the others are known
/// to have one fan).
fn split_fans(mesh: &mut TriangleMesh, candidate: &[bool]) {
    let nv = mesh.vertices.len();
    if !candidate.iter().any(|&c| c) {
        return;
    }
    // Triangle corners by vertex (compressed rows).
    let mut start = vec![0usize; nv + 1];
    for t in &mesh.triangles {
        for &v in t {
            start[v as usize + 1] += 1;
        }
    }
    for v in 0..nv {
        start[v + 1] += start[v];
    }
    let mut fill = start.clone();
    let mut corners = vec![(0u32, 0u8); start[nv]];
    for (ti, t) in mesh.triangles.iter().enumerate() {
        for (k, &v) in t.iter().enumerate() {
            corners[fill[v as usize]] = (ti as u32, k as u8);
            fill[v as usize] += 1;
        }
    }
    for v in (0..nv).filter(|&v| candidate[v]) {
        let around = &corners[start[v]..start[v + 1]];
        // The link of v: each triangle's edge opposite v.
        let link: Vec<(u32, u32)> = around
            .iter()
            .map(|&(t, k)| {
                let t = mesh.triangles[t as usize];
                (t[(k as usize + 1) % 3], t[(k as usize + 2) % 3])
            })
            .collect();
        let (fan, fans) = link_fans(&link);
        if fans < 2 {
            continue;
        }
        let p = mesh.vertices[v];
        for f in 0..fans {
            let members: Vec<usize> = (0..around.len()).filter(|&c| fan[c] == f).collect();
            let centre = members
                .iter()
                .map(|&c| mesh.vertices[link[c].0 as usize] + mesh.vertices[link[c].1 as usize])
                .sum::<Vec3>()
                / (2 * members.len()) as f64;
            let q = p + 0.01 * (centre - p);
            let id = if f == 0 {
                mesh.vertices[v] = q;
                v as u32
            } else {
                mesh.vertices.push(q);
                (mesh.vertices.len() - 1) as u32
            };
            for &c in &members {
                let (t, k) = around[c];
                mesh.triangles[t as usize][k as usize] = id;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two tetrahedra touching at one vertex: the vertex becomes two, one per fan, each
    /// moved towards its own tetrahedron; the volume is kept to the move's size.
    #[test]
    fn a_vertex_joining_two_fans_is_split() {
        let p = |x: f64, y: f64, z: f64| Vec3::new(x, y, z);
        let vertices = vec![
            p(0.0, 0.0, 0.0),
            p(1.0, 0.0, 0.0),
            p(0.0, 1.0, 0.0),
            p(0.0, 0.0, 1.0),
            p(-1.0, 0.0, 0.0),
            p(0.0, -1.0, 0.0),
            p(0.0, 0.0, -1.0),
        ];
        let tet = |a: u32, b: u32, c: u32, d: u32| [[a, c, b], [a, b, d], [a, d, c], [b, c, d]];
        let mut triangles = tet(0, 1, 2, 3).to_vec();
        triangles.extend(tet(0, 4, 6, 5));
        let mut mesh = TriangleMesh { vertices, triangles };
        let volume = mesh.volume();
        split_fans(&mut mesh, &[true; 7]);
        assert_eq!(mesh.vertices.len(), 8);
        let uses = |v: u32| mesh.triangles.iter().filter(|t| t.contains(&v)).count();
        assert_eq!((uses(0), uses(7)), (3, 3));
        assert!(mesh.vertices[0].x > 0.0 && mesh.vertices[7].x < 0.0, "{:?}", mesh.vertices);
        assert!((mesh.volume() - volume).abs() < 0.02 * volume.abs());
        assert_eq!(mesh.open_edges(), 0);
    }

    /// A lattice face with liquid on one diagonal and air on the other is resolved by its
    /// mean: the corner nearest zero of the losing sign crosses over, and no face alternates.
    #[test]
    fn alternating_faces_are_resolved_by_their_mean() {
        let n = [3u32, 3, 3];
        let mut sdf = vec![1.0f32; 27];
        let at = |i: usize, j: usize, k: usize| i + 3 * j + 9 * k;
        // The face k = 1 spanned by (1,1)…(2,2): liquid at (1,1) and (2,2), air (0.1 and 0.5)
        // at (2,1) and (1,2); its mean is negative, so the liquid joins across it and the air
        // corner nearest zero becomes liquid.
        sdf[at(1, 1, 1)] = -1.0;
        sdf[at(2, 2, 1)] = -1.0;
        sdf[at(2, 1, 1)] = 0.1;
        sdf[at(1, 2, 1)] = 0.5;
        resolve_saddles(&mut sdf, n, 1.0);
        assert!((sdf[at(2, 1, 1)] + 0.01).abs() < 1e-6, "{}", sdf[at(2, 1, 1)]);
        assert_eq!(sdf[at(1, 2, 1)], 0.5);
    }
}
