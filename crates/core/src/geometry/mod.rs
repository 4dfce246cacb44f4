//! Geometry of the generator (paper Sec. 4.2–4.3): the body template SDF, the posed-space
//! tetrahedral grid, SMPL-guided inverse skinning, the grid under one pose and its field band,
//! marching tetrahedra and the normal transport.
//!
//! These are the CPU reference implementations ("slow, obviously correct"); tensor versions
//! used in training are checked against them.

pub mod context_cache;
pub mod dmtet;
pub mod id_map;
pub mod inverse_skinning;
#[cfg(any(feature = "generator", feature = "wgpu"))]
pub mod per_device;
pub mod posed_grid;
pub mod spatial;
pub mod template_sdf;
pub mod tet_grid;

pub use dmtet::{marching_tets, TriMesh};
pub use inverse_skinning::InverseSkinning;
pub use posed_grid::{BodyContext, PosedGrid};
pub use template_sdf::TemplateSdf;
pub use tet_grid::TetGrid;
