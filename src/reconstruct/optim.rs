//! The optimisers of the vertex positions (one per stage; the mesh changes between stages).

use anyhow::{anyhow, Result};
use faer::linalg::solvers::Solve;
use faer::sparse::{SparseColMat, Triplet};
use faer::{Mat, Side};
use nalgebra::{Point3, Vector3};

use super::config::Optimizer;
use crate::mesh::TriMesh;

type V3 = Vector3<f64>;

/// Largest step of one coordinate of u, in units of the learning rate: the second moment is one
/// root-mean-square for all vertices, so a few outlying gradients (rays near grazing) must not
/// throw their vertices far.
const STEP_CLAMP: f64 = 3.0;

/// The state of one stage's optimiser.
pub enum Stepper {
    Sgd {
        lr: f64,
        /// [`drt_size_scale`]: the gradient (1/mm) times it is the gradient of the same object
        /// at DRT's sizes, which DRT's clamp of each component to ±1 is applied to.
        scale: f64,
        momentum: f64,
        velocity: Vec<V3>,
    },
    LargeSteps {
        /// Cholesky factor of I + λL.
        llt: faer::sparse::linalg::solvers::Llt<usize, f64>,
        /// u = (I + λL)x.
        u: Mat<f64>,
        m: Mat<f64>,
        v: f64,
        t: i32,
        /// Learning rate at the first iteration (mm in u) and its factor per iteration.
        lr: f64,
        lr_factor: f64,
        beta1: f64,
        beta2: f64,
        clip: f64,
    },
}

/// The bounding-box diagonals (mm) DRT's learning rates are kept for as they are: around DRT's
/// objects (the shared pig, dog and horse span 234–277 mm).
const DRT_SIZES_MM: (f64, f64) = (200.0, 300.0);

/// The factor on DRT's learning rates and gradients (set in mm for DRT's objects) for `mesh`:
/// 1 within [`DRT_SIZES_MM`], the diagonal over the range's nearer end outside it. The terms
/// are scale-free, so their gradient is inversely proportional to the object's size: with the
/// gradient times this factor clamped and the step times it, an object moves as the same object
/// at the range's end would, scaled (at full steps a 12 mm object turned inside out in the
/// warm-up, and a 9 m one barely moved; with the steps scaled but not the gradient, which the
/// clamp then cut, a 2.3 mm one collapsed).
fn drt_size_scale(mesh: &TriMesh) -> f64 {
    let diagonal = mesh.bbox_diagonal();
    let (lo, hi) = DRT_SIZES_MM;
    if diagonal > hi {
        diagonal / hi
    } else {
        (diagonal / lo).clamp(f64::MIN_POSITIVE, 1.0)
    }
}

impl Stepper {
    /// The optimiser for stage `stage` of `stages` on `mesh`, whose target edge is `edge_mm`, for
    /// `iterations` steps.
    pub fn new(
        o: &Optimizer,
        mesh: &TriMesh,
        (stage, stages): (usize, usize),
        edge_mm: f64,
        iterations: usize,
    ) -> Result<Self> {
        Ok(match *o {
            Optimizer::Sgd {
                lr_start,
                lr_end,
                momentum,
            } => {
                let t = if stages > 1 {
                    stage as f64 / (stages - 1) as f64
                } else {
                    1.0
                };
                let scale = drt_size_scale(mesh);
                Stepper::Sgd {
                    lr: 1.0 / ((1.0 - t) / lr_start + t / lr_end) * scale,
                    scale,
                    momentum,
                    velocity: vec![V3::zeros(); mesh.positions.len()],
                }
            }
            Optimizer::LargeSteps {
                lambda,
                lr_edge,
                beta1,
                beta2,
                clip,
                lr_end_share,
                crease_deg,
                crease_share,
            } => {
                let system = LargeStepsSystem::new(mesh, lambda, (crease_deg, crease_share));
                let llt = system.factor()?;
                let u = system.apply(&mesh.positions);
                let n = mesh.positions.len();
                Stepper::LargeSteps {
                    llt,
                    u,
                    m: Mat::zeros(n, 3),
                    v: 0.0,
                    t: 0,
                    lr: lr_edge * edge_mm,
                    lr_factor: lr_end_share.powf(1.0 / iterations.saturating_sub(1).max(1) as f64),
                    beta1,
                    beta2,
                    clip,
                }
            }
        })
    }

