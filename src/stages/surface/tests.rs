//! The particle stage's tests: the forward maps, and each adjoint against central
//! differences.

use super::*;
use crate::geometry::body::RigidBody;
use crate::geometry::fractions::NodeSdf;
use crate::geometry::grid::{Grid, Mac};
use crate::geometry::shape::Solid;
use crate::math::{Pose, Vec3};

/// The forward maps.
mod forward {
    use super::*;

    /// Scattered particles, some on the tank's faces and edges.
    fn scattered(grid: &Grid, n: usize) -> Vec<Vec3> {
        let size = grid.size();
        (0..n)
            .map(|i| {
                let r = |k: usize| ((i * 7919 + k * 104_729) % 10_007) as f64 / 10_006.0;
                let edge = |t: f64| if i % 97 == 0 { t.round() } else { t };
                Vec3::new(edge(r(1)) * size.x, r(2) * size.y, edge(r(3)) * size.z)
            })
            .collect()
    }

    #[test]
    fn liquid_sdf_is_the_nearest_particles_distance_up_to_two_cells() {
        // Sparse: most cells find their nearest particle one or two cells away, or none.
        let grid = Grid { n: [11, 9, 10], dx: 0.1 };
        let pos = scattered(&grid, 60);
        let model = SurfaceModel {
            radius: 0.03,
            sparse_cells: false,
            sparse_depth: 0.0,
            softness: 0.0,
            per_axis: 2,
        };
        let bins = Bins::new(&pos, &grid);
        let (phi, who) = liquid_sdf_nearest(&pos, &bins, &[], &grid, &model, None, None);
        let cells = grid.cells();
        let mut rings = [0; 3];
        for c in 0..grid.num_cells() {
            let [i, j, k] = cells.ijk(c);
            let x = cells.position(i, j, k);
            let (d, p) = (0..pos.len())
                .map(|p| ((pos[p] - x).length(), p as u32))
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .expect("particles");
            if d <= 2.0 * grid.dx {
                rings[usize::from(d >= 0.5 * grid.dx) + usize::from(d > grid.dx)] += 1;
                assert_eq!((phi[c], who[c]), (d - model.radius, p), "cell {c}");
            } else {
                assert_eq!(
                    (phi[c], who[c]),
                    (2.0 * grid.dx - model.radius, crate::geometry::grid::NONE),
                    "cell {c}"
                );
            }
        }
        // Found in the own cell, within one cell and within two: every search ring is used.
        assert!(rings.iter().all(|&r| r >= 10), "{rings:?}");
    }

    /// The rings the search scans one after the other are the cells of the block it used
    /// to scan whole (the cell, then the 3³ block, then the 5³ block less its 44 far cells),
    /// each ring in lattice order.
    #[test]
    fn rings_partition_the_neighbour_block_in_lattice_order() {
        let grid = Grid { n: [7, 6, 5], dx: 0.1 };
        for c in 0..grid.num_cells() {
            let ijk = grid.cells().ijk(c);
            for reach in 1..=2 {
                let mut block = Vec::new();
                for_neighbour_cells(&grid, ijk, reach, |n| block.push(n));
                let mut rings = vec![c];
                for r in 1..=reach {
                    let mut ring = Vec::new();
                    for_ring_cells(&grid, ijk, r, |n| ring.push(n));
                    assert!(ring.windows(2).all(|w| w[0] < w[1]), "ring {r} of cell {c}");
                    rings.extend(ring);
                }
                rings.sort_unstable();
                assert_eq!(rings, block, "reach {reach} of cell {c}");
            }
        }
    }

    /// On particles exactly on the seeding lattice (ties everywhere: a cell's centre is as
    /// far from several of them), with holes and a splash above, φ and the particle it is the
    /// distance to are those of the whole-block scan the ring search replaced: the first
    /// nearest particle in lattice order, then in its cell's bin.
    #[test]
    fn ring_search_ties_as_the_block_scan_did() {
        let grid = Grid { n: [10, 9, 8], dx: 0.1 };
        let node_sdf = NodeSdf::new(&grid, &[]);
        let pool = Solid::aabb(Vec3::ZERO, Vec3::new(1.0, 0.4, 0.8));
        let mut pos = seed(&grid, &[pool], 8, &node_sdf, None);
        pos.retain(|x| (x.x * 40.0) as usize % 7 != 3 || x.y > 0.2);
        pos.extend([Vec3::new(0.55, 0.65, 0.35), Vec3::new(0.125, 0.775, 0.625)]);
        let model = SurfaceModel {
            radius: particle_radius(grid.dx, 2),
            sparse_cells: true,
            sparse_depth: 0.0,
            softness: 0.0,
            per_axis: 2,
        };
        let bins = Bins::new(&pos, &grid);
        let cells = grid.cells();
        let block_scan = |c: usize| {
            let ijk = cells.ijk(c);
            let x = cells.position(ijk[0], ijk[1], ijk[2]);
            let nearest = |reach: usize| {
                let mut best = (f64::MAX, crate::geometry::grid::NONE);
                for_neighbour_cells(&grid, ijk, reach, |n| {
                    for &p in bins.cell(n) {
                        let d = (pos[p as usize] - x).length_squared();
                        if d < best.0 {
                            best = (d, p);
                        }
                    }
                });
                (best.0.sqrt(), best.1)
            };
            let mut d = nearest(0);
            if d.0 >= 0.5 * grid.dx {
                d = nearest(1);
            }
            if d.0 > grid.dx {
                d = nearest(2);
                if d.0 > 2.0 * grid.dx {
                    d = (2.0 * grid.dx, crate::geometry::grid::NONE);
                }
            }
            let value = d.0 - model.radius;
            if value >= 0.0 && !bins.cell(c).is_empty() {
                (-1e-3 * grid.dx, crate::geometry::grid::NONE)
            } else {
                (value, d.1)
            }
        };
        let (phi, who) = liquid_sdf_nearest(&pos, &bins, &[], &grid, &model, None, None);
        let plain = liquid_sdf(&pos, &bins, &[], &grid, &model, None, None);
        let mut tied = 0;
        for c in 0..grid.num_cells() {
            let (value, p) = block_scan(c);
            assert_eq!((phi[c].to_bits(), who[c]), (value.to_bits(), p), "cell {c}");
            assert_eq!(plain[c].to_bits(), value.to_bits(), "cell {c}");
            if p != crate::geometry::grid::NONE {
                let [i, j, k] = cells.ijk(c);
                let d = (pos[p as usize] - cells.position(i, j, k)).length();
                tied += usize::from(
                    pos.iter().filter(|y| (**y - cells.position(i, j, k)).length() == d).count()
                        > 1,
                );
            }
        }
        assert!(tied > 100, "ties tested: {tied}");
    }

