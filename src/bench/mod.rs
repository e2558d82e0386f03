//! Benchmarks behind `glasscan bench …`: they measure what they name and print ratios.

pub mod calibrated;
pub mod gradient;
pub mod reconstruct;
pub mod remesh;
pub mod trace;
