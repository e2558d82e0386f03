//! Other projects' data as glasscan scan folders.

pub mod drt;