    #[test]
    fn bins_list_each_cells_particles_in_order_with_any_thread_count() {
        let grid = Grid { n: [7, 5, 9], dx: 0.1 };
        // More than two of the counting sort's chunks of 65,536.
        let pos = scattered(&grid, 150_000);
        let run = |t: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap();
            pool.install(|| Bins::new(&pos, &grid))
        };
        let (a, b) = (run(1), run(2));
        assert_eq!((&a.start, &a.items), (&b.start, &b.items));
        for c in 0..grid.num_cells() {
            let want: Vec<u32> =
                (0..pos.len() as u32).filter(|&p| cell_of(&grid, pos[p as usize]) == c).collect();
            assert_eq!(a.cell(c), &want[..], "cell {c}");
        }
    }

    #[test]
    fn deposit_is_the_serial_scatter_with_any_thread_count() {
        let grid = Grid { n: [6, 5, 8], dx: 0.1 };
        // More than two of the slab sort's chunks of 65,536.
        let mut pos = scattered(&grid, 140_000);
        // Two outside the tank, whose folded slabs are not adjacent.
        pos.insert(17, Vec3::new(0.21, 0.33, -0.25));
        pos.push(Vec3::new(0.43, 0.12, 1.06));
        let run = |t: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap();
            pool.install(|| particle_density(&pos, &grid, 8, None))
        };
        let (a, b) = (run(1), run(2));
        assert!(a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()));
        let mut serial = vec![0.0; grid.num_cells()];
        let mut terms = vec![0usize; grid.num_cells()];
        for x in &pos {
            let (idx, w, _) = deposit_weights(&grid, *x);
            for c in 0..8 {
                let (bi, bj, bk) = (c & 1, (c >> 1) & 1, (c >> 2) & 1);
                let cell = grid.cell(idx[0][bi], idx[1][bj], idx[2][bk]);
                serial[cell] += w[0][bi] * w[1][bj] * w[2][bk] / 8.0;
                terms[cell] += 1;
            }
        }
        // The slab pairs add in another order than one serial pass: the two sums of n
        // non-negative terms differ by at most n·ε times the sum.
        for ((x, y), n) in a.iter().zip(&serial).zip(&terms) {
            let bound = *n as f64 * f64::EPSILON * y;
            assert!((x - y).abs() <= bound, "{x} against {y} ({n} terms)");
        }
        let total: f64 = a.iter().sum();
        assert!((total - pos.len() as f64 / 8.0).abs() < 1e-9, "each particle deposits one unit");
    }

    #[test]
    fn radius_for_eight_per_cell() {
        let r = particle_radius(1.0, 2);
        assert!((r - (11f64.sqrt() + 3f64.sqrt()) / 8.0).abs() < 1e-14);
    }

    #[test]
    fn seeded_box_has_exact_volume_and_flat_surface() {
        use crate::geometry::shape::Solid;
        let grid = Grid { n: [8, 8, 8], dx: 0.125 };
        let region = Solid::aabb(Vec3::ZERO, Vec3::new(1.0, 0.5, 1.0));
        let sdf = NodeSdf::new(&grid, &[]);
        let pos = seed(&grid, &[region], 8, &sdf, None);
        assert_eq!(pos.len(), 8 * 8 * 4 * 8);
        let bins = Bins::new(&pos, &grid);
        let vol = liquid_volume(&pos, &grid, 8, None);
        assert!((vol - 0.5).abs() < 1e-12, "volume {vol}");
        let model = SurfaceModel {
            radius: particle_radius(grid.dx, 2),
            sparse_cells: true,
            sparse_depth: 0.0,
            softness: 0.0,
            per_axis: 2,
        };
        let phi = liquid_sdf(&pos, &bins, &[], &grid, &model, None, None);
        // Centres at y = 7/16 (below) and 9/16 (above) straddle the surface y = 0.5 evenly.
        let below = phi[grid.cell(3, 3, 3)];
        let above = phi[grid.cell(3, 4, 3)];
        assert!(below < 0.0 && above > 0.0);
        assert!((below / (below - above) - 0.5).abs() < 1e-12);
    }

    /// The continuous sparse-cell rule (`sparse_depth` > 0): a lone particle makes its cell
    /// liquid once it is that deep inside it, and moving it across a face moves φ
    /// continuously (the rule as it was switches a cell from air to liquid the moment it
    /// holds the particle).
    #[test]
    fn continuous_sparse_cells_are_liquid_inside_and_continuous_across_faces() {
        let grid = Grid { n: [8, 8, 8], dx: 0.1 };
        let radius = particle_radius(grid.dx, 2);
        let depth = 0.05;
        let sparse = SurfaceModel {
            radius,
            sparse_cells: true,
            sparse_depth: depth,
            softness: 0.0,
            per_axis: 2,
        };
        let jumping = SurfaceModel { sparse_depth: 0.0, ..sparse };
        let plain = SurfaceModel { sparse_cells: false, ..sparse };
        let phi_at = |x: Vec3, model: &SurfaceModel| {
            let pos = [x];
            liquid_sdf(&pos, &Bins::new(&pos, &grid), &[], &grid, model, None, None)
        };
        let (a, b) = (grid.cell(3, 4, 4), grid.cell(4, 4, 4));
        // Near a corner of cell a, 0.1 of a cell inside it, farther from its centre than the
        // particle radius: air by the distance, liquid by the rule (on its floor); cell b
        // stays air.
        let corner = Vec3::new(0.39, 0.49, 0.49);
        assert!(phi_at(corner, &plain)[a] > 0.0);
        let held = phi_at(corner, &sparse);
        assert_eq!(held[a], -distance::SPARSE_FLOOR * grid.dx);
        assert!(held[b] > 0.0);
        // Along a line through the face x = 0.4 between cells a and b, 0.042 off their
        // centres' line in y and z: every cell's φ moves by at most the rule's Lipschitz
        // constant (the distance's is 1) times the step, the rule sets φ somewhere on the
        // line, and both cells are air where the particle is within `depth` of the face.
        let lipschitz = ((0.5 * 3f64.sqrt() * grid.dx - radius) / (depth * grid.dx)).max(1.0);
        let h = 1e-5;
        let at = |n: usize| Vec3::new(0.38 + n as f64 * h, 0.492, 0.492);
        let mut last = phi_at(at(0), &sparse);
        let (mut ruled, mut worst) = (0, 0.0f64);
        for n in 1..=4000 {
            let phi = phi_at(at(n), &sparse);
            for c in 0..grid.num_cells() {
                worst = worst.max((phi[c] - last[c]).abs() / h);
            }
            ruled += usize::from(phi[a] < phi_at(at(n), &plain)[a]);
            last = phi;
        }
        assert!(worst <= lipschitz * (1.0 + 1e-6), "slope {worst} over {lipschitz}");
        assert!(ruled > 100, "the rule set cell a's φ in {ruled} samples");
        assert!(phi_at(at(0), &sparse)[a] < 0.0 && phi_at(at(4000), &sparse)[b] < 0.0);
        let face = phi_at(at(2000), &sparse);
        assert!(face[a] > 0.0 && face[b] > 0.0, "a particle on the face is air to both");
        // The rule as it was jumps there: the cell holding the particle is liquid.
        let jumped = phi_at(at(2000), &jumping);
        assert!(jumped[a].min(jumped[b]) < 0.0);
    }

    /// The soft minimum's particle radius puts a flat, freshly seeded surface on a cell
    /// face halfway between the centres that straddle it, as the nearest particle's does.
    #[test]
    fn soft_sdf_puts_a_seeded_flat_surface_on_its_face() {
        let grid = Grid { n: [11, 10, 11], dx: 0.1 };
        let off = sub_offsets(2);
        let mut pos = Vec::new();
        for k in 0..11 {
            for j in 0..7 {
                for i in 0..11 {
                    for &a in &off {
                        for &b in &off {
                            for &c in &off {
                                let p = Vec3::new(i as f64 + a, j as f64 + b, k as f64 + c);
                                pos.push(p * 0.1);
                            }
                        }
                    }
                }
            }
        }
        for tau in [0.05, 0.1, 0.25] {
            let model = SurfaceModel::soft(grid.dx, 2, tau);
            let phi = liquid_sdf(&pos, &Bins::new(&pos, &grid), &[], &grid, &model, None, None);
            // Away from the walls (the reach short of them).
            let (below, above) = (phi[grid.cell(5, 6, 5)], phi[grid.cell(5, 7, 5)]);
            assert!(below < 0.0 && above > 0.0, "τ {tau}: {below} {above}");
            assert!((below + above).abs() < 1e-12, "τ {tau}: θ off ½: {below} {above}");
            // Flat up to the walls and into the corners (the particles mirrored there).
            for (i, k) in [(0, 5), (10, 5), (0, 0), (10, 10), (1, 9)] {
                let wall = (phi[grid.cell(i, 6, k)], phi[grid.cell(i, 7, k)]);
                assert!((wall.0 - below).abs() < 1e-12, "τ {tau}: at ({i}, {k}): {wall:?}");
                assert!((wall.1 - above).abs() < 1e-12, "τ {tau}: at ({i}, {k}): {wall:?}");
            }
            // Deep in it a cell reads what a narrow band's deep cells are given.
            let deep = phi[grid.cell(5, 3, 5)];
            assert!(deep < below, "τ {tau}: {deep} not below {below}");
            assert!((deep - model.full_phi(grid.dx)).abs() < 1e-12, "τ {tau}: {deep}");
        }
    }

    /// The soft minimum's sum a row of block cells at a time (a centre whose block lies
    /// inside the tank) against the same sum a block cell at a time: scattered particles
    /// bunched in places, ghosts, and a band's deep cells beside both.
    #[test]
    fn soft_sdf_sums_rows_as_it_sums_cells() {
        use super::super::softmin::SoftSdf;
        let grid = Grid { n: [12, 10, 9], dx: 0.1 };
        let scatter = |n: usize, seed: usize, lo: Vec3, span: Vec3| -> Vec<Vec3> {
            (0..n)
                .map(|i| {
                    let f = |k: usize| ((i * k * 7919 + k * 104729 + seed) % 1000) as f64 / 1e3;
                    lo + span * Vec3::new(f(3), f(5), f(7))
                })
                .collect()
        };
        let mut pos = scatter(900, 0, Vec3::splat(0.0), Vec3::new(1.2, 0.7, 0.9));
        pos.extend(scatter(200, 11, Vec3::new(0.4, 0.3, 0.3), Vec3::splat(0.15)));
        let ghosts = scatter(150, 23, Vec3::new(0.5, 0.4, 0.2), Vec3::new(0.3, 0.3, 0.4));
        let cells = grid.num_cells();
        let band: Vec<bool> = (0..cells).map(|c| grid.cells().ijk(c)[1] < 3).collect();
        let model = SurfaceModel::soft(grid.dx, 2, 0.35);
        let bins = Bins::new(&pos, &grid);
        let mut inner = 0;
        for deep in [None, Some(band.as_slice())] {
            for g in [&[][..], &ghosts[..]] {
                let soft = SoftSdf::new(&pos, &bins, g, &grid, &model, deep);
                for c in 0..cells {
                    let ijk = grid.cells().ijk(c);
                    if !soft.is_inner(ijk) {
                        continue;
                    }
                    inner += 1;
                    let (rows, by_cell) = (soft.inner_sum(ijk), soft.walled_sum(ijk));
                    assert_eq!(rows.1, by_cell.1, "at {ijk:?}");
                    let diff = (rows.0 - by_cell.0).abs();
                    assert!(diff <= 1e-14 * by_cell.0, "at {ijk:?}: {rows:?} {by_cell:?}");
                }
            }
        }
        assert!(inner > 4 * 100, "too few centres read by rows: {inner}");
    }

    /// φ made only where a step reads its value (`Reads`) against φ made everywhere: a
    /// jittered block of liquid with a sloped surface, droplets above it, a band's deep
    /// cells below and a solid's neighbourhood in one corner. Every cell keeps its sign; the
    /// cells that hold the deep value are liquid at least a tenth of a cell deep by the
    /// full sum, have only liquid face neighbours and are not near the solid; every other
    /// cell has the same bits.
    #[test]
    fn soft_sdf_leaves_out_only_the_interior() {
        let grid = Grid { n: [14, 12, 10], dx: 0.1 };
        let off = sub_offsets(2);
        let mut pos = Vec::new();
        for c in 0..grid.num_cells() {
            let [i, j, k] = grid.cells().ijk(c);
            // A surface sloping from 6 to 9 cells high along x.
            if (j as f64) > 6.0 + 3.0 * i as f64 / 14.0 {
                continue;
            }
            for (s, (&a, (&b, &e))) in off.iter().zip(off.iter().zip(&off)).enumerate() {
                for t in 0..2 {
                    let jitter = |q: usize| ((c * 7919 + s * 104729 + t * 31 + q) % 97) as f64;
                    let o = Vec3::new(a, if t == 0 { b } else { 1.0 - b }, e)
                        + (Vec3::new(jitter(1), jitter(2), jitter(3)) / 97.0 - 0.5) * 0.3;
                    let q = Vec3::new(i as f64, j as f64, k as f64) + o;
                    pos.push(q * grid.dx);
                    pos.push(
                        (Vec3::new(i as f64, j as f64, k as f64) + Vec3::splat(1.0) - o) * grid.dx,
                    );
                }
            }
        }
        // Droplets over the surface.
        pos.extend((0..40).map(|i| Vec3::new(0.1 + 0.03 * i as f64, 1.05, 0.5)));
        let cells = grid.num_cells();
        let band: Vec<bool> = (0..cells).map(|c| grid.cells().ijk(c)[1] < 2).collect();
        let near: Vec<bool> = (0..cells)
            .map(|c| {
                let [i, j, k] = grid.cells().ijk(c);
                i >= 9 && j <= 4 && k >= 6
            })
            .collect();
        let model = SurfaceModel::soft(grid.dx, 2, 0.35);
        let deep_phi = model.full_phi(grid.dx);
        let bins = Bins::new(&pos, &grid);
        for deep in [None, Some(Deep { cells: &band, phi: deep_phi })] {
            let all = liquid_sdf(&pos, &bins, &[], &grid, &model, deep, None);
            let reads = Some(Reads { near_solids: &near });
            let (read, marks) = liquid_sdf_nearest(&pos, &bins, &[], &grid, &model, deep, reads);
            let mut left_out = 0;
            for c in 0..cells {
                let ijk = grid.cells().ijk(c);
                assert_eq!(all[c] < 0.0, read[c] < 0.0, "sign at {ijk:?}");
                if all[c].to_bits() == read[c].to_bits() {
                    continue;
                }
                left_out += 1;
                assert_eq!(read[c], deep_phi, "at {ijk:?}");
                assert_eq!(marks[c], crate::geometry::grid::NONE, "at {ijk:?}");
                assert!(all[c] < -0.1 * grid.dx, "at {ijk:?}: {}", all[c] / grid.dx);
                assert!(!near[c], "near the solid at {ijk:?}");
                for f in 0..6 {
                    if let Some(n) = grid.cells().neighbour(c, ijk, f / 2, f % 2) {
                        assert!(all[n] < 0.0, "air beside {ijk:?}");
                    }
                }
            }
            // Of 1,110 liquid cells, 700 are left out (507 with the band, whose deep cells
            // hold the deep value either way).
            let liquid = all.iter().filter(|p| **p < 0.0).count();
            eprintln!("{} band: {left_out} of {liquid} liquid cells left out", deep.is_some());
            assert!(left_out > 400, "only {left_out} cells left out");
        }
    }

    /// A lone particle moving out of a cell's reach: φ there is its soft distance (its
    /// distance less r, less τ·ln c_p, softly capped by the far value) and goes over
    /// continuously into the far value.
    #[test]
    fn soft_sdf_fades_continuously_as_a_particle_leaves() {
        let grid = Grid { n: [9, 5, 5], dx: 0.1 };
        let tau = 0.1 * grid.dx;
        let model = SurfaceModel::soft(grid.dx, 2, 0.1);
        let centre = grid.cells().position(2, 2, 2);
        let far = SOFT_REACH * grid.dx - model.radius;
        let offset = |d: f64| Vec3::new(d, 1e-3, -2e-3);
        let phi_at = |d: f64| {
            let pos = [centre + offset(d)];
            liquid_sdf(&pos, &Bins::new(&pos, &grid), &[], &grid, &model, None, None)
                [grid.cell(2, 2, 2)]
        };
        let samples: Vec<(f64, f64)> =
            (0..=2000).map(|s| 0.05 + 0.2 * s as f64 / 2000.0).map(|d| (d, phi_at(d))).collect();
        for w in samples.windows(2) {
            // |∂φ/∂d| is about 1 (the distance's) but where the cut-off bends it.
            assert!((w[1].1 - w[0].1).abs() < 3.0 * (w[1].0 - w[0].0), "a jump at {}", w[0].0);
        }
        for d in [0.06, 0.1, 0.15] {
            let len = offset(d).length();
            let c = (1.0 - len * len / 0.04).powi(3);
            let expected =
                -tau * (c * (-(len - model.radius) / tau).exp() + (-far / tau).exp()).ln();
            assert!((phi_at(d) - expected).abs() < 1e-12, "at {d}: {} vs {expected}", phi_at(d));
        }
        assert_eq!(phi_at(0.21), far, "beyond the reach: the far value");
    }
}