    /// One step along −`grad` (∂E/∂position); returns the new positions.
    pub fn step(&mut self, positions: &[Point3<f64>], grad: &[V3]) -> Vec<Point3<f64>> {
        match self {
            Stepper::Sgd {
                lr,
                scale,
                momentum,
                velocity,
            } => {
                // Nesterov: v ← μv − lr·g; x ← x + μv − lr·g.
                let mut out = Vec::with_capacity(positions.len());
                for ((p, g), v) in positions.iter().zip(grad).zip(velocity.iter_mut()) {
                    let g = g.map(|c| (c * *scale).clamp(-1.0, 1.0));
                    *v = *v * *momentum - g * *lr;
                    out.push(p + *v * *momentum - g * *lr);
                }
                out
            }
            Stepper::LargeSteps {
                llt,
                u,
                m,
                v,
                t,
                lr,
                lr_factor,
                beta1,
                beta2,
                clip,
            } => {
                let n = positions.len();
                let grad = clipped(grad, *clip);
                // ∂E/∂u = (I + λL)⁻¹ ∂E/∂x (the matrix is symmetric).
                let mut gu = Mat::from_fn(n, 3, |i, j| grad[i][j]);
                llt.solve_in_place(gu.as_mut());
                *t += 1;
                let mut g2 = 0.0f64;
                for i in 0..n {
                    for j in 0..3 {
                        let g = gu[(i, j)];
                        m[(i, j)] = *beta1 * m[(i, j)] + (1.0 - *beta1) * g;
                        g2 += g * g;
                    }
                }
                *v = *beta2 * *v + (1.0 - *beta2) * g2 / (3 * n) as f64;
                let lr = *lr * lr_factor.powi(*t - 1);
                let mhat = 1.0 - beta1.powi(*t);
                let vhat = (*v / (1.0 - beta2.powi(*t))).sqrt() + 1e-30;
                for i in 0..n {
                    for j in 0..3 {
                        let step = (m[(i, j)] / mhat / vhat).clamp(-STEP_CLAMP, STEP_CLAMP);
                        u[(i, j)] -= lr * step;
                    }
                }
                let mut x = u.clone();
                llt.solve_in_place(x.as_mut());
                (0..n)
                    .map(|i| Point3::new(x[(i, 0)], x[(i, 1)], x[(i, 2)]))
                    .collect()
            }
        }
    }
}

/// Large Steps' matrix I + L_w over a mesh: L_w the uniform Laplacian whose edge (i, j) weighs
/// λ, or `crease_share`·λ where i or j is a crease vertex (a face more than `crease_deg` degrees
/// from its normal; none when `crease_deg` is 0). Without crease vertices the sums are formed as
/// with a single weight, so the matrix and u are the same to the bit.
struct LargeStepsSystem {
    /// Per vertex, its neighbours, each with whether their edge is a crease vertex's.
    rows: Vec<Vec<(usize, bool)>>,
    /// The weights of a plain and of a crease vertex's edge.
    weights: [f64; 2],
    /// Per vertex, 1 + the weights of its edges.
    diagonal: Vec<f64>,
}

impl LargeStepsSystem {
    fn new(mesh: &TriMesh, lambda: f64, (crease_deg, crease_share): (f64, f64)) -> Self {
        let n = mesh.positions.len();
        let crease: Vec<bool> = if crease_deg > 0.0 {
            let bound = crease_deg.to_radians();
            mesh.normal_spread().iter().map(|&s| s > bound).collect()
        } else {
            vec![false; n]
        };
        let mut rows: Vec<Vec<(usize, bool)>> = vec![Vec::new(); n];
        for e in mesh.interior_edges() {
            let [a, b] = e.verts.map(|v| v as usize);
            let at_crease = crease[a] || crease[b];
            rows[a].push((b, at_crease));
            rows[b].push((a, at_crease));
        }
        let weights = [lambda, lambda * crease_share];
        let diagonal = (rows.iter())
            .map(|row| {
                let creases = row.iter().filter(|r| r.1).count();
                let plain = row.len() - creases;
                1.0 + weights[0] * plain as f64 + weights[1] * creases as f64
            })
            .collect();
        Self {
            rows,
            weights,
            diagonal,
        }
    }

