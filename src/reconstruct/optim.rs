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
        lr: f64,
        beta1: f64,
        beta2: f64,
    },
}

impl Stepper {
    /// The optimiser for stage `stage` of `stages` on `mesh`, whose target edge is `edge_mm`.
    pub fn new(
        o: &Optimizer,
        mesh: &TriMesh,
        stage: usize,
        stages: usize,
        edge_mm: f64,
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
                Stepper::Sgd {
                    lr: 1.0 / ((1.0 - t) / lr_start + t / lr_end),
                    momentum,
                    velocity: vec![V3::zeros(); mesh.positions.len()],
                }
            }
            Optimizer::LargeSteps {
                lambda,
                lr_edge,
                beta1,
                beta2,
            } => {
                let n = mesh.positions.len();
                let mut neighbours: Vec<Vec<usize>> = vec![Vec::new(); n];
                for e in mesh.interior_edges() {
                    let [a, b] = e.verts.map(|v| v as usize);
                    neighbours[a].push(b);
                    neighbours[b].push(a);
                }
                let mut triplets = Vec::new();
                for (i, nb) in neighbours.iter().enumerate() {
                    triplets.push(Triplet::new(i, i, 1.0 + lambda * nb.len() as f64));
                    triplets.extend(nb.iter().map(|&j| Triplet::new(i, j, -lambda)));
                }
                let m = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &triplets)
                    .map_err(|e| anyhow!("Large Steps matrix: {e:?}"))?;
                let llt = m.sp_cholesky(Side::Lower).map_err(|e| {
                    anyhow!("Large Steps: the matrix I + λL is not positive definite ({e:?})")
                })?;
                // u = (I + λL)x.
                let x = Mat::from_fn(n, 3, |i, j| mesh.positions[i][j]);
                let mut u = Mat::zeros(n, 3);
                for (i, nb) in neighbours.iter().enumerate() {
                    for j in 0..3 {
                        let s: f64 = nb.iter().map(|&k| x[(k, j)]).sum();
                        u[(i, j)] = (1.0 + lambda * nb.len() as f64) * x[(i, j)] - lambda * s;
                    }
                }
                Stepper::LargeSteps {
                    llt,
                    u,
                    m: Mat::zeros(n, 3),
                    v: 0.0,
                    t: 0,
                    lr: lr_edge * edge_mm,
                    beta1,
                    beta2,
                }
            }
        })
    }

    /// One step along −`grad` (∂E/∂position); returns the new positions.
    pub fn step(&mut self, positions: &[Point3<f64>], grad: &[V3]) -> Vec<Point3<f64>> {
        match self {
            Stepper::Sgd {
                lr,
                momentum,
                velocity,
            } => {
                // Nesterov: v ← μv − lr·g; x ← x + μv − lr·g.
                let mut out = Vec::with_capacity(positions.len());
                for ((p, g), v) in positions.iter().zip(grad).zip(velocity.iter_mut()) {
                    let g = g.map(|c| c.clamp(-1.0, 1.0));
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
                beta1,
                beta2,
            } => {
                let n = positions.len();
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
                let mhat = 1.0 - beta1.powi(*t);
                let vhat = (*v / (1.0 - beta2.powi(*t))).sqrt() + 1e-30;
                for i in 0..n {
                    for j in 0..3 {
                        let step = (m[(i, j)] / mhat / vhat).clamp(-STEP_CLAMP, STEP_CLAMP);
                        u[(i, j)] -= *lr * step;
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