mod adjoint {
    //! Each particle-stage adjoint against central differences of its forward map, for a
    //! fixed linear functional of the output: ⟨∇L, d⟩ = (L(x + εd) − L(x − εd)) / 2ε.
    use super::*;
    use crate::math::{Rotation, SharedShape};

    fn grid() -> Grid {
        Grid { n: [8, 7, 6], dx: 0.1 }
    }

    /// Particles spread over the tank, away from lattice planes.
    fn particles(n: usize) -> Vec<Vec3> {
        (0..n)
            .map(|i| {
                let f = |k: usize| ((i * k * 7919 + k * 104729) % 1000) as f64 / 1000.0;
                Vec3::new(0.05 + 0.7 * f(3), 0.05 + 0.6 * f(5), 0.05 + 0.5 * f(7))
                    + Vec3::splat(1e-4)
            })
            .collect()
    }

    fn field(grid: &Grid, seed: usize) -> Mac {
        let mut u = Mac::zeros(grid);
        for a in 0..3 {
            for (f, x) in u.c[a].iter_mut().enumerate() {
                *x = (((f * 7919 + a * 131 + seed * 31) % 101) as f64 / 50.0 - 1.0) * 0.6 + 0.0123;
            }
        }
        u
    }

    fn dir(n: usize, seed: usize) -> Vec<Vec3> {
        (0..n)
            .map(|i| {
                let f = |k: usize| ((i * 31 + k * 17 + seed * 7) % 23) as f64 / 11.5 - 1.0;
                Vec3::new(f(1), f(2), f(3))
            })
            .collect()
    }

