//! What each camera pixel sees of the monitor: weighted monitor points, summed over the pixel's
//! area samples, for the two light transports of the simulator.
//!
//! - **Simple** (the model the losses invert): one refracted path per area sample, weighted by
//!   its Fresnel transmittance (or 1).
//! - **Physical**: at every interface the light splits into a Fresnel-weighted reflection and
//!   refraction (total internal reflection reflects all of it), each branch followed on to a depth
//!   limit or until it carries less than [`MIN_WEIGHT`]: captures then hold the ghosts of
//!   internally and externally reflected light and lose the energy reflected away. Branching is
//!   deterministic (no random choices), so the same scan renders the same images.

use nalgebra::{Point2, Point3, Vector3};
use rayon::prelude::*;

use super::render::{Outcome, Sample, ViewSetup};
use crate::rig::Screen;
use crate::trace::path::{Surface, SurfaceHit, TRACE_CHUNK};
use crate::trace::refract::refract;
use crate::trace::{Ray, TraceError};

/// The light transport of a simulated capture.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Transport {
    /// One refracted path per area sample: the losses' own model.
    #[default]
    Simple,
    /// Fresnel reflection and refraction at every interface, internal reflections included.
    Physical,
}

/// Branches carrying less light than this (share of a sample's) are dropped.
pub const MIN_WEIGHT: f64 = 1e-4;
/// Most interfaces a branch meets before it is dropped.
pub const MAX_DEPTH: u32 = 10;

/// The light each pixel gathers: pixel `p`'s contributions are `points[offsets[p]..offsets[p +
/// 1]]` (monitor pixel coordinates) with `weights` (shares of one area sample's light).
pub struct Light {
    pub offsets: Vec<usize>,
    pub points: Vec<Point2<f64>>,
    pub weights: Vec<f64>,
    /// Light that reached the monitor after at least one reflection, and all light that reached
    /// it, over the pixels whose samples met the object (sums of weights).
    pub ghost_weight: f64,
    pub object_weight: f64,
    /// Light dropped by the physical tracer (depth limit, [`MIN_WEIGHT`], undefined splits).
    pub dropped_weight: f64,
}

impl Light {
    /// The simple transport: each area sample's one landing point with its weight.
    pub fn from_samples(samples: &[Sample], spp: u32) -> Self {
        let mut light = Light::empty(samples.len() / spp as usize);
        for px in samples.chunks(spp as usize) {
            for s in px
                .iter()
                .filter(|s| matches!(s.outcome, Outcome::Monitor(_)))
            {
                light.points.push(s.monitor);
                light.weights.push(s.weight);
                if s.outcome.hit_object() {
                    light.object_weight += s.weight;
                }
            }
            light.offsets.push(light.points.len());
        }
        light
    }

    /// No light yet, room for `pixels` pixels: bands of rows are added to it in image order.
    pub fn empty(pixels: usize) -> Self {
        let mut offsets = Vec::with_capacity(pixels + 1);
        offsets.push(0);
        Light {
            offsets,
            points: Vec::new(),
            weights: Vec::new(),
            ghost_weight: 0.0,
            object_weight: 0.0,
            dropped_weight: 0.0,
        }
    }
}

/// A branch of a sample's light.
#[derive(Clone, Copy, Debug)]
struct Branch {
    /// Index of the area sample it belongs to.
    sample: usize,
    origin: Point3<f64>,
    dir: Vector3<f64>,
    weight: f64,
    depth: u32,
    reflections: u32,
}

