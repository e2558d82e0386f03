//! glasscan's integration tests, one test binary (one link of OpenCV, HDF5 and Embree) with a
//! module per subject and the shared helpers in [`common`]. The readers' fuzz tests are a binary
//! of their own (`tests/fuzz_readers.rs`): they set the process-wide memory budget.

mod common;

mod blur;
mod calibrate;
mod calibration_files;
mod capture;
mod cli;
mod decode;
mod doc_links;
mod embree_agreement;
mod eval_metrics;
mod gradients;
mod hostile_input;
mod hull;
mod import_drt;
mod layering;
mod mesh_io;
mod mesh_validate;
mod nothing_lost;
mod readme;
mod reconstruct;
mod refraction;
mod remesh;
mod simulate;
