//! Input and output: PLY, OBJ, JSON and CSV writers ([`output`]), a run's recorder and its
//! locked output folder (`recorder`, `folder`, feature `csv`), ParaView frames (`vtk`, feature `vtk`), the liquid's surface
//! mesh (`liquid_mesh`, feature `surface`), a software rasteriser of meshes ([`render`]) and
//! pictures (`plot`, feature `plots`).

#[cfg(feature = "csv")]
pub mod folder;
#[cfg(feature = "surface")]
pub mod liquid_mesh;
pub mod output;
#[cfg(feature = "plots")]
pub mod plot;
#[cfg(feature = "csv")]
pub mod recorder;
pub mod render;
#[cfg(feature = "vtk")]
pub mod vtk;
