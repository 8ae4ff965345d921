//! A level built by colour: from a coarse lattice ([`split`]), or the finest straight from the
//! pressure stencil's rows ([`split_rows`]), each entry with its neighbours of the other
//! colour and their couplings.

use super::lattice::{cell_ijk, LatticeStencil};
use super::level::{coef32, diag32, pack, unpack, Level};
use super::tuning::{MIN_PAR, SORT_CHUNK};
use crate::geometry::grid::NONE;
use crate::math::buffer::refill;
use crate::solvers::stencil::Stencil;
use rayon::prelude::*;

/// Splits a coarse lattice stencil by colour into `level` (its vectors reused); returns the
/// packed slot of each cell.
pub(super) fn split(lat: &LatticeStencil, level: &mut Level) -> Vec<u32> {
    let len = lat.diag.len();
    let mut slot = vec![NONE; len];
    let mut count = [0usize; 2];
    let colour_of = |c: usize| {
        let [i, j, k] = lat.ijk(c);
        (i + j + k) % 2
    };
    let mut present = [0usize; 2];
    for c in (0..len).filter(|&c| lat.diag[c] > 0.0) {
        present[colour_of(c)] += 1;
    }
    for (h, &n) in level.half.iter_mut().zip(&present) {
        h.clear_for(n);
    }
    for c in 0..len {
        if lat.diag[c] > 0.0 {
            let colour = colour_of(c);
            slot[c] = pack(colour, count[colour]);
            count[colour] += 1;
            level.half[colour].cell.push(c as u32);
        }
    }
    let stride = [1, lat.n[0], lat.n[0] * lat.n[1]];
    for (colour, h) in level.half.iter_mut().enumerate() {
        let pad = count[1 - colour] as u32;
        h.cell
            .par_iter()
            .with_min_len(MIN_PAR)
            .map(|&c| {
                let c = c as usize;
                let ijk = lat.ijk(c);
                let (mut nbr, mut coef) = ([pad; 6], [0.0; 6]);
                for a in 0..3 {
                    if ijk[a] > 0 {
                        let m = c - stride[a];
                        let w = lat.plus[m][a];
                        if w != 0.0 && slot[m] != NONE {
                            nbr[2 * a] = unpack(slot[m]).1 as u32;
                            coef[2 * a] = coef32(w);
                        }
                    }
                    if ijk[a] + 1 < lat.n[a] {
                        let p = c + stride[a];
                        let w = lat.plus[c][a];
                        if w != 0.0 && slot[p] != NONE {
                            nbr[2 * a + 1] = unpack(slot[p]).1 as u32;
                            coef[2 * a + 1] = coef32(w);
                        }
                    }
                }
                (nbr, coef)
            })
            .unzip_into_vecs(&mut h.nbr, &mut h.coef);
        h.cell.par_iter().map(|&c| diag32(lat.diag[c as usize])).collect_into_vec(&mut h.diag);
        h.mark_uniform();
    }
    slot
}