    fn dot(a: &[Vec3], b: &[Vec3]) -> f64 {
        a.iter().zip(b).map(|(x, y)| x.dot(*y)).sum()
    }

    /// For φ_L of `model` (beside the `deep` cells, whose φ is −0.05) at particles `p0`, the
    /// derivative of Σ φ̄·φ_L along `dp` by the adjoint and by central differences at 1e-7,
    /// with φ_L and the particles each cell's φ moves with.
    fn sdf_adjoint_and_fd(
        grid: &Grid,
        model: &SurfaceModel,
        deep: Option<&[bool]>,
        p0: &[Vec3],
        dp: &[Vec3],
        phi_bar: &[f64],
    ) -> (f64, f64, Vec<f64>, Vec<u32>) {
        let deep_of = || deep.map(|cells| Deep { cells, phi: -0.05 });
        let sdf = |p: &[Vec3]| {
            let phi = liquid_sdf(p, &Bins::new(p, grid), &[], grid, model, deep_of(), None);
            phi.iter().zip(phi_bar).map(|(a, b)| a * b).sum::<f64>()
        };
        let (phi, marks) =
            liquid_sdf_nearest(p0, &Bins::new(p0, grid), &[], grid, model, deep_of(), None);
        let mut g = vec![Vec3::ZERO; p0.len()];
        liquid_sdf_adjoint(p0, &[], &marks, None, grid, model, deep, phi_bar, &mut g, &mut []);
        // The sums read from φ: the same to rounding.
        let mut read = vec![Vec3::ZERO; p0.len()];
        let phi_in = Some(phi.as_slice());
        liquid_sdf_adjoint(p0, &[], &marks, phi_in, grid, model, deep, phi_bar, &mut read, &mut []);
        let most = g.iter().map(|v| v.length()).fold(0.0, f64::max);
        for (a, b) in g.iter().zip(&read) {
            assert!((*a - *b).length() <= 1e-13 * most, "{a} summed, {b} read from φ");
        }
        let eps = 1e-7;
        let shift = |s: f64| p0.iter().zip(dp).map(|(x, d)| *x + s * *d).collect::<Vec<_>>();
        let fd = (sdf(&shift(eps)) - sdf(&shift(-eps))) / (2.0 * eps);
        (dot(&g, dp), fd, phi, marks)
    }

    /// The liquid distance and its nearest particle per cell against a search over every
    /// particle, for a dense block (where a cell's own particle is the nearest) beside sparse
    /// ones (where the search must look one or two rings out, or give up at 2·dx).
    #[test]
    fn nearest_particle_is_the_nearest_of_all() {
        let grid = grid();
        let mut pos = particles(150);
        // A dense block: 8 jittered particles in each of 3×3×2 cells.
        for c in 0..18 {
            let ijk = [1 + c % 3, 1 + (c / 3) % 3, 1 + c / 9];
            for q in 0..8 {
                let r = |k: usize| ((c * 131 + q * 17 + k * 7) % 97) as f64 / 97.0 * 0.02 - 0.01;
                let sub = [q & 1, (q >> 1) & 1, (q >> 2) & 1];
                pos.push(Vec3::from_array(
                    [0, 1, 2]
                        .map(|a| (ijk[a] as f64 + 0.25 + 0.5 * sub[a] as f64) * grid.dx + r(a)),
                ));
            }
        }
        let model = SurfaceModel {
            radius: particle_radius(grid.dx, 2),
            sparse_cells: false,
            sparse_depth: 0.0,
            softness: 0.0,
            per_axis: 2,
        };
        let bins = Bins::new(&pos, &grid);
        let (phi, who) = liquid_sdf_nearest(&pos, &bins, &[], &grid, &model, None, None);
        let cells = grid.cells();
        let mut own = 0;
        for c in 0..grid.num_cells() {
            let [i, j, k] = cells.ijk(c);
            let x = cells.position(i, j, k);
            let (d, p) = pos
                .iter()
                .enumerate()
                .map(|(p, y)| ((*y - x).length(), p as u32))
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .unwrap();
            if d <= 2.0 * grid.dx {
                assert_eq!((phi[c], who[c]), (d - model.radius, p), "cell {c}");
                own += usize::from(d < 0.5 * grid.dx);
            } else {
                assert_eq!(phi[c], 2.0 * grid.dx - model.radius, "cell {c}");
            }
        }
        assert!(own >= 18, "the dense block's cells find their own particle: {own}");
    }

