//! Turning captures into monitor correspondences.

pub mod graycode;
