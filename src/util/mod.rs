//! Small helpers shared by every stage: atomic file and image output.

pub mod atomic;
pub mod image;