    /// Advection through a field with a solid obstacle and the tank walls in reach: the
    /// adjoint in the positions and in the field against central differences, the same on
    /// one thread and two.
    #[test]
    fn advection_adjoint_matches_central_differences() {
        let grid = grid();
        let obstacle =
            Solid::new(SharedShape::ball(0.12), Pose::from_translation(Vec3::new(0.4, 0.3, 0.3)));
        let node_sdf = NodeSdf::new(&grid, &[obstacle]);
        let (p0, u, du) = (particles(200), field(&grid, 1), field(&grid, 2));
        let (c, dp) = (dir(200, 3), dir(200, 4));
        let (dt, subs) = (0.05, 3);
        let run = |p: &[Vec3], u: &Mac| {
            let mut q = p.to_vec();
            advect_substepped(&mut q, u, &grid, dt, subs, &node_sdf);
            dot(&q, &c)
        };
        // On one thread the reads are scattered as they are made, on more they are kept and
        // scattered after: the same bits.
        let adjoint = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let mut pbar = c.clone();
            let mut ubar = Mac::zeros(&grid);
            pool.install(|| {
                advect_adjoint(&p0, &mut pbar, &u, &grid, dt, subs, &node_sdf, &mut ubar)
            });
            (pbar, ubar)
        };
        let (pbar, ubar) = adjoint(1);
        let (pbar_two, ubar_two) = adjoint(2);
        assert_eq!((&pbar, &ubar), (&pbar_two, &ubar_two));
        let eps = 1e-7;
        let shift = |s: f64| p0.iter().zip(&dp).map(|(x, d)| *x + s * *d).collect::<Vec<_>>();
        let fd = (run(&shift(eps), &u) - run(&shift(-eps), &u)) / (2.0 * eps);
        let ad = dot(&pbar, &dp);
        assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "positions: adjoint {ad:e}, fd {fd:e}");
        let moved = |s: f64| {
            let mut v = u.clone();
            for a in 0..3 {
                for (x, d) in v.c[a].iter_mut().zip(&du.c[a]) {
                    *x += s * d;
                }
            }
            v
        };
        let fd = (run(&p0, &moved(eps)) - run(&p0, &moved(-eps))) / (2.0 * eps);
        let ad = ubar.dot(&du);
        assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "field: adjoint {ad:e}, fd {fd:e}");
    }

    /// [`Walls::keep`]'s adjoint at points a tenth of the difference step short of the
    /// margin's edge, at a tank wall (the clamp) and at a static solid (the push): the slope
    /// of the side each point is on, as central differences small enough to stay there read
    /// it. A central difference across the edge read half the clamp's zero.
    #[test]
    fn keep_adjoint_takes_the_side_of_the_margin_a_point_is_on() {
        let grid = grid();
        let centre = Vec3::new(0.4, 0.3, 0.3);
        let obstacle = Solid::new(SharedShape::ball(0.12), Pose::from_translation(centre));
        let node_sdf = NodeSdf::new(&grid, &[obstacle]);
        let walls = Walls::new(&grid, &node_sdf);
        let (margin, step) = (1e-3 * grid.dx, jacobian_step(&grid));
        let short = margin - 0.1 * step;
        let nodes = grid.nodes();
        let sdf = node_sdf.values().unwrap();
        // Along a ray from the ball's centre, the point where the sampled distance is `short`.
        let at_ball = |dir: Vec3| {
            let (mut lo, mut hi) = (0.05, 0.2);
            for _ in 0..200 {
                let mid = 0.5 * (lo + hi);
                if nodes.sample(sdf, centre + mid * dir) < short {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            centre + lo * dir
        };
        let points = [
            Vec3::new(short, 0.31, 0.27),
            Vec3::new(0.43, 0.7 - short, 0.12),
            at_ball(Vec3::new(0.6, 0.75, 0.27).normalize()),
            at_ball(Vec3::new(-0.36, 0.48, 0.8).normalize()),
        ];
        for (i, y) in points.iter().enumerate() {
            assert_ne!(walls.keep(*y), *y, "point {i} is kept as it is");
        }
        let eps = 0.02 * step;
        for (i, y) in points.iter().enumerate() {
            for (k, bar) in
                [Vec3::X, Vec3::Y, Vec3::Z, Vec3::new(0.3, -0.7, 0.5)].iter().enumerate()
            {
                let ad = walls.keep_adjoint(*y, *bar, step);
                for a in 0..3 {
                    let e = eps * crate::math::unit(a);
                    let fd = bar.dot(walls.keep(*y + e) - walls.keep(*y - e)) / (2.0 * eps);
                    assert!(
                        (ad[a] - fd).abs() <= 1e-5,
                        "point {i}, bar {k}, axis {a}: adjoint {}, fd {fd}",
                        ad[a]
                    );
                }
            }
        }
    }

    /// A point a millimetre inside a box's edge is pushed out continuously as it crosses the
    /// plane where the edge's two faces are equally near (the closest surface point jumped
    /// there from one face to the other, 1.4e-3 apart), and ends `margin` outside; a point
    /// inside a face's middle goes straight out through that face.
    #[test]
    fn push_out_is_continuous_across_a_box_edge() {
        let body = RigidBody::with_density(
            "box".into(),
            SharedShape::cuboid(0.2, 0.1, 0.15),
            Pose::from_parts(Vec3::new(0.5, 0.5, 0.5), Rotation::IDENTITY),
            500.0,
        );
        let margin = 1e-4;
        let pushed = |x: Vec3| {
            let mut p = [x];
            push_out_of_bodies(&mut p, std::slice::from_ref(&body), margin);
            p[0]
        };
        // Depths 1e-3 − s from the +x face and 1e-3 + s from the +y face.
        let at = |s: f64| pushed(Vec3::new(0.699 + s, 0.599 - s, 0.5));
        let gap = (at(-1e-9) - at(1e-9)).length();
        assert!(gap < 1e-7, "the push jumped by {gap:e} across the diagonal plane");
        for s in [-2e-4, 0.0, 2e-4] {
            let d = body.sdf(at(s));
            assert!((d - margin).abs() < 1e-6, "pushed {s:e}: distance {d:e}");
        }
        let middle = pushed(Vec3::new(0.5, 0.599, 0.5));
        assert!((middle - Vec3::new(0.5, 0.6 + margin, 0.5)).length() < 1e-12, "{middle:?}");
    }

    /// The push out of a tilted box and a ball: positions and the bodies' pose.
    #[test]
    fn push_out_adjoint_matches_central_differences() {
        let grid = grid();
        let pose = |x: [f64; 3], q: Rotation| Pose::from_parts(Vec3::from_array(x), q);
        let bodies = vec![
            RigidBody::with_density(
                "box".into(),
                SharedShape::cuboid(0.15, 0.1, 0.12),
                pose(
                    [0.31, 0.33, 0.29],
                    Rotation::from_axis_angle(Vec3::new(0.3, 1.0, 0.2).normalize(), 0.4),
                ),
                500.0,
            ),
            RigidBody::with_density(
                "ball".into(),
                SharedShape::ball(0.1),
                pose([0.55, 0.4, 0.3], Rotation::IDENTITY),
                500.0,
            ),
        ];
        let (p0, c, dp) = (particles(400), dir(400, 5), dir(400, 6));
        let margin = 1e-3 * grid.dx;
        let run = |p: &[Vec3], bodies: &[RigidBody]| {
            let mut q = p.to_vec();
            push_out_of_bodies(&mut q, bodies, margin);
            dot(&q, &c)
        };
        let mut pbar = c.clone();
        let pose_bar =
            push_out_of_bodies_adjoint(&p0, &mut pbar, &bodies, margin, jacobian_step(&grid));
        let mut pushed = p0.clone();
        push_out_of_bodies(&mut pushed, &bodies, margin);
        assert!(pushed.iter().zip(&p0).filter(|(a, b)| a != b).count() > 20, "too few pushed");
        let eps = 1e-7;
        let shift = |s: f64| p0.iter().zip(&dp).map(|(x, d)| *x + s * *d).collect::<Vec<_>>();
        let fd = (run(&shift(eps), &bodies) - run(&shift(-eps), &bodies)) / (2.0 * eps);
        let ad = dot(&pbar, &dp);
        assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "positions: adjoint {ad:e}, fd {fd:e}");
        for (b, k) in [(0, 0), (0, 4), (1, 1), (1, 5)] {
            let moved = |s: f64| {
                let mut bs = bodies.clone();
                let e = s * crate::math::unit(k % 3);
                if k < 3 {
                    bs[b].x += e;
                } else {
                    bs[b].q = (Rotation::from_scaled_axis(e) * bs[b].q).normalize();
                }
                bs
            };
            let fd = (run(&p0, &moved(eps)) - run(&p0, &moved(-eps))) / (2.0 * eps);
            let ad = pose_bar[b][k];
            assert!(
                (ad - fd).abs() <= 1e-5 * fd.abs().max(1e-3),
                "body {b} dir {k}: {ad:e} vs {fd:e}"
            );
        }
    }

    /// Points a hundredth of the adjoint's difference step inside the margin's edge, where
    /// the push (by what a point lacks of the margin) meets no push with a kink: the
    /// adjoint takes the slope of the side each point is on, as central differences small
    /// enough to stay there do. Reading both sides (the rule before), the Jacobian's
    /// normal part was half what it is, and a particle of the floating box's run had its
    /// ∂/∂θ₁ off by 30% (docs/gradients.md, "The push-out's two sides").
    #[test]
    fn push_out_adjoint_takes_the_side_of_the_margin_a_point_is_on() {
        let grid = grid();
        let box_pose = Pose::from_parts(
            Vec3::new(0.31, 0.33, 0.29),
            Rotation::from_axis_angle(Vec3::new(0.3, 1.0, 0.2).normalize(), 0.4),
        );
        let body = RigidBody::with_density(
            "box".into(),
            SharedShape::cuboid(0.15, 0.1, 0.12),
            box_pose,
            500.0,
        );
        let bodies = [body];
        let (margin, step) = (1e-3 * grid.dx, jacobian_step(&grid));
        // Points on the box's faces (local ±x, ±y, ±z), moved out to just short of the
        // margin along the face's normal.
        let local = [
            Vec3::new(0.15, 0.02, -0.03),
            Vec3::new(-0.15, -0.04, 0.05),
            Vec3::new(0.03, 0.1, 0.01),
            Vec3::new(-0.06, -0.1, 0.04),
            Vec3::new(0.05, 0.03, 0.12),
            Vec3::new(-0.02, 0.05, -0.12),
        ];
        let p0: Vec<Vec3> = local
            .iter()
            .map(|l| {
                let n = (*l / Vec3::new(0.15, 0.1, 0.12)).round();
                box_pose.rotation * (*l + n * (margin - 1e-2 * step)) + box_pose.translation
            })
            .collect();
        for (i, x) in p0.iter().enumerate() {
            let d = bodies[0].sdf(*x);
            assert!(d < margin && margin - d < 0.1 * step, "point {i} at {d:e}");
        }
        let c = dir(p0.len(), 11);
        let run = |p: &[Vec3], bodies: &[RigidBody]| {
            let mut q = p.to_vec();
            push_out_of_bodies(&mut q, bodies, margin);
            dot(&q, &c)
        };
        let mut pbar = c.clone();
        let pose_bar = push_out_of_bodies_adjoint(&p0, &mut pbar, &bodies, margin, step);
        // Steps that keep every point on its side of the edge.
        let eps = 1e-4 * step;
        for (i, a) in (0..p0.len()).flat_map(|i| (0..3).map(move |a| (i, a))) {
            let shift = |s: f64| {
                let mut p = p0.clone();
                p[i] += s * crate::math::unit(a);
                p
            };
            let fd = (run(&shift(eps), &bodies) - run(&shift(-eps), &bodies)) / (2.0 * eps);
            let ad = pbar[i][a];
            assert!((ad - fd).abs() <= 1e-5, "point {i} axis {a}: adjoint {ad:e}, fd {fd:e}");
        }
        for k in 0..6 {
            let moved = |s: f64| {
                let mut bs = bodies.to_vec();
                let e = s * crate::math::unit(k % 3);
                if k < 3 {
                    bs[0].x += e;
                } else {
                    bs[0].q = (Rotation::from_scaled_axis(e) * bs[0].q).normalize();
                }
                bs
            };
            let fd = (run(&p0, &moved(eps)) - run(&p0, &moved(-eps))) / (2.0 * eps);
            let ad = pose_bar[0][k];
            assert!((ad - fd).abs() <= 1e-5, "pose direction {k}: adjoint {ad:e}, fd {fd:e}");
        }
    }

    /// φ_L and the particle density in the particles.
    #[test]
    fn sdf_and_density_adjoints_match_central_differences() {
        let grid = grid();
        let (p0, dp) = (particles(300), dir(300, 8));
        let cells = grid.num_cells();
        let phi_bar: Vec<f64> = (0..cells).map(|c| ((c * 37) % 11) as f64 / 5.0 - 1.0).collect();
        let model = SurfaceModel {
            radius: particle_radius(grid.dx, 2),
            sparse_cells: true,
            sparse_depth: 0.0,
            softness: 0.0,
            per_axis: 2,
        };
        let sdf = |p: &[Vec3]| {
            let phi = liquid_sdf(p, &Bins::new(p, &grid), &[], &grid, &model, None, None);
            phi.iter().zip(&phi_bar).map(|(a, b)| a * b).sum::<f64>()
        };
        let dens = |p: &[Vec3]| {
            particle_density(p, &grid, 8, None)
                .iter()
                .zip(&phi_bar)
                .map(|(a, b)| a * b)
                .sum::<f64>()
        };
        let (_, nearest) =
            liquid_sdf_nearest(&p0, &Bins::new(&p0, &grid), &[], &grid, &model, None, None);
        let mut g_sdf = vec![Vec3::ZERO; p0.len()];
        liquid_sdf_adjoint(
            &p0,
            &[],
            &nearest,
            None,
            &grid,
            &model,
            None,
            &phi_bar,
            &mut g_sdf,
            &mut [],
        );
        let mut g_dens = vec![Vec3::ZERO; p0.len()];
        particle_density_adjoint(&p0, &grid, 8, &phi_bar, &mut g_dens);
        let eps = 1e-7;
        let shift = |s: f64| p0.iter().zip(&dp).map(|(x, d)| *x + s * *d).collect::<Vec<_>>();
        for (name, f, g) in
            [("sdf", &sdf as &dyn Fn(&[Vec3]) -> f64, &g_sdf), ("density", &dens, &g_dens)]
        {
            let fd = (f(&shift(eps)) - f(&shift(-eps))) / (2.0 * eps);
            let ad = dot(g, &dp);
            assert!(fd.abs() > 1e-3, "{name}: a vanishing derivative checks nothing");
            assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "{name}: adjoint {ad:e}, fd {fd:e}");
        }
    }

    /// φ_L where the continuous sparse-cell rule sets it: lone particles on its ramp
    /// (between 0 and `sparse_depth` of a cell inside their cells, nearest a face along each
    /// axis in turn).
    #[test]
    fn continuous_sparse_rule_adjoint_matches_central_differences() {
        let grid = grid();
        let radius = particle_radius(grid.dx, 2);
        let model = SurfaceModel {
            radius,
            sparse_cells: true,
            sparse_depth: 0.05,
            softness: 0.0,
            per_axis: 2,
        };
        // Cells two apart, so each particle's cell has no other particle within reach; each
        // particle near a corner of its cell (farther from its centre than the radius),
        // 0.033–0.038 of a cell inside it along the axis n % 3 and a little deeper along the
        // others, at offsets with no symmetry (which would make two particles tie as the
        // nearest of a cell between them, a kink of φ).
        let p0: Vec<Vec3> = (0..6)
            .map(|n| {
                let (i, j) = ((n % 3) as f64, (n / 3) as f64);
                let centre = Vec3::new(0.15 + 0.2 * i, 0.15 + 0.2 * j, 0.25);
                let sign = |k: usize| if (n * 5 + k * 3) % 4 < 2 { 1.0 } else { -1.0 };
                let size = |k: usize| 0.044 + 0.0002 * ((n * 7 + k * 3) % 5) as f64;
                let mut offset = Vec3::new(size(0) * sign(0), size(1) * sign(1), size(2) * sign(2));
                offset[n % 3] = (0.0462 + 1e-4 * n as f64) * sign(n % 3);
                centre + offset
            })
            .collect();
        let dp = dir(p0.len(), 3);
        let cells = grid.num_cells();
        let phi_bar: Vec<f64> = (0..cells).map(|c| ((c * 37) % 11) as f64 / 5.0 - 1.0).collect();
        let (ad, fd, _, nearest) = sdf_adjoint_and_fd(&grid, &model, None, &p0, &dp, &phi_bar);
        let tagged = |p: &&u32| **p != crate::geometry::grid::NONE && **p & distance::SPARSE != 0;
        let ruled = nearest.iter().filter(tagged).count();
        assert_eq!(ruled, p0.len(), "each particle's cell set by the rule");
        assert!(fd.abs() > 1e-2, "a vanishing derivative checks nothing: {fd:e}");
        assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "adjoint {ad:e}, fd {fd:e}");
    }

    /// φ_L as the soft minimum (`softmin.rs`) in the particles: scattered particles, whose
    /// cells see many, few or one (a lone particle's cell goes over into the far value),
    /// alone and beside a band's deep cells (counted as a sub-lattice each).
    #[test]
    fn soft_sdf_adjoint_matches_central_differences() {
        let grid = grid();
        let mut p0 = particles(120);
        // Two lone particles near the tank's far corners, 1.2 and 1.7 cells from the centres
        // nearest them: cells whose φ the far value holds in part.
        p0.push(Vec3::new(0.7312, 0.6187, 0.5121));
        p0.push(Vec3::new(0.0433, 0.6621, 0.0617));
        let dp = dir(p0.len(), 5);
        let cells = grid.num_cells();
        let phi_bar: Vec<f64> = (0..cells).map(|c| ((c * 37) % 11) as f64 / 5.0 - 1.0).collect();
        let model = SurfaceModel::soft(grid.dx, 2, 0.1);
        let band: Vec<bool> = (0..cells).map(|c| grid.cells().ijk(c) == [3, 0, 2]).collect();
        for deep in [None, Some(band.as_slice())] {
            let (ad, fd, phi, _) = sdf_adjoint_and_fd(&grid, &model, deep, &p0, &dp, &phi_bar);
            let far = SOFT_REACH * grid.dx - model.radius;
            let capped = phi.iter().filter(|&&f| f > far - 0.05 * grid.dx && f < far).count();
            assert!(capped > 0, "no cell the far value holds in part: it goes unchecked");
            assert!(fd.abs() > 1e-2, "a vanishing derivative checks nothing: {fd:e}");
            let with = deep.is_some();
            assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "deep {with}: adjoint {ad:e}, fd {fd:e}");
        }
    }

    /// The soft minimum's derivative in a body's pose through its ghosts (the seeding sites
    /// it displaced, riding with it): a box turned off the grid's axes beside the −x wall (its
    /// ghosts' mirror images counted), among scattered particles; each of the six pose
    /// directions against central differences at 1e-7.
    #[test]
    fn ghost_pose_adjoint_matches_central_differences() {
        let grid = grid();
        let turn = Rotation::from_scaled_axis(Vec3::new(0.3, -0.5, 0.2));
        let body = RigidBody::with_density(
            "box".into(),
            SharedShape::cuboid(0.12, 0.1, 0.08),
            Pose::from_parts(Vec3::new(0.15, 0.33, 0.31), turn),
            500.0,
        );
        // Every seeding site of the tank; the body keeps those it covers.
        let sites: Vec<Vec3> = (0..grid.num_cells())
            .flat_map(|c| sites(&grid, grid.cells().ijk(c), &sub_offsets(2)).collect::<Vec<_>>())
            .collect();
        let displaced = vec![Displaced::of(&body, &sites, 1e-3 * grid.dx)];
        assert!(displaced[0].len() > 40, "too few ghosts: {}", displaced[0].len());
        let p0: Vec<Vec3> = particles(120).into_iter().filter(|x| body.sdf(*x) > 0.0).collect();
        let bins = Bins::new(&p0, &grid);
        let cells = grid.num_cells();
        let phi_bar: Vec<f64> = (0..cells).map(|c| ((c * 37) % 11) as f64 / 5.0 - 1.0).collect();
        let model = SurfaceModel::soft(grid.dx, 2, 0.35);
        let loss = |b: &RigidBody| {
            let ghosts = ghost_sites(std::slice::from_ref(b), &displaced);
            let phi = liquid_sdf(&p0, &bins, &ghosts, &grid, &model, None, None);
            phi.iter().zip(&phi_bar).map(|(a, b)| a * b).sum::<f64>()
        };
        let ghosts = ghost_sites(std::slice::from_ref(&body), &displaced);
        let (phi, marks) = liquid_sdf_nearest(&p0, &bins, &ghosts, &grid, &model, None, None);
        let mut pbar = vec![Vec3::ZERO; p0.len()];
        let mut gbar = vec![Vec3::ZERO; ghosts.len()];
        liquid_sdf_adjoint(
            &p0,
            &ghosts,
            &marks,
            Some(&phi),
            &grid,
            &model,
            None,
            &phi_bar,
            &mut pbar,
            &mut gbar,
        );
        let mut pose = [[0.0; 6]];
        ghost_pose_adjoint(std::slice::from_ref(&body), &displaced, &gbar, &mut pose);
        let eps = 1e-7;
        for d in 0..6 {
            let moved = |s: f64| {
                let mut b = body.clone();
                let mut e = [0.0; 3];
                e[d % 3] = s;
                if d < 3 {
                    b.x += Vec3::from_array(e);
                } else {
                    b.q = Rotation::from_scaled_axis(Vec3::from_array(e)) * b.q;
                }
                b
            };
            let fd = (loss(&moved(eps)) - loss(&moved(-eps))) / (2.0 * eps);
            let ad = pose[0][d];
            assert!(
                fd.abs() > 1e-2,
                "direction {d}: a vanishing derivative checks nothing: {fd:e}"
            );
            assert!((ad - fd).abs() <= 1e-6 * fd.abs(), "direction {d}: adjoint {ad:e}, fd {fd:e}");
        }
    }
}

