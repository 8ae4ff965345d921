//! What `diffluid optimize` and `diffluid bench` write (features `csv` and `plots`; ParaView
//! frames with `vtk`): the tables, the JSON result and the pictures, so the command line only
//! parses arguments and prints.
//!
//! The files: `optimization.rs` (what `optimize` and `control` write: tables, result, charts,
//! pictures), `render.rs` (`render`: a run's frames drawn) and `studies.rs` (`bench`: each
//! study's table and charts).

mod optimization;
mod render;
mod studies;

pub use optimization::{write_control, write_optimization};
pub use render::{
    render_run, RenderRequest, MAX_PICTURE_HEIGHT, MAX_PICTURE_SIDE, MIN_PICTURE_SIDE,
};
pub use studies::{smoothness_charts, write_bench, Study};
