//! The smoothness term (docs/architecture.md §4): a penalty ψ(cos θ) on every interior edge, θ the angle
//! between the normals of its two faces.

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::diff::{face_cross_adjoint, normalize_adjoint};
use super::{Accumulator, Contributions, DropReason};
use crate::mesh::{InteriorEdge, TriMesh};

type V3 = Vector3<f64>;

/// The penalty on an edge's dihedral angle.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Smoothness {
    /// −log(1 + cos θ) (the paper and DRT): unbounded as a fold closes (θ → 180°).
    NegLogOnePlusCos,
    /// log(2 − cos θ) (a published reproduction): bounded, gentle on sharp features.
    LogTwoMinusCos,
    /// τ·log(1 + (1 − cos θ)/τ) with a fixed τ > 0: log(2 − cos θ) at τ = 1, and the smaller
    /// τ, the more tolerant of large angles (sharp features).
    Tolerant { tau: f64 },
}

impl Smoothness {
    /// ψ(c) and dψ/dc.
    pub fn apply(&self, c: f64) -> (f64, f64) {
        match *self {
            Smoothness::NegLogOnePlusCos => (-(1.0 + c).ln(), -1.0 / (1.0 + c)),
            Smoothness::LogTwoMinusCos => ((2.0 - c).ln(), -1.0 / (2.0 - c)),
            Smoothness::Tolerant { tau } => {
                let x = (1.0 - c) / tau;
                (tau * x.ln_1p(), -1.0 / (1.0 + x))
            }
        }
    }
}

/// Adds Σ ψ(cos θ) over `edges` (from [`TriMesh::interior_edges`]) and its gradient to `acc`.
/// Edges with a zero-area face or a non-finite value are dropped and counted.
pub fn add_smoothness(
    mesh: &TriMesh,
    edges: &[InteriorEdge],
    kind: Smoothness,
    acc: &mut Accumulator,
) {
    let crosses: Vec<V3> = (0..mesh.faces.len())
        .into_par_iter()
        .map(|f| mesh.face_cross(f))
        .collect();
    let chunks: Vec<Contributions> = edges
        .par_chunks(4096)
        .map(|chunk| {
            let mut c = Contributions::with_capacity(6 * chunk.len(), 0);
            for e in chunk {
                let [f, g] = e.faces;
                match pair_gradient(mesh, &crosses, [f as usize, g as usize], kind) {
                    Ok((loss, grads)) => {
                        c.loss += loss;
                        c.used += 1;
                        c.weight += 1.0;
                        c.grad.extend_from_slice(&grads);
                    }
                    Err(r) => c.drops.count(r),
                }
            }
            c
        })
        .collect();
    acc.add(&chunks);
}

/// ψ of the edge between faces `f` and `g` and the gradient on the vertices of both; `crosses`
/// holds every face's [`TriMesh::face_cross`] (computed once for all the edges).
fn pair_gradient(
    mesh: &TriMesh,
    crosses: &[V3],
    [f, g]: [usize; 2],
    kind: Smoothness,
) -> Result<(f64, [(u32, V3); 6]), DropReason> {
    let (nf, ng) = (crosses[f], crosses[g]);
    let (lf, lg) = (nf.norm(), ng.norm());
    if lf == 0.0 || lg == 0.0 {
        return Err(DropReason::NonFinite);
    }
    let (uf, ug) = (nf / lf, ng / lg);
    let (loss, dpsi) = kind.apply(uf.dot(&ug));
    if !(loss.is_finite() && dpsi.is_finite()) {
        return Err(DropReason::NonFinite);
    }
    let mut out = [(0u32, V3::zeros()); 6];
    for (k, (face, u, other, len)) in [(f, uf, ug, lf), (g, ug, uf, lg)].into_iter().enumerate() {
        let gn = normalize_adjoint(&u, len, &(other * dpsi));
        let tri: [Point3<f64>; 3] = mesh.corners(face);
        let mut gt = [V3::zeros(); 3];
        face_cross_adjoint(&tri, &gn, &mut gt);
        for j in 0..3 {
            out[3 * k + j] = (mesh.faces[face][j], gt[j]);
        }
    }
    Ok((loss, out))
}
