//! The losses of the optimisation and their exact gradients with respect to every vertex
//! position (docs/architecture.md §4–5), written by hand: [`refraction`] (decoded monitor points,
//! with [`bits`]: the measured Gray bits, and [`sample`]: the pixels an iteration traces),
//! [`silhouette`] (contour edges against the masks), [`smoothness`] (dihedral angles) and
//! [`membrane`] (where the refraction data cannot see).
//!
//! Each chunk of rays or edges is differentiated on one thread into [`Contributions`], which are
//! summed into an [`Accumulator`] in chunk order (deterministic); rays or edges whose derivative
//! would not be finite are dropped and counted in [`Drops`], never added.

pub mod bits;
pub mod blur;
pub mod diff;
pub mod membrane;
pub mod refraction;
pub mod sample;
pub mod scatter;
pub mod silhouette;
pub mod smoothness;
pub mod targets;

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

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
    /// The same penalty with its scale δ multiplied by `factor`.
    pub fn scaled(self, factor: f64) -> Robust {
        match self {
            Robust::L2 => Robust::L2,
            Robust::Huber(d) => Robust::Huber(d * factor),
            Robust::Cauchy(d) => Robust::Cauchy(d * factor),
        }
    }

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
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
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

    pub fn add(&mut self, o: &Drops) {
        self.no_hit += o.no_hit;
        self.total_internal_reflection += o.total_internal_reflection;
        self.refraction_count += o.refraction_count;
        self.missed_monitor += o.missed_monitor;
        self.grazing += o.grazing;
        self.near_critical += o.near_critical;
        self.non_finite += o.non_finite;
    }
}

/// What one chunk of rays (or edges) adds, computed on one thread: loss, counts and the
/// per-vertex gradient entries. Chunks are summed in their order ([`Accumulator::add`]), so the
/// sums do not depend on the thread schedule: same inputs, same bits.
#[derive(Clone, Debug, Default)]
pub struct Contributions {
    pub loss: f64,
    pub used: usize,
    /// Sum of the weights of the terms used (a pixel's from its decoding uncertainty; a contour
    /// edge or an edge pair weighs 1): a term's mean is `loss / weight`.
    pub weight: f64,
    pub drops: Drops,
    /// (vertex, ∂L/∂position) entries.
    pub grad: Vec<(u32, V3)>,
    /// (vertex, ∂L/∂unit vertex normal) entries.
    pub ngrad: Vec<(u32, V3)>,
    /// ∂L/∂ the object's refractive index.
    pub ior: f64,
    /// (vertex, penalty) entries, one per `grad` entry of a refraction pixel: its loss per unit
    /// of its weight; only for a [`Accumulator::counting`] one.
    pub penalties: Vec<(u32, f64)>,
}

impl Contributions {
    /// Empty, with room for `grad` position and `ngrad` normal entries, so that pushing as many
    /// does not reallocate and copy them.
    pub fn with_capacity(grad: usize, ngrad: usize) -> Self {
        Self {
            grad: Vec::with_capacity(grad),
            ngrad: Vec::with_capacity(ngrad),
            ..Self::default()
        }
    }

    /// Empty, with room for `grad` and `ngrad` entries, reusing the lists of `spare` (whose
    /// memory is already touched) where it has one.
    pub fn reusing(
        spare: &std::sync::Mutex<Vec<Contributions>>,
        grad: usize,
        ngrad: usize,
    ) -> Self {
        let reused = spare.lock().ok().and_then(|mut s| s.pop());
        let Some(mut c) = reused else {
            return Self::with_capacity(grad, ngrad);
        };
        c.grad.reserve(grad);
        c.ngrad.reserve(ngrad);
        Self {
            grad: c.grad,
            ngrad: c.ngrad,
            penalties: c.penalties,
            ..Self::default()
        }
    }

    /// Adds a pixel of weight `weight` (its loss and gradient already carry it).
    pub fn push_pixel(&mut self, g: &PixelGradient, weight: f64) {
        self.grad.extend_from_slice(&g.grad);
        self.ngrad.extend_from_slice(&g.ngrad);
        self.count_pixel(g.loss, weight, g.ior);
    }