    /// The Cholesky factor of the matrix.
    fn factor(&self) -> Result<faer::sparse::linalg::solvers::Llt<usize, f64>> {
        let n = self.rows.len();
        let mut triplets = Vec::new();
        for (i, row) in self.rows.iter().enumerate() {
            triplets.push(Triplet::new(i, i, self.diagonal[i]));
            triplets.extend(
                row.iter()
                    .map(|&(j, c)| Triplet::new(i, j, -self.weights[c as usize])),
            );
        }
        let m = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &triplets)
            .map_err(|e| anyhow!("Large Steps matrix: {e:?}"))?;
        m.sp_cholesky(Side::Lower)
            .map_err(|e| anyhow!("Large Steps: the matrix I + λL is not positive definite ({e:?})"))
    }

    /// u = (I + L_w)x for the positions x (n × 3).
    fn apply(&self, positions: &[Point3<f64>]) -> Mat<f64> {
        Mat::from_fn(self.rows.len(), 3, |i, j| {
            let mut sums = [0.0; 2];
            for &(k, c) in &self.rows[i] {
                sums[c as usize] += positions[k][j];
            }
            self.diagonal[i] * positions[i][j]
                - self.weights[0] * sums[0]
                - self.weights[1] * sums[1]
        })
    }
}

/// Adam on the object's refractive index, a parameter of the stages of a run with an unknown
/// index ([`super::index`]): each step is the learning rate (index units) times the gradient's
/// running mean over its root mean square (at most [`STEP_CLAMP`]), the rate falling
/// geometrically from [`INDEX_LR`] to [`INDEX_LR_END`] over the stage, the index kept to its
/// range; the stage's estimate is the mean of its last iterates.
pub struct IndexStepper {
    /// The current index.
    pub ior: f64,
    range: (f64, f64),
    m: f64,
    v: f64,
    t: i32,
    lr_factor: f64,
    /// The first iteration averaged, the sum of the averaged indices and their count.
    tail_first: usize,
    tail_sum: f64,
    tail_count: usize,
}

/// The index stepper's learning rate at a stage's first iteration (index units): the dog's
/// first `balanced` stage after the warm-up moves its index 0.11 (1.55 → 1.44) in 150
/// iterations.
pub const INDEX_LR: f64 = 0.005;
/// The index stepper's learning rate at a stage's last iteration (index units).
pub const INDEX_LR_END: f64 = 0.0005;
const INDEX_BETA1: f64 = 0.9;
const INDEX_BETA2: f64 = 0.999;

impl IndexStepper {
    /// From index `ior` within `range`, for `iterations` steps, averaging the last `share` of
    /// them (at least the last).
    pub fn new(ior: f64, range: (f64, f64), iterations: usize, share: f64) -> Self {
        let averaged = ((share * iterations as f64).round() as usize).clamp(1, iterations.max(1));
        Self {
            ior: ior.clamp(range.0, range.1),
            range,
            m: 0.0,
            v: 0.0,
            t: 0,
            lr_factor: (INDEX_LR_END / INDEX_LR).powf(1.0 / (iterations.max(2) - 1) as f64),
            tail_first: iterations.saturating_sub(averaged),
            tail_sum: 0.0,
            tail_count: 0,
        }
    }