/// The closing of air pockets (`pockets.rs`).
mod pockets {
    use super::*;
    use crate::geometry::weights::FaceWeights;

    /// Every face open but those across the plane x = 4·dx between i = 3 and 4 below j = 6
    /// (a wall standing in the liquid), on a 9 × 9 × 6 grid.
    fn walled(grid: &Grid) -> FaceWeights {
        FaceWeights::new(&[0, 1, 2].map(|a| {
            let lat = grid.faces(a);
            (0..lat.len())
                .map(|f| {
                    let [i, j, _] = lat.ijk(f);
                    if a == 0 && i == 4 && j < 6 {
                        0.0
                    } else {
                        1.0
                    }
                })
                .collect()
        }))
    }

    /// Liquid below y = 5·dx (φ a signed distance to it), with: a one-cell gap in the
    /// particles at (2, 2, 2), φ 0.2·dx; a two-cell gap at (6, 1, 3)–(6, 2, 3), φ 0.3·dx;
    /// a bubble wider than a cell at (2, 2, 4), φ 0.9·dx.
    fn liquid(grid: &Grid) -> Vec<f64> {
        let cells = grid.cells();
        let dx = grid.dx;
        let mut phi: Vec<f64> =
            (0..cells.len()).map(|c| (cells.ijk(c)[1] as f64 + 0.5) * dx - 5.0 * dx).collect();
        phi[grid.cell(2, 2, 2)] = 0.2 * dx;
        phi[grid.cell(6, 1, 3)] = 0.3 * dx;
        phi[grid.cell(6, 2, 3)] = 0.3 * dx;
        phi[grid.cell(2, 2, 4)] = 0.9 * dx;
        phi
    }