/// The finest level, from the stencil over the unknowns straight into `level` (its vectors
/// reused): the rows with a positive diagonal, split by colour. Fills the packed slot of each
/// row and the row of each entry.
pub(super) fn split_rows(
    n: [usize; 3],
    cell_of_row: &[u32],
    a: &Stencil,
    level: &mut Level,
    slot_of_row: &mut Vec<u32>,
    row: &mut [Vec<u32>; 2],
) {
    let colour_of = |c: u32| {
        let [i, j, k] = cell_ijk(n, c as usize);
        (i + j + k) % 2
    };
    // The entries of each colour in row order, a chunk of rows a task: each chunk counts its
    // present rows of each colour, and then writes its slots and entries from where the
    // chunks before it end.
    let chunks = cell_of_row.len().div_ceil(SORT_CHUNK);
    let counts: Vec<[usize; 2]> = (0..chunks)
        .into_par_iter()
        .map(|ch| {
            let rows = ch * SORT_CHUNK..((ch + 1) * SORT_CHUNK).min(cell_of_row.len());
            let mut k = [0; 2];
            for r in rows.filter(|&r| a.diag[r] > 0.0) {
                k[colour_of(cell_of_row[r])] += 1;
            }
            k
        })
        .collect();
    let mut first = Vec::with_capacity(chunks);
    let mut count = [0usize; 2];
    for k in &counts {
        first.push(count);
        count = [count[0] + k[0], count[1] + k[1]];
    }
    refill(slot_of_row, cell_of_row.len(), NONE);
    for ((h, row), &n) in level.half.iter_mut().zip(row.iter_mut()).zip(&count) {
        h.clear_for(n);
        refill(&mut h.cell, n, 0);
        refill(row, n, 0);
    }
    // Each chunk's piece of a colour's vector.
    fn pieces<'v>(v: &'v mut [u32], counts: &[[usize; 2]], colour: usize) -> Vec<&'v mut [u32]> {
        let mut rest = v;
        counts
            .iter()
            .map(|k| {
                let (piece, tail) = std::mem::take(&mut rest).split_at_mut(k[colour]);
                rest = tail;
                piece
            })
            .collect()
    }
    let [h0, h1] = &mut level.half;
    let [row0, row1] = row;
    let cells = pieces(&mut h0.cell, &counts, 0).into_iter().zip(pieces(&mut h1.cell, &counts, 1));
    let rows = pieces(row0, &counts, 0).into_iter().zip(pieces(row1, &counts, 1));
    let pieces: Vec<_> = cells.zip(rows).collect();
    slot_of_row.par_chunks_mut(SORT_CHUNK).zip(pieces).enumerate().for_each(
        |(ch, (slots, ((c0, c1), (r0, r1))))| {
            let (cell, row) = ([c0, c1], [r0, r1]);
            let mut at = [0usize; 2];
            for (t, slot) in slots.iter_mut().enumerate() {
                let r = ch * SORT_CHUNK + t;
                if a.diag[r] > 0.0 {
                    let c = cell_of_row[r];
                    let colour = colour_of(c);
                    *slot = pack(colour, first[ch][colour] + at[colour]);
                    cell[colour][at[colour]] = c;
                    row[colour][at[colour]] = r as u32;
                    at[colour] += 1;
                }
            }
        },
    );
    let slot_of_row = &*slot_of_row;
    // A neighbour row is an entry when present; its coupling is the − row's + coefficient
    // (the stencil lists neighbours only across open faces between two unknowns).
    let entry = |r: u32, w: f64| -> Option<u32> {
        (r != NONE && w != 0.0 && slot_of_row[r as usize] != NONE)
            .then(|| unpack(slot_of_row[r as usize]).1 as u32)
    };
    for (colour, (h, rows)) in level.half.iter_mut().zip(row.iter()).enumerate() {
        let pad = count[1 - colour] as u32;
        rows.par_iter()
            .with_min_len(MIN_PAR)
            .map(|&r| {
                let r = r as usize;
                let (mut nbr, mut coef) = ([pad; 6], [0.0; 6]);
                for d in 0..3 {
                    let m = a.nbr[r][2 * d];
                    let w = if m == NONE { 0.0 } else { a.plus[m as usize][d] };
                    if let Some(e) = entry(m, w) {
                        nbr[2 * d] = e;
                        coef[2 * d] = coef32(w);
                    }
                    let p = a.nbr[r][2 * d + 1];
                    let w = a.plus[r][d];
                    if let Some(e) = entry(p, w) {
                        nbr[2 * d + 1] = e;
                        coef[2 * d + 1] = coef32(w);
                    }
                }
                (nbr, coef)
            })
            .unzip_into_vecs(&mut h.nbr, &mut h.coef);
        rows.par_iter().map(|&r| diag32(a.diag[r as usize])).collect_into_vec(&mut h.diag);
        h.mark_uniform();
    }
}
