//! glasscan: reconstruct the mesh of a solid transparent object from a turntable scan in front of
//! a monitor showing Gray-code patterns (differentiable refraction tracing, Lyu et al. 2020).
//!
//! Units: millimetres in 3D, pixels in images. The binary (`src/main.rs`) is a thin CLI over
//! [`cli`]; every stage lives in its own module.

#![deny(unsafe_code)]

pub mod bench;
pub mod calibrate;
pub mod capture;
pub mod cli;
pub mod decode;
pub mod eval;
pub mod hull;
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
