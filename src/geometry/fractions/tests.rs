//! Thin solids: how finely a body is sampled for its thickness, a thin plate's fractions
//! holding its volume at any pose, and thin static plates sealed watertight at any
//! orientation while thick solids keep their volume fractions.

use super::static_faces::volume_weights;
use super::*;
use crate::geometry::body::RigidBody;
use crate::geometry::grid::Grid;
use crate::geometry::shape::Solid;
use crate::math::{Pose, Rotation, SharedShape, Vec3};

/// Deterministic numbers in [0, 1).
fn lcg(state: &mut u64) -> f64 {
    *state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    (*state >> 11) as f64 / (1u64 << 53) as f64
}

fn random_unit(state: &mut u64) -> Vec3 {
    let z = 2.0 * lcg(state) - 1.0;
    let a = std::f64::consts::TAU * lcg(state);
    let r = (1.0 - z * z).sqrt();
    Vec3::new(r * a.cos(), r * a.sin(), z)
}

#[test]
fn thick_bodies_keep_the_half_cell_sampling() {
    let dx = 0.05;
    for (cells, r) in [(4.0, 2), (0.5, 2), (0.49, 4), (0.25, 4), (0.2, 8), (0.1, 16), (0.01, 16)] {
        assert_eq!(samples_per_cell(cells * dx, dx), r, "{cells} cells");
    }
}

/// A quarter-cell plate at 20 poses: its fractions hold its whole volume (the volume
/// correction's λ within ±1), which sampling every dx/2 misses for most of them.
#[test]
fn thin_plates_keep_their_volume_at_any_pose() {
    let grid = Grid { n: [16, 16, 16], dx: 0.05 };
    let mut state = 7;
    let (mut worst, mut worst_coarse) = (0.0f64, 0.0f64);
    for _ in 0..20 {
        let x = Vec3::new(0.35, 0.35, 0.35)
            + 0.1 * Vec3::new(lcg(&mut state), lcg(&mut state), lcg(&mut state));
        let q = Rotation::from_axis_angle(random_unit(&mut state), 3.0 * lcg(&mut state));
        let shape = SharedShape::cuboid(0.15, 0.25 * grid.dx / 2.0, 0.1);
        let b = RigidBody::with_density("plate".into(), shape, Pose::from_parts(x, q), 1000.0);
        assert_eq!(b.samples_per_cell(grid.dx), 8);
        worst = worst.max(b.face_fractions(&grid).volume_error(&grid, b.volume()));
        let coarse = body_faces(&grid, b.bounds(), |p| b.sdf(p), Some(b.volume()), SUBSAMPLE);
        worst_coarse = worst_coarse.max(coarse.volume_error(&grid, b.volume()));
    }
    // Measured 7e-16 against 0.81 sampled every dx/2.
    assert!(worst < 1e-14, "volume error {worst:e}");
    assert!(worst_coarse > 0.3, "every dx/2 the plate's volume is missed by {worst_coarse}");
}

/// Whether the open faces `w` join a cell on the − side of the plane n·x = d − t/2 to one
/// on the + side of n·x = d + t/2 (a breadth-first walk over cells).
fn leaks(grid: &Grid, w: &[Vec<f64>; 3], n: Vec3, d: f64, t: f64) -> bool {
    let cells = grid.cells();
    let side = |c: usize| {
        let [i, j, k] = cells.ijk(c);
        n.dot(cells.position(i, j, k)) - d
    };
    let mut seen = vec![false; cells.len()];
    let mut queue: Vec<usize> = (0..cells.len()).filter(|&c| side(c) < -t / 2.0).collect();
    for &c in &queue {
        seen[c] = true;
    }
    while let Some(c) = queue.pop() {
        if side(c) > t / 2.0 {
            return true;
        }
        let ijk = cells.ijk(c);
        for axis in 0..3 {
            let lat = grid.faces(axis);
            for step in [0, 1] {
                let mut f = ijk;
                f[axis] += step;
                if w[axis][lat.index(f[0], f[1], f[2])] <= 0.0 {
                    continue;
                }
                let (minus, plus) = grid.face_cells(axis, f);
                if let Some(o) = if step == 0 { minus } else { plus } {
                    if !seen[o] {
                        seen[o] = true;
                        queue.push(o);
                    }
                }
            }
        }
    }
    false
}

/// A static plate across the whole tank, 0.05 to 1.9 cells thick, at 40 random
/// orientations and offsets: no path of open faces crosses it. By volume fractions alone
/// most of them leak.
#[test]
fn thin_static_plates_are_watertight_at_any_orientation() {
    let grid = Grid { n: [12, 12, 12], dx: 1.0 / 12.0 };
    let centre = Vec3::splat(0.5);
    let mut state = 11;
    let mut leaky_by_volume = 0;
    for case in 0..40 {
        let n = random_unit(&mut state);
        let t = grid.dx * (0.05 + 1.85 * lcg(&mut state));
        let p = centre + grid.dx * (lcg(&mut state) - 0.5) * n;
        let plate = Solid::new(
            SharedShape::cuboid(2.0, t / 2.0, 2.0),
            Pose::from_parts(p, Rotation::from_rotation_arc(Vec3::Y, n)),
        );
        assert!(is_thin(&grid, &plate), "case {case}: t = {t}");
        let d = n.dot(p);
        let w = face_weights(&grid, std::slice::from_ref(&plate));
        assert!(!leaks(&grid, &w, n, d, t), "case {case}: n {n:?}, t {t}");
        leaky_by_volume += usize::from(leaks(&grid, &volume_weights(&grid, &[plate]), n, d, t));
    }
    // Measured 40 of 40.
    assert!(leaky_by_volume >= 30, "{leaky_by_volume} of 40 leak by volume fractions");
}

/// Solids with a part 2 cells across or more keep their volume fractions exactly.
#[test]
fn thick_static_solids_keep_their_volume_fractions() {
    let grid = Grid { n: [12, 12, 12], dx: 1.0 / 12.0 };
    let tilt = Rotation::from_axis_angle(Vec3::new(0.3, 1.0, 0.2).normalize(), 0.6);
    let at = Vec3::new(0.47, 0.52, 0.49);
    for (shape, thin) in [
        (SharedShape::ball(2.2 * grid.dx), false),
        (SharedShape::cuboid(0.3, 1.1 * grid.dx, 0.3), false),
        (SharedShape::cuboid(0.3, 0.9 * grid.dx, 0.3), true),
        (SharedShape::ball(0.5 * grid.dx), true),
    ] {
        let s = Solid::new(shape, Pose::from_parts(at, tilt));
        assert_eq!(is_thin(&grid, &s), thin, "{s:?}");
        if !thin {
            let solids = [s];
            assert_eq!(face_weights(&grid, &solids), volume_weights(&grid, &solids));
        }
    }
}
