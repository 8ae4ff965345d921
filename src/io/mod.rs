//! Input and output: PLY, JSON and CSV writers ([`output`]), a run's recorder
//! (`recorder`, feature `csv`), ParaView frames (`vtk`, feature `vtk`) and pictures
//! (`plot`, feature `plots`).

#[cfg(feature = "surface")]
pub mod liquid_mesh;
pub mod output;
#[cfg(feature = "plots")]
pub mod plot;
#[cfg(feature = "csv")]
pub mod recorder;
#[cfg(feature = "vtk")]
pub mod vtk;