    #[test]
    fn gaps_in_the_liquid_close_and_the_surface_and_bubbles_stay() {
        let grid = Grid { n: [9, 9, 6], dx: 0.1 };
        let weights = walled(&grid);
        let before = liquid(&grid);
        let mut phi = before.clone();
        let pockets = close_pockets(&mut phi, &grid, &weights, 0.5);
        // The gaps are liquid now, the bubble is air still (lowered by σ: 3·0.9 − 2).
        assert!(phi[grid.cell(2, 2, 2)] < 0.0);
        assert!(phi[grid.cell(6, 1, 3)] < 0.0 && phi[grid.cell(6, 2, 3)] < 0.0);
        assert!((phi[grid.cell(2, 2, 4)] - 0.7 * grid.dx).abs() < 1e-12);
        // Nothing else moved: the surface's cells, the air above, the liquid.
        let moved: Vec<usize> = (0..phi.len()).filter(|&c| phi[c] != before[c]).collect();
        let mut expected =
            vec![grid.cell(2, 2, 2), grid.cell(6, 1, 3), grid.cell(6, 2, 3), grid.cell(2, 2, 4)];
        expected.sort();
        assert_eq!(moved, expected);
        assert_eq!(pockets.len(), 4);
    }

    #[test]
    fn a_closed_face_does_not_connect_air() {
        // Two columns of air side by side in the liquid, at i = 3 and i = 4: the one at
        // i = 4 open to the air above, the one at i = 3 closed above by liquid, beside it
        // through the faces the wall closes.
        let grid = Grid { n: [9, 9, 6], dx: 0.1 };
        let dx = grid.dx;
        let mut before = liquid(&grid);
        for j in 0..5 {
            before[grid.cell(3, j, 1)] = 0.25 * dx;
            before[grid.cell(4, j, 1)] = 0.25 * dx;
        }
        before[grid.cell(3, 4, 1)] = -0.1 * dx;
        let open = FaceWeights::new(&[0, 1, 2].map(|a| vec![1.0; grid.faces(a).len()]));
        for (weights, closes) in [(open, false), (walled(&grid), true)] {
            let mut phi = before.clone();
            close_pockets(&mut phi, &grid, &weights, 0.5);
            for j in 0..4 {
                assert_eq!(phi[grid.cell(3, j, 1)] < 0.0, closes, "j = {j}");
                assert_eq!(phi[grid.cell(4, j, 1)], 0.25 * dx, "j = {j}");
            }
        }
    }

