//! The physical rig: camera, monitor, turntable, and their calibration files (docs/architecture.md §2).

pub mod calib_io;
pub mod camera;
pub mod screen;
pub mod turntable;

pub use camera::Camera;
pub use screen::Screen;
pub use turntable::Turntable;