    /// One step down `grad` (∂loss/∂index, per unit of the loss) at iteration `it`; `None`, and
    /// no step, when `grad` is not finite.
    pub fn step(&mut self, it: usize, grad: f64) -> Option<()> {
        if !grad.is_finite() {
            return None;
        }
        self.t += 1;
        self.m = INDEX_BETA1 * self.m + (1.0 - INDEX_BETA1) * grad;
        self.v = INDEX_BETA2 * self.v + (1.0 - INDEX_BETA2) * grad * grad;
        let mhat = self.m / (1.0 - INDEX_BETA1.powi(self.t));
        let rms = (self.v / (1.0 - INDEX_BETA2.powi(self.t))).sqrt();
        if rms > 0.0 {
            let lr = INDEX_LR * self.lr_factor.powi(self.t - 1);
            let step = (mhat / rms).clamp(-STEP_CLAMP, STEP_CLAMP) * lr;
            self.ior = (self.ior - step).clamp(self.range.0, self.range.1);
        }
        if it >= self.tail_first {
            self.tail_sum += self.ior;
            self.tail_count += 1;
        }
        Some(())
    }

    /// The mean of the averaged iterates (the current index before any).
    pub fn estimate(&self) -> f64 {
        if self.tail_count == 0 {
            self.ior
        } else {
            self.tail_sum / self.tail_count as f64
        }
    }
}

/// The mean of the vertex positions over a stage's last iterations (Polyak–Ruppert averaging).
pub struct TailMean {
    /// The first iteration averaged.
    first: usize,
    sum: Vec<V3>,
    count: usize,
}

impl TailMean {
    /// Averages the last `share` of `iterations` (none when `share` is 0).
    pub fn new(iterations: usize, share: f64) -> Self {
        let n = (share * iterations as f64).round() as usize;
        Self {
            first: if n == 0 {
                usize::MAX
            } else {
                iterations - n.min(iterations)
            },
            sum: Vec::new(),
            count: 0,
        }
    }

    /// Adds the positions after iteration `it` when it is in the tail.
    pub fn add(&mut self, it: usize, positions: &[Point3<f64>]) {
        if it < self.first {
            return;
        }
        self.sum.resize(positions.len(), V3::zeros());
        for (s, p) in self.sum.iter_mut().zip(positions) {
            *s += p.coords;
        }
        self.count += 1;
    }

    /// The mean, when any iteration was averaged.
    pub fn mean(&self) -> Option<Vec<Point3<f64>>> {
        let n = self.count as f64;
        (self.count > 0).then(|| self.sum.iter().map(|s| Point3::from(s / n)).collect())
    }
}

/// The quantile of the non-zero gradient lengths that [`clipped`] scales: the median is no scale
/// in fine stages, where most vertices see no sampled ray in an iteration.
const CLIP_QUANTILE: f64 = 0.99;

