//! What a run writes: its locked output folder, surface meshes, ParaView frames, each read
//! back.

#[allow(dead_code)] // each group uses part of it
#[path = "../common/mod.rs"]
mod common;

mod liquid_mesh;
mod output_folder;
mod vtk;