/// The physical transport of a band of image rows of one view, added to `light` (which holds the
/// rows above it): `samples` are the simple trace of the same rays (in pixel order, `spp` per
/// pixel), which says which rays may meet the object.
pub fn add_physical_light(
    v: &ViewSetup,
    surface: &dyn Surface,
    (rays, samples): (&[Option<Ray>], &[Sample]),
    spp: u32,
    light: &mut Light,
) -> Result<(), TraceError> {
    let to_world = v.pose.inverse();
    let screen = v.screen.transformed(&to_world);
    let start = |(sample, r): (usize, &Ray)| Branch {
        sample,
        origin: r.origin,
        dir: r.dir,
        weight: 1.0,
        depth: 0,
        reflections: 0,
    };
    let rays = || {
        rays.iter()
            .enumerate()
            .filter_map(|(i, r)| r.as_ref().map(|r| (i, r)))
    };
    // Rays the simple trace saw miss the object fly straight on; the others branch.
    let (meet, miss): (Vec<Branch>, Vec<Branch>) = rays()
        .map(start)
        .partition(|b| samples[b.sample].outcome.hit_object());
    let traced: Vec<(Vec<Branch>, f64)> = meet
        .par_chunks(TRACE_CHUNK)
        .map(|c| trace_branches(surface, c, v.settings.ior, v.settings.ior_air))
        .collect::<Result<_, _>>()?;
    let dropped: f64 = traced.iter().map(|t| t.1).sum();
    let mut exits: Vec<Branch> = traced.into_iter().flat_map(|t| t.0).collect();
    exits.extend(miss);
    gather(exits, &screen, samples, spp, light);
    light.dropped_weight += dropped;
    Ok(())
}

/// Follows `branches` through `surface` on the calling thread, one interface at a time for all;
/// returns the branches that left it (or never met it), and the light dropped (branches past the
/// depth limit or below [`MIN_WEIGHT`], or at an undefined split).
fn trace_branches(
    surface: &dyn Surface,
    branches: &[Branch],
    ior: f64,
    ior_air: f64,
) -> Result<(Vec<Branch>, f64), TraceError> {
    let offset = surface.offset();
    let mut active = branches.to_vec();
    let mut exits = Vec::new();
    let mut dropped = 0.0;
    let mut first = true;
    while !active.is_empty() {
        let batch: Vec<Ray> = active.iter().map(|b| Ray::new(b.origin, b.dir)).collect();
        let mut hits = vec![None; batch.len()];
        surface.intersect_serial(&batch, &mut hits, first)?;
        first = false;
        let mut next = Vec::with_capacity(active.len());
        for (b, h) in active.iter().zip(&hits) {
            match h {
                None => exits.push(*b),
                Some(h) => dropped += split(b, h, (ior, ior_air), offset, &mut next),
            }
        }
        active = next;
    }
    Ok((exits, dropped))
}

/// Pushes the reflected and refracted branches of `b` at `h` that carry enough light; returns
/// the light dropped.
fn split(
    b: &Branch,
    h: &SurfaceHit,
    (ior, ior_air): (f64, f64),
    offset: f64,
    out: &mut Vec<Branch>,
) -> f64 {
    if b.depth >= MAX_DEPTH {
        return b.weight;
    }
    let entering = b.dir.dot(&h.geometric_normal) < 0.0;
    let (n_i, n_t) = if entering {
        (ior_air, ior)
    } else {
        (ior, ior_air)
    };
    let n = if entering {
        h.shading_normal
    } else {
        -h.shading_normal
    };
    if b.dir.dot(&n) >= 0.0 {
        return b.weight; // the interpolated normal faces away: no defined split
    }
    let refracted = refract(&b.dir, &n, n_i, n_t);
    let transmittance = refracted.map_or(0.0, |r| r.transmittance);
    let reflected = b.dir - n * (2.0 * b.dir.dot(&n));
    // A reflection stays on the side it came from (an interpolated normal may send it through).
    let reflected =
        ((reflected.dot(&h.geometric_normal) < 0.0) != entering).then(|| reflected.normalize());
    let branches = [
        (
            reflected,
            b.weight * (1.0 - transmittance),
            b.reflections + 1,
        ),
        (
            refracted.map(|r| r.dir.normalize()),
            b.weight * transmittance,
            b.reflections,
        ),
    ];
    let mut dropped = 0.0;
    for (dir, weight, reflections) in branches {
        let side = dir.map_or(0.0, |d| d.dot(&h.geometric_normal));
        match dir {
            Some(dir) if weight >= MIN_WEIGHT && side.abs() >= 1e-12 => out.push(Branch {
                origin: h.point + dir * (offset / side.abs().max(1e-3)),
                dir,
                weight,
                depth: b.depth + 1,
                reflections,
                ..*b
            }),
            _ => dropped += weight,
        }
    }
    dropped
}

