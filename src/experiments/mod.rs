//! Experiments on top of the world: scene files ([`scene`], [`shapes`]) as one way to build
//! a world and a loss, the optimisation of a body's initial state ([`optimize`]), the
//! benchmark studies ([`mod@bench`]), and what the CLI writes for them (`outputs`, features
//! `csv` and `plots`).

pub mod bench;
pub mod control;
#[cfg(feature = "lbfgs")]
mod lbfgs;
pub mod optimize;
#[cfg(all(feature = "csv", feature = "plots"))]
pub mod outputs;
pub mod scene;
pub mod shapes;
