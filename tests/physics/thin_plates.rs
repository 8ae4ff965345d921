//! Plates thinner than a cell still couple to the liquid.
//!
//! (1) Hydrostatics: a neutrally buoyant plate a quarter (and an eighth) of a cell thick,
//! submerged and tilted off the grid's planes, feels ρ·g·V up and no torque about its centre
//! in the first solve, as closely as a thick plate does there: its face fractions, sampled
//! finely enough for its thickness, hold its whole volume about the right centroid. Sampled
//! every dx/2 it fell between the samples and lost 50–68% (79–93%) of its buoyancy.
//!
//! (2) Leakage: a static quarter-cell plate across the tank, holding 0.5 m of water against
//! 0.1 m, lets no liquid through in 0.3 s, whether it sits on a grid plane of faces, off it,
//! through the cell centres, or tilted. By volume fractions alone all of the flow went
//! through: three quarters of each crossed face stayed open.

use diffluid::experiments::bench::{plate_hydrostatics, plate_leakage, THIN_DX};

#[test]
fn sub_cell_plates_keep_their_hydrostatic_force_and_torque() {
    let mut worst = (0.0f64, 0.0f64);
    for cells in [0.25, 0.125] {
        for (axis, degrees) in [([0.0, 0.0, 1.0], 30.0), ([0.3, 1.0, 0.2], 17.0)] {
            let (f, t) = plate_hydrostatics(cells, axis, degrees).unwrap();
            eprintln!("{cells} cells, {degrees}° about {axis:?}: force {f:.2e}, torque {t:.2e}");
            worst = (worst.0.max(f), worst.1.max(t));
        }
    }
    // Measured: force 4e-7 to 3.3e-6, torque 5.1e-4 to 1.2e-3, as for thick plates at this
    // pose (2 and 4 cells: force 3.6e-6 to 5.1e-5, torque 1.0e-3 to 1.9e-3); the target
    // is 2% for both.
    assert!(worst.0 < 3e-5 && worst.1 < 1e-2, "force, torque errors {worst:?}");
}

#[test]
fn static_quarter_cell_plates_do_not_leak() {
    let mut worst: f64 = 0.0;
    for (offset, degrees) in [(0.0, 0.0), (0.3, 0.0), (0.5, 0.0), (0.3, 20.0)] {
        let l = plate_leakage(0.25, [0.5 + offset * THIN_DX, 0.3, 0.15], degrees).unwrap();
        eprintln!("centre {offset} cells off x = 0.5, {degrees}°: leakage {l:.3}");
        worst = worst.max(l.abs());
    }
    // Measured 0 for all but the plate 0.3 cells off, -0.011 there (a particle or two of the
    // right pool ends up left of the plate's far face); 0.99 to 1.0 by volume fractions alone.
    assert!(worst < 0.05, "leakage {worst}");
}