/// The exits landed on the monitor, gathered per pixel in sample order and added to `light`.
fn gather(
    mut exits: Vec<Branch>,
    screen: &Screen,
    samples: &[Sample],
    spp: u32,
    light: &mut Light,
) {
    exits.sort_by_key(|b| b.sample);
    let mut k = 0;
    for (p, px) in samples.chunks(spp as usize).enumerate() {
        let end = (p + 1) * spp as usize;
        let on_object = px.iter().any(|s| s.outcome.hit_object());
        while k < exits.len() && exits[k].sample < end {
            let b = &exits[k];
            k += 1;
            let Some((_, at)) = screen.intersect(&b.origin, &b.dir) else {
                continue;
            };
            light.points.push(at);
            light.weights.push(b.weight);
            if on_object {
                light.object_weight += b.weight;
                if b.reflections > 0 {
                    light.ghost_weight += b.weight;
                }
            }
        }
        light.offsets.push(light.points.len());
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::shapes::{cuboid, icosphere};
    use crate::trace::path::{MeshSurface, NormalModel};
    use crate::trace::refract::IOR_AIR;

    fn start(sample: usize, origin: Point3<f64>, dir: Vector3<f64>) -> Branch {
        Branch {
            sample,
            origin,
            dir: dir.normalize(),
            weight: 1.0,
            depth: 0,
            reflections: 0,
        }
    }

    /// Light through a slab at normal incidence: transmitted T²/(1 − R²) = 2n/(n² + 1) in all,
    /// of which T²R²/(1 − R²) after internal reflections (the ghosts), the rest reflected back.
    #[test]
    fn a_slab_at_normal_incidence_transmits_and_ghosts_as_the_closed_form_says() {
        let slab = cuboid(Vector3::new(40.0, 40.0, 10.0), 4);
        let surface = MeshSurface::new(&slab, NormalModel::Face).unwrap();
        let ior = 1.5;
        let rays = [start(0, Point3::new(1.0, 2.0, 50.0), -Vector3::z())];
        let (exits, _) = trace_branches(&surface, &rays, ior, IOR_AIR).unwrap();
        let n = ior / IOR_AIR;
        let r = ((n - 1.0) / (n + 1.0)).powi(2);
        let t = 1.0 - r;
        let through: f64 = exits
            .iter()
            .filter(|b| b.dir.z < 0.0)
            .map(|b| b.weight)
            .sum();
        let ghosts: f64 = exits
            .iter()
            .filter(|b| b.dir.z < 0.0 && b.reflections > 0)
            .map(|b| b.weight)
            .sum();
        let back: f64 = exits
            .iter()
            .filter(|b| b.dir.z > 0.0)
            .map(|b| b.weight)
            .sum();
        assert!(
            (through - 2.0 * n / (n * n + 1.0)).abs() < 2.0 * MIN_WEIGHT,
            "{through}"
        );
        assert!(
            (ghosts - t * t * r * r / (1.0 - r * r)).abs() < 2.0 * MIN_WEIGHT,
            "{ghosts}"
        );
        assert!((through + back - 1.0).abs() < 2.0 * MIN_WEIGHT, "{back}");
        for b in &exits {
            assert!(b.dir.x.abs() < 1e-12 && b.dir.y.abs() < 1e-12, "{b:?}");
        }
    }

    /// Through a faceted sphere, at any incidence and with total internal reflection inside
    /// (the facets trap light at IOR 2.42 until the depth limit), the light that leaves and the
    /// light dropped add up to what came in.
    #[test]
    fn light_through_a_sphere_is_conserved() {
        let sphere = icosphere(20.0, 4);
        let surface = MeshSurface::new(&sphere, NormalModel::Face).unwrap();
        let rays: Vec<Branch> = (0..200)
            .map(|i| {
                let y = -18.0 + 36.0 * i as f64 / 199.0;
                start(i, Point3::new(0.0, y, 60.0), -Vector3::z())
            })
            .collect();
        for ior in [1.4723, 2.42] {
            for ray in &rays {
                let (exits, dropped) =
                    trace_branches(&surface, std::slice::from_ref(ray), ior, IOR_AIR).unwrap();
                let out: f64 = exits.iter().map(|b| b.weight).sum();
                assert!(
                    (out + dropped - 1.0).abs() < 1e-9,
                    "ior {ior}: {out} + {dropped}"
                );
                if ior < 2.0 {
                    assert!(dropped < 0.01, "{ray:?}: {dropped}");
                }
            }
        }
    }
}
