//! Writers: PLY, JSON, VTK, pictures.
pub mod output;
pub mod plot;
pub mod vtk;