/// `grad` with every vector longer than `clip` × the 99th percentile of the non-zero lengths cut
/// to that length (unchanged when `clip` is 0 or all are zero).
fn clipped(grad: &[V3], clip: f64) -> Vec<V3> {
    if clip <= 0.0 {
        return grad.to_vec();
    }
    let lengths: Vec<f64> = grad.iter().map(|g| g.norm()).collect();
    let mut nonzero: Vec<f64> = lengths.iter().copied().filter(|&l| l > 0.0).collect();
    if nonzero.is_empty() {
        return grad.to_vec();
    }
    let k = ((nonzero.len() - 1) as f64 * CLIP_QUANTILE).round() as usize;
    let bound = clip * *nonzero.select_nth_unstable_by(k, f64::total_cmp).1;
    grad.iter()
        .zip(&lengths)
        .map(|(g, &l)| if l > bound { g * (bound / l) } else { *g })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::shapes::icosphere;

    /// The index stepper on a noisy quadratic loss in the index (minimum 1.48, the gradient's
    /// noise as large as its value 0.07 away), from 1.55 in 150 iterations as in `balanced`: its
    /// estimate settles within 0.003 of the minimum; with the minimum below the range it stays
    /// at the range's floor; a non-finite gradient is refused.
    #[test]
    fn the_index_stepper_settles_at_the_minimum_within_its_range() {
        use rand::{RngExt, SeedableRng};
        let run = |minimum: f64| {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
            let mut x = IndexStepper::new(1.55, (1.4, 1.7), 150, 0.5);
            for it in 0..150 {
                let noise = 0.14 * (2.0 * rng.random::<f64>() - 1.0);
                x.step(it, 2.0 * (x.ior - minimum) + noise).unwrap();
            }
            x.estimate()
        };
        let settled = run(1.48);
        assert!((settled - 1.48).abs() < 0.003, "{settled}");
        assert!((run(1.3) - 1.4).abs() < 1e-12);
        let mut x = IndexStepper::new(1.55, (1.4, 1.7), 10, 0.5);
        assert_eq!(x.step(0, f64::NAN), None);
        assert_eq!(x.ior, 1.55);
    }

    #[test]
    fn tail_mean_averages_only_the_last_share_of_iterations() {
        let at = |x: f64| vec![Point3::new(x, 2.0 * x, -x)];
        let mut tail = TailMean::new(4, 0.5);
        for (it, x) in [100.0, 50.0, 1.0, 3.0].into_iter().enumerate() {
            tail.add(it, &at(x));
        }
        assert_eq!(tail.mean(), Some(at(2.0)));
        let mut off = TailMean::new(4, 0.0);
        off.add(3, &at(1.0));
        assert_eq!(off.mean(), None);
    }

    #[test]
    fn clipping_cuts_only_outliers_to_the_bound() {
        // 200 unit gradients, one of length 1e12 and one zero: the 99th percentile is 1.
        let mut grad = vec![V3::new(1.0, 0.0, 0.0); 200];
        grad.push(V3::new(0.0, 0.0, -1e12));
        grad.push(V3::zeros());
        let out = clipped(&grad, 5.0);
        assert_eq!(out[..200], grad[..200]);
        assert!((out[200] - V3::new(0.0, 0.0, -5.0)).norm() < 1e-9);
        assert_eq!(out[201], V3::zeros());
        assert_eq!(clipped(&grad, 0.0), grad);
    }

    /// How far (mm, mean over vertices) 20 Large Steps steps shrink a sphere of radius 10 mm
    /// under the gradient ∂E/∂x = outward unit normal, when vertex 0's gradient in the first step
    /// is 1e12 times longer (one outlying ray).
    fn shrink_after_one_outlier(clip: f64) -> f64 {
        let mesh = crate::mesh::shapes::icosphere(10.0, 3);
        let o = Optimizer::LargeSteps {
            lambda: 20.0,
            lr_edge: 0.3,
            beta1: 0.9,
            beta2: 0.999,
            clip,
            lr_end_share: 1.0,
            crease_deg: 0.0,
            crease_share: 1.0,
        };
        let mut stepper = Stepper::new(&o, &mesh, (0, 1), 1.0, 20).unwrap();
        let mut positions = mesh.positions.clone();
        for it in 0..20 {
            let mut grad: Vec<V3> = positions.iter().map(|p| p.coords.normalize()).collect();
            if it == 0 {
                grad[0] *= 1e12;
            }
            positions = stepper.step(&positions, &grad);
        }
        let radii: f64 = positions.iter().map(|p| p.coords.norm()).sum();
        10.0 - radii / positions.len() as f64
    }

    /// A 20 mm box (0.625 mm edges) whose vertices on one of its edges are pulled outward along
    /// their normals (as silhouettes pull a rounded crease towards the outline) while springs
    /// (1 per mm) hold every other vertex where it was: after 60 Large Steps steps, the mean
    /// displacement of the vertices beside that edge (on its two sides, within 2 mm of it) over
    /// the pulled vertices' mean displacement.
    fn spill_onto_the_sides(crease_deg: f64) -> f64 {
        const STEPS: usize = 60;
        let mesh = crate::mesh::shapes::cuboid(V3::new(20.0, 20.0, 20.0), 32);
        let normals = mesh.vertex_normals();
        let pulled: Vec<bool> = (mesh.positions.iter())
            .map(|p| (p.x - 10.0).abs() < 1e-9 && (p.z - 10.0).abs() < 1e-9)
            .collect();
        let o = Optimizer::LargeSteps {
            lambda: 20.0,
            lr_edge: 0.3,
            beta1: 0.9,
            beta2: 0.999,
            clip: 0.0,
            lr_end_share: 1.0,
            crease_deg,
            crease_share: 0.25,
        };
        let mut stepper = Stepper::new(&o, &mesh, (0, 1), 1.0, 20).unwrap();
        let mut positions = mesh.positions.clone();
        for _ in 0..STEPS {
            let grad: Vec<V3> = (0..positions.len())
                .map(|i| {
                    if pulled[i] {
                        -normals[i]
                    } else {
                        positions[i] - mesh.positions[i]
                    }
                })
                .collect();
            positions = stepper.step(&positions, &grad);
        }
        // The vertices beside the edge: on its two sides, within 2 mm of it.
        let near = |p: &Point3<f64>| {
            let d = (p.x - 10.0).abs().max((p.z - 10.0).abs());
            d > 1e-9 && (p.x - 10.0).abs().min((p.z - 10.0).abs()) < 1e-9 && d <= 2.0
        };
        let mean_moved = |which: &dyn Fn(usize) -> bool| {
            let moved: Vec<f64> = (0..positions.len())
                .filter(|&i| which(i))
                .map(|i| (positions[i] - mesh.positions[i]).norm())
                .collect();
            crate::util::mean(&moved)
        };
        mean_moved(&|i| near(&mesh.positions[i])) / mean_moved(&|i| pulled[i])
    }

    /// With the crease vertices' edges at a quarter of λ, a pull on one of a box's edges moves the
    /// sides beside it less (0.17 of the edge's displacement against 0.51): the edge sharpens
    /// instead of the sides bulging.
    #[test]
    fn creases_under_large_steps_keep_their_pull_off_the_faces_beside_them() {
        let (plain, crease) = (spill_onto_the_sides(0.0), spill_onto_the_sides(25.0));
        eprintln!("spill: plain {plain}, crease {crease}");
        assert!(crease < 0.7 * plain, "{crease} against {plain}");
    }

    #[test]
    fn clipping_keeps_one_outlying_gradient_from_freezing_the_other_vertices() {
        // 20 steps of 0.3 mm (the learning rate) shrink the sphere by about 20 · 0.3 mm.
        let (free, frozen) = (
            shrink_after_one_outlier(10.0),
            shrink_after_one_outlier(0.0),
        );
        assert!(free > 3.0, "with clipping the sphere shrinks by {free} mm");
        assert!(
            frozen.abs() < 0.1 * free,
            "without clipping: {frozen} mm against {free} mm"
        );
    }

    /// A scale-free loss's gradient is inversely proportional to the object's size: SGD steps on
    /// an object a hundredth (a tenth) the size, with a hundred (ten) times the gradient, are the
    /// other one's steps scaled, below (above) DRT's sizes; within them they are DRT's steps.
    #[test]
    fn drt_steps_follow_the_object_outside_drts_sizes() {
        let o = Optimizer::Sgd {
            lr_start: 0.1,
            lr_end: 0.05,
            momentum: 0.95,
        };
        // Moves after three steps on an icosphere (bounding-box diagonal 2√3 × radius).
        let moves = |radius: f64, grad_scale: f64| {
            let mesh = icosphere(radius, 2);
            let mut stepper = Stepper::new(&o, &mesh, (0, 3), 1.0, 3).unwrap();
            let grad: Vec<V3> = (0..mesh.positions.len())
                .map(|i| V3::new(0.3, -2.0, 0.01 * i as f64) * grad_scale)
                .collect();
            let mut p = mesh.positions.clone();
            for _ in 0..3 {
                p = stepper.step(&p, &grad);
            }
            p.iter()
                .zip(&mesh.positions)
                .map(|(p, q)| p - q)
                .collect::<Vec<V3>>()
        };
        let similar = |a: &[V3], b: &[V3], ratio: f64| {
            a.iter()
                .zip(b)
                .all(|(a, b)| (a * ratio - b).norm() <= 1e-9 * b.norm().max(1e-12))
        };
        assert!(
            similar(&moves(0.4, 100.0), &moves(40.0, 1.0), 100.0),
            "small"
        );
        assert!(similar(&moves(1e4, 0.1), &moves(1e3, 1.0), 0.1), "large");
        assert!(
            similar(&moves(70.0, 1.0), &moves(85.0, 1.0), 1.0),
            "DRT's sizes"
        );
        assert!(!similar(&moves(40.0, 1.0), &moves(70.0, 1.0), 1.0));
    }
}
