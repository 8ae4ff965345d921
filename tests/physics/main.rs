//! Physics: what the liquid and the bodies do, each module one invariant (still water at
//! rest with p = ρgh, divergence-free projections, Archimedes, momentum in a closed box,
//! contact, thin plates, determinism across thread counts) with the physics it checks in its
//! opening paragraph.

#[allow(dead_code)] // each group uses part of it
#[path = "../common/mod.rs"]
mod common;

mod contact;
mod coupling;
mod dam_break;
mod floating_rest;
mod interior_values;
mod momentum;
mod narrow_band;
mod parity;
mod projection;
mod solver;
mod still_water;
mod thin_moving;
mod thin_plates;
mod weak_coupling;