    /// Adds a used pixel's loss, weight and ∂L/∂index, its gradient entries already in place.
    pub fn count_pixel(&mut self, loss: f64, weight: f64, ior: f64) {
        self.loss += loss;
        self.used += 1;
        self.weight += weight;
        self.ior += ior;
    }
}

/// A loss and its gradient being summed: per vertex ∂L/∂position and, for the vertex-normal
/// model, ∂L/∂(unit vertex normal), turned into position gradients by [`Self::finish`].
#[derive(Clone, Debug)]
pub struct Accumulator {
    pub loss: f64,
    pub used: usize,
    /// See [`Contributions::weight`].
    pub weight: f64,
    pub drops: Drops,
    pub grad: Vec<V3>,
    pub normal_grad: Vec<V3>,
    /// ∂L/∂ the object's refractive index.
    pub ior: f64,
    /// Per vertex, the position-gradient entries added (a ray's refraction at one of its faces,
    /// a contour edge at it); kept only by [`Self::counting`], else empty.
    pub touches: Vec<u32>,
    /// Per vertex, the sum of the [`Contributions::penalties`] it receives (the penalties of
    /// the refraction pixels behind its touches); kept only by [`Self::counting`], else empty.
    pub penalty: Vec<f64>,
    /// Chunks already added, emptied, whose lists the next chunks reuse ([`Self::add_reusing`]).
    pub spare: Vec<Contributions>,
    /// The chunks' entries sorted by part when they are added ([`scatter::scatter`]), kept for
    /// the next chunks.
    pub sorted: Vec<scatter::PartSorted>,
}

impl Accumulator {
    /// As [`Self::new`], also counting the entries each vertex receives ([`Self::touches`]).
    pub fn counting(vertices: usize, vertex_normals: bool) -> Self {
        Self {
            touches: vec![0; vertices],
            penalty: vec![0.0; vertices],
            ..Self::new(vertices, vertex_normals)
        }
    }

    pub fn new(vertices: usize, vertex_normals: bool) -> Self {
        Self {
            loss: 0.0,
            used: 0,
            weight: 0.0,
            drops: Drops::default(),
            grad: vec![V3::zeros(); vertices],
            normal_grad: if vertex_normals {
                vec![V3::zeros(); vertices]
            } else {
                Vec::new()
            },
            ior: 0.0,
            touches: Vec::new(),
            penalty: Vec::new(),
            spare: Vec::new(),
            sorted: Vec::new(),
        }
    }

    /// As [`Self::add`], then keeps the chunks, emptied, in [`Self::spare`].
    pub fn add_reusing(&mut self, chunks: Vec<Contributions>) {
        self.add(&chunks);
        self.spare.extend(chunks.into_iter().map(|mut c| {
            c.grad.clear();
            c.ngrad.clear();
            c.penalties.clear();
            c
        }));
    }

    /// Adds chunks' contributions, in their order: every vertex sees the same sequence of
    /// additions whatever the schedule and the thread count ([`scatter::scatter`], one part of
    /// the vertex range per thread).
    pub fn add(&mut self, chunks: &[Contributions]) {
        for c in chunks {
            self.loss += c.loss;
            self.used += c.used;
            self.weight += c.weight;
            self.drops.add(&c.drops);
            self.ior += c.ior;
        }
        if !self.touches.is_empty() {
            for &(v, _) in chunks.iter().flat_map(|c| &c.grad) {
                if let Some(t) = self.touches.get_mut(v as usize) {
                    *t += 1;
                }
            }
            for &(v, x) in chunks.iter().flat_map(|c| &c.penalties) {
                if let Some(t) = self.penalty.get_mut(v as usize) {
                    *t += x;
                }
            }
        }
        let parts = rayon::current_num_threads();
        let sorted = &mut self.sorted;
        scatter::scatter(&mut self.grad, chunks, |c| &c.grad, parts, sorted);
        if !self.normal_grad.is_empty() {
            scatter::scatter(&mut self.normal_grad, chunks, |c| &c.ngrad, parts, sorted);
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
