//! The losses of the optimisation and their exact gradients with respect to every vertex
//! position (DESIGN §4–5), written by hand: [`refraction`] (decoded monitor points),
//! [`silhouette`] (contour edges against the masks) and [`smoothness`] (dihedral angles).
//!
//! Gradients are accumulated per thread in an [`Accumulator`] and summed; rays or edges whose
//! derivative would not be finite are dropped and counted in [`Drops`], never added.

pub mod diff;
pub mod refraction;
pub mod silhouette;
pub mod smoothness;
pub mod targets;

use std::cell::RefCell;

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};
use thread_local::ThreadLocal;

use crate::mesh::TriMesh;
use diff::{face_cross_adjoint, normalize_adjoint};
pub use refraction::DropReason;
use refraction::PixelGradient;

type V3 = Vector3<f64>;

/// A robust penalty ρ applied to a squared residual r² (scale in the residual's unit: mm for
/// the screen form).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Robust {
    /// ρ = r².
    L2,
    /// ρ = r² up to |r| = δ, then 2δ|r| − δ².
    Huber(f64),
    /// ρ = δ² log(1 + r²/δ²).
    Cauchy(f64),
}

impl Robust {
    /// ρ(r²) and dρ/d(r²).
    #[inline]
    pub fn apply(&self, r2: f64) -> (f64, f64) {
        match *self {
            Robust::L2 => (r2, 1.0),
            Robust::Huber(d) => {
                if r2 <= d * d {
                    (r2, 1.0)
                } else {
                    let r = r2.sqrt();
                    (2.0 * d * r - d * d, d / r)
                }
            }
            Robust::Cauchy(d) => {
                let d2 = d * d;
                (d2 * (r2 / d2).ln_1p(), 1.0 / (1.0 + r2 / d2))
            }
        }
    }
}

/// Rays (or edges) left out of a term, by reason.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Drops {
    /// The camera ray missed the mesh although the pixel is an object pixel.
    pub no_hit: usize,
    pub total_internal_reflection: usize,
    /// Paths whose refraction count the settings exclude.
    pub refraction_count: usize,
    pub missed_monitor: usize,
    pub grazing: usize,
    pub near_critical: usize,
    pub non_finite: usize,
}

impl Drops {
    pub fn total(&self) -> usize {
        self.no_hit
            + self.total_internal_reflection
            + self.refraction_count
            + self.missed_monitor
            + self.grazing
            + self.near_critical
            + self.non_finite
    }

    fn add(&mut self, o: &Drops) {
        self.no_hit += o.no_hit;
        self.total_internal_reflection += o.total_internal_reflection;
        self.refraction_count += o.refraction_count;
        self.missed_monitor += o.missed_monitor;
        self.grazing += o.grazing;
        self.near_critical += o.near_critical;
        self.non_finite += o.non_finite;
    }
}

/// One [`Accumulator`] per worker thread, summed at the end: the hot loops add to their own
/// thread's buffers (no locks, no atomics), and the buffers live across views.
pub struct Accumulators {
    vertices: usize,
    vertex_normals: bool,
    per_thread: ThreadLocal<RefCell<Accumulator>>,
}

impl Accumulators {
    pub fn new(vertices: usize, vertex_normals: bool) -> Self {
        Self {
            vertices,
            vertex_normals,
            per_thread: ThreadLocal::new(),
        }
    }

    /// Runs `f` on the calling thread's accumulator.
    #[inline]
    pub fn with<R>(&self, f: impl FnOnce(&mut Accumulator) -> R) -> R {
        let cell = self
            .per_thread
            .get_or(|| RefCell::new(Accumulator::new(self.vertices, self.vertex_normals)));
        f(&mut cell.borrow_mut())
    }

    /// The sum over threads.
    pub fn total(self) -> Accumulator {
        let (v, n) = (self.vertices, self.vertex_normals);
        self.per_thread
            .into_iter()
            .map(RefCell::into_inner)
            .fold(Accumulator::new(v, n), Accumulator::merge)
    }
}

/// A loss and its gradient being summed: per vertex ∂L/∂position and, for the vertex-normal
/// model, ∂L/∂(unit vertex normal), turned into position gradients by [`Self::finish`].
#[derive(Clone, Debug)]
pub struct Accumulator {
    pub loss: f64,
    pub used: usize,
    pub drops: Drops,
    pub grad: Vec<V3>,
    pub normal_grad: Vec<V3>,
}

impl Accumulator {
    pub fn new(vertices: usize, vertex_normals: bool) -> Self {
        Self {
            loss: 0.0,
            used: 0,
            drops: Drops::default(),
            grad: vec![V3::zeros(); vertices],
            normal_grad: if vertex_normals {
                vec![V3::zeros(); vertices]
            } else {
                Vec::new()
            },
        }
    }

    pub fn add_pixel(&mut self, g: &PixelGradient) {
        self.loss += g.loss;
        self.used += 1;
        for &(v, x) in &g.grad {
            self.grad[v as usize] += x;
        }
        for &(v, x) in &g.ngrad {
            self.normal_grad[v as usize] += x;
        }
    }

    pub fn merge(mut self, o: Self) -> Self {
        self.merge_from(o);
        self
    }

    pub fn merge_from(&mut self, o: Self) {
        self.loss += o.loss;
        self.used += o.used;
        self.drops.add(&o.drops);
        for (a, b) in self.grad.iter_mut().zip(&o.grad) {
            *a += b;
        }
        for (a, b) in self.normal_grad.iter_mut().zip(&o.normal_grad) {
            *a += b;
        }
    }

    /// The gradient with respect to the positions of `mesh`: the vertex-normal adjoints go
    /// through each normal's normalisation and the area-weighted sum of its faces' normals.
    pub fn finish(mut self, mesh: &TriMesh) -> Vec<V3> {
        if self.normal_grad.is_empty() {
            return self.grad;
        }
        let mut sums = vec![V3::zeros(); mesh.positions.len()];
        for (f, t) in mesh.faces.iter().enumerate() {
            let c = mesh.face_cross(f);
            for &v in t {
                sums[v as usize] += c;
            }
        }
        let gsum: Vec<V3> = sums
            .iter()
            .zip(&self.normal_grad)
            .map(|(s, g)| {
                let norm = s.norm();
                if norm > 0.0 {
                    normalize_adjoint(&(s / norm), norm, g)
                } else {
                    V3::zeros()
                }
            })
            .collect();
        for t in &mesh.faces {
            let gn: V3 = t.iter().map(|&v| gsum[v as usize]).sum();
            let tri: [Point3<f64>; 3] = t.map(|v| mesh.positions[v as usize]);
            let mut g = [V3::zeros(); 3];
            face_cross_adjoint(&tri, &gn, &mut g);
            for k in 0..3 {
                self.grad[t[k] as usize] += g[k];
            }
        }
        self.grad
    }
}