    /// A deterministic field of air and liquid values with no two alike (no ties).
    fn rough(grid: &Grid) -> Vec<f64> {
        let cells = grid.cells();
        (0..cells.len())
            .map(|c| {
                let [_, j, _] = cells.ijk(c);
                let r = ((c * 7919 + 104_729) % 10_007) as f64 / 10_007.0;
                (j as f64 - 3.0) * 0.4 * grid.dx + (r - 0.5) * 1.2 * grid.dx
            })
            .collect()
    }

    #[test]
    fn closing_is_continuous_and_moves_no_cell_further_than_three_times_the_change() {
        let grid = Grid { n: [8, 8, 8], dx: 0.1 };
        let weights = walled(&grid);
        let base = rough(&grid);
        let mut closed = base.clone();
        let pockets = close_pockets(&mut closed, &grid, &weights, 0.5);
        assert!(pockets.len() > 20, "the field should have pockets: {}", pockets.len());
        for k in 1..40 {
            let h = 1e-3 * grid.dx * k as f64;
            let moved: Vec<f64> = base
                .iter()
                .enumerate()
                .map(|(c, p)| p + h * (((c * 31 + k) % 7) as f64 / 3.0 - 1.0))
                .collect();
            let mut other = moved.clone();
            close_pockets(&mut other, &grid, &weights, 0.5);
            let input = base.iter().zip(&moved).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            let output = closed.iter().zip(&other).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            assert!(output <= 3.0 * input + 1e-15, "{output} > 3·{input}");
        }
    }

    #[test]
    fn adjoint_matches_central_differences() {
        let grid = Grid { n: [8, 8, 8], dx: 0.1 };
        let weights = walled(&grid);
        let base = rough(&grid);
        let w: Vec<f64> = (0..base.len()).map(|c| ((c * 13) % 17) as f64 / 17.0 - 0.4).collect();
        let loss = |phi: &[f64]| -> f64 {
            let mut phi = phi.to_vec();
            close_pockets(&mut phi, &grid, &weights, 0.5);
            phi.iter().zip(&w).map(|(a, b)| a * b).sum()
        };
        let mut closed = base.clone();
        let pockets = close_pockets(&mut closed, &grid, &weights, 0.5);
        // σ's three pieces and origins other than the cell itself are all exercised.
        assert!(pockets.changed.iter().any(|&(c, o, _)| c != o));
        assert!(pockets.changed.iter().any(|&(_, _, s)| s == -1.0));
        assert!(pockets.changed.iter().any(|&(_, _, s)| s == 3.0));
        let mut bar = w.clone();
        pockets.adjoint(&mut bar);
        let eps = 1e-9;
        for c in 0..base.len() {
            let mut p = base.clone();
            p[c] += eps;
            let up = loss(&p);
            p[c] -= 2.0 * eps;
            let fd = (up - loss(&p)) / (2.0 * eps);
            assert!((fd - bar[c]).abs() < 1e-6, "cell {c}: fd {fd}, adjoint {}", bar[c]);
        }
    }
}
