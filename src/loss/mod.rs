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

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;
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
    pub fn reusing(spare: &Mutex<Vec<Contributions>>, grad: usize, ngrad: usize) -> Self {
        let reused = lock(spare).pop();
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
    /// Chunks already added, emptied, whose lists the next chunks reuse ([`Self::add_in_order`]).
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

    /// Computes chunks `0..n` with `chunk` on the pool's threads, handed out in their order,
    /// and adds each as soon as it and every chunk before it are done: the additions of
    /// [`Self::add`] over all of them, in the same order, but only the chunks in flight are
    /// held, so their entries are added while still in cache. `chunk` takes its lists from the
    /// spare ones it is given ([`Contributions::reusing`]); added chunks go back there, emptied,
    /// and stay in [`Self::spare`] for the next call. The first error stops the handing out and
    /// is returned (the chunks added by then stay added).
    pub fn add_in_order<E: Send>(
        &mut self,
        n: usize,
        chunk: impl Fn(usize, &Mutex<Vec<Contributions>>) -> Result<Contributions, E> + Sync,
    ) -> Result<(), E> {
        let spare = Mutex::new(std::mem::take(&mut self.spare));
        let next = AtomicUsize::new(0);
        let order = InOrder {
            adder: Mutex::new(Adder {
                acc: &mut *self,
                added: 0,
                pending: (0..n).map(|_| None).collect(),
            }),
            inbox: Mutex::new(Vec::new()),
            spare: &spare,
        };
        let worker = |_| loop {
            let k = next.fetch_add(1, Ordering::Relaxed);
            if k >= n {
                return Ok(());
            }
            match chunk(k, &spare) {
                Ok(c) => order.submit(k, c),
                Err(e) => {
                    next.store(n, Ordering::Relaxed);
                    return Err(e);
                }
            }
        };
        let threads = rayon::current_num_threads().clamp(1, n.max(1));
        let r = (0..threads).into_par_iter().try_for_each(worker);
        // Every chunk is added by now (see `InOrder::submit`); the inbox is looked at once more
        // all the same.
        let rest = std::mem::take(&mut *lock(&order.inbox));
        lock(&order.adder).take(rest, &spare);
        drop(order);
        self.spare = spare.into_inner().unwrap_or_else(|e| e.into_inner());
        r
    }

    /// Adds chunks' contributions, in their order: every vertex sees the same sequence of
    /// additions whatever the schedule and the thread count ([`scatter::scatter`], one part of
    /// the vertex range per thread).
    pub fn add(&mut self, chunks: &[Contributions]) {
        for c in chunks {
            self.add_counts(c);
        }
        let parts = rayon::current_num_threads();
        let sorted = &mut self.sorted;
        scatter::scatter(&mut self.grad, chunks, |c| &c.grad, parts, sorted);
        if !self.normal_grad.is_empty() {
            scatter::scatter(&mut self.normal_grad, chunks, |c| &c.ngrad, parts, sorted);
        }
    }

    /// Adds one chunk's contributions on the calling thread.
    fn add_chunk(&mut self, c: &Contributions) {
        self.add_counts(c);
        scatter::add_entries(&mut self.grad, 0, std::iter::once(&c.grad[..]));
        if !self.normal_grad.is_empty() {
            scatter::add_entries(&mut self.normal_grad, 0, std::iter::once(&c.ngrad[..]));
        }
    }

    /// Adds a chunk's loss, counts and index derivative, and for a counting one its touches and
    /// penalties.
    fn add_counts(&mut self, c: &Contributions) {
        self.loss += c.loss;
        self.used += c.used;
        self.weight += c.weight;
        self.drops.add(&c.drops);
        self.ior += c.ior;
        if self.touches.is_empty() {
            return;
        }
        for &(v, _) in &c.grad {
            if let Some(t) = self.touches.get_mut(v as usize) {
                *t += 1;
            }
        }
        for &(v, x) in &c.penalties {
            if let Some(t) = self.penalty.get_mut(v as usize) {
                *t += x;
            }
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

/// Where the chunks of [`Accumulator::add_in_order`] go when they are done: a thread that
/// finishes one leaves it in the inbox and adds what is ready unless another thread is adding
/// (then that one adds it), so no thread waits while another adds.
struct InOrder<'a, 'b> {
    adder: Mutex<Adder<'a>>,
    inbox: Mutex<Vec<(usize, Contributions)>>,
    spare: &'b Mutex<Vec<Contributions>>,
}

impl InOrder<'_, '_> {
    /// Leaves chunk `k` in the inbox, then, while the inbox holds chunks and no other thread
    /// is adding, adds what is ready. (A thread that finds the adder busy leaves; the adder,
    /// once free, looks at the inbox again, so no chunk is left behind.)
    fn submit(&self, k: usize, c: Contributions) {
        lock(&self.inbox).push((k, c));
        loop {
            let mut adder = match self.adder.try_lock() {
                Ok(a) => a,
                Err(std::sync::TryLockError::Poisoned(e)) => e.into_inner(),
                Err(std::sync::TryLockError::WouldBlock) => return,
            };
            loop {
                let done = std::mem::take(&mut *lock(&self.inbox));
                if done.is_empty() {
                    break;
                }
                adder.take(done, self.spare);
            }
            drop(adder);
            if lock(&self.inbox).is_empty() {
                return;
            }
        }
    }
}

/// The adding side of [`InOrder`]: the accumulator and the chunks done out of order.
struct Adder<'a> {
    acc: &'a mut Accumulator,
    /// Chunks `0..added` are added.
    added: usize,
    pending: Vec<Option<Contributions>>,
}

impl Adder<'_> {
    /// Takes the chunks `done` (index, chunk) and adds every chunk from `added` on that is
    /// done, in order; their lists, emptied, go to `spare`.
    fn take(&mut self, done: Vec<(usize, Contributions)>, spare: &Mutex<Vec<Contributions>>) {
        for (k, c) in done {
            self.pending[k] = Some(c);
        }
        while let Some(mut c) = self.pending.get_mut(self.added).and_then(Option::take) {
            self.acc.add_chunk(&c);
            self.added += 1;
            c.grad.clear();
            c.ngrad.clear();
            c.penalties.clear();
            lock(spare).push(c);
        }
    }
}

/// Locks `m`, whether or not a thread panicked holding it (what it guards stays consistent:
/// lists and sums, each updated before the next step).
fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 40 chunks of entries over 30 vertices (some beyond them), with loss, counts and
    /// penalties.
    fn chunks() -> Vec<Contributions> {
        (0..40u32)
            .map(|c| {
                let entry = |i: u32| {
                    let v = (i * 7 + c * 13) % 33;
                    let x = 1.0 / (1.0 + f64::from(i) + 0.37 * f64::from(c));
                    (v, V3::new(x, -x * 1e-9, x * 1e9))
                };
                Contributions {
                    loss: f64::from(c).sqrt(),
                    used: c as usize,
                    weight: 0.1 * f64::from(c),
                    ior: 1.0 / (1.0 + f64::from(c)),
                    grad: (0..25).map(entry).collect(),
                    ngrad: (3..20).map(entry).collect(),
                    penalties: (0..25).map(|i| (entry(i).0, entry(i).1.x)).collect(),
                    ..Contributions::default()
                }
            })
            .collect()
    }

    fn bits(a: &Accumulator) -> Vec<u64> {
        let vectors = a.grad.iter().chain(&a.normal_grad);
        let scalars = [a.loss, a.weight, a.ior]
            .into_iter()
            .chain(a.penalty.clone());
        vectors
            .flat_map(|x| x.iter().copied().collect::<Vec<_>>())
            .chain(scalars)
            .map(f64::to_bits)
            .collect()
    }

    /// Chunks added as they are done, on 1 to 4 threads, over two calls: the same bits as
    /// adding them all at once, and the spare lists kept.
    #[test]
    fn adding_in_order_matches_adding_all_at_once() {
        let chunks = chunks();
        let mut all = Accumulator::counting(30, true);
        all.add(&chunks);
        for threads in 1..=4 {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let mut acc = Accumulator::counting(30, true);
            for half in chunks.chunks(20) {
                let r: Result<(), ()> = pool.install(|| {
                    acc.add_in_order(half.len(), |k, spare| {
                        let mut c = Contributions::reusing(spare, 0, 0);
                        c.grad.extend_from_slice(&half[k].grad);
                        c.ngrad.extend_from_slice(&half[k].ngrad);
                        c.penalties.extend_from_slice(&half[k].penalties);
                        let (loss, used, weight, ior) =
                            (half[k].loss, half[k].used, half[k].weight, half[k].ior);
                        Ok(Contributions {
                            loss,
                            used,
                            weight,
                            ior,
                            ..c
                        })
                    })
                });
                r.unwrap();
            }
            assert_eq!(bits(&acc), bits(&all), "{threads} threads");
            assert_eq!(
                (acc.used, acc.touches.clone()),
                (all.used, all.touches.clone())
            );
            assert!(!acc.spare.is_empty() && acc.spare.iter().all(|c| c.grad.is_empty()));
        }
    }

    /// A chunk's error is returned, on any number of threads; on one, no chunk after it is
    /// computed.
    #[test]
    fn adding_in_order_stops_at_an_error() {
        for threads in 1..=3 {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let computed = AtomicUsize::new(0);
            let mut acc = Accumulator::new(5, false);
            let r = pool.install(|| {
                acc.add_in_order(1000, |k, _| {
                    computed.fetch_add(1, Ordering::Relaxed);
                    if k == 3 {
                        Err(k)
                    } else {
                        Ok(Contributions::default())
                    }
                })
            });
            assert_eq!(r, Err(3), "{threads} threads");
            if threads == 1 {
                assert_eq!(computed.into_inner(), 4);
            }
        }
    }
}
