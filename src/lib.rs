//! glasscan: reconstruct the mesh of a solid transparent object from a turntable scan in front of
//! a monitor showing Gray-code patterns (differentiable refraction tracing, Lyu et al. 2020).
//!
//! Units: millimetres in 3D, pixels in images. Every stage lives in its own module; the
//! pipeline's entry point is [`reconstruct::pipeline::reconstruct_scan`]. The command line
//! (`src/main.rs` and `src/cli/`, feature `cli`) is a thin layer over this library.

#![deny(unsafe_code)]

pub mod bench;
pub mod calibrate;
#[cfg(feature = "capture")]
pub mod capture;
pub mod decode;
pub mod eval;
pub mod hull;
#[cfg(feature = "hdf5")]
pub mod import;
pub mod loss;
pub mod mesh;
pub mod patterns;
pub mod reconstruct;
pub mod remesh;
pub mod rig;
pub mod scan;
pub mod simulate;
pub mod trace;
pub mod util;
