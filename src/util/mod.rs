//! Small helpers shared by every stage: atomic file output.

pub mod atomic;
