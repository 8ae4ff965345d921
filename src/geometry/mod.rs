//! The grid and what stands in it: the MAC grid, parry shapes and OBJ meshes, rigid bodies,
//! and the face fractions bodies and obstacles cut out of the grid.
pub mod body;
pub mod fractions;
pub mod grid;
pub mod interior;
pub mod mesh;
pub mod seal;
pub mod shape;
pub mod spin;
pub mod weights;
