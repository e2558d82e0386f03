//! Ray tracing: Embree queries ([`embree`]), Snell's law ([`refract`]) and refraction paths
//! through an object ([`path`]), a mesh's local thickness ([`thickness`]).
//!
//! [`embree`] is the only place in glasscan with `unsafe` code (besides the cache hint of
//! [`crate::util::prefetch`]): a safe layer over the C shim in `wrapper/` (bindings generated
//! by bindgen). Rays, hits and closest points are in the mesh's frame and units (mm).

#[allow(unsafe_code)]
pub mod embree;
pub mod path;
pub mod refract;
pub mod thickness;

pub use embree::{embree_version, BuildMode, ClosestPoint, Device, Hit, Ray, Scene, TraceError};
