//! The membrane term on the vertices the refraction data cannot see: the Dirichlet energy
//! Σ ‖x_a − x_b‖² / h² over every edge with an end among them (h the stage's edge length), a
//! function of those vertices alone — the others are its constants, so it never pulls the rim
//! that holds a patch. Its minimum spans each patch as a harmonic surface on its rim — a flat
//! one across a planar rim — and its gradient on a uniformly bent patch is about the mean
//! curvature times the normal, the same everywhere on it, so the patch flattens as a whole. (A
//! bending penalty — dihedral angles, or the squared umbrella operator — has no gradient inside
//! a uniformly bent patch and moves it only from its rim inward; and with the rim free to move,
//! the energy shrinks the patch and everything attached to it.)
//!
//! On a graded mesh (long edges in a flat face's middle, short ones where the surface bends)
//! the energy also pulls each vertex towards its neighbours' centroid along the surface, a pull
//! along a flat face that dragged a block's plinth outwards stage by stage; there the
//! optimisation takes the term's gradient along each vertex normal only ([`along_normals`]), and
//! where a vertex sits on the surface is the remesher's to decide.

use nalgebra::Vector3;
use rayon::prelude::*;

use super::{Accumulator, Contributions};
use crate::mesh::{InteriorEdge, TriMesh};

type V3 = Vector3<f64>;

/// Edges per parallel chunk.
const EDGE_CHUNK: usize = 4096;

/// Adds Σ ‖x_a − x_b‖² / `edge_mm`² over the `edges` with an end `selected` and its gradient
/// with respect to the selected vertices (the others are constants of the term) to `acc`, as a
/// mean over all of the mesh's vertices (their count is the term's
/// [`Accumulator::weight`]), so that the term's pull on a vertex compares with the data terms' at
/// every resolution.
pub fn add_membrane(
    mesh: &TriMesh,
    edges: &[InteriorEdge],
    selected: &[bool],
    edge_mm: f64,
    acc: &mut Accumulator,
) {
    let scale = 1.0 / (edge_mm * edge_mm);
    let mut chunks: Vec<Contributions> = edges
        .par_chunks(EDGE_CHUNK)
        .map(|chunk| {
            let mut c = Contributions::with_capacity(2 * chunk.len(), 0);
            for e in chunk {
                let [a, b] = e.verts;
                if !(selected[a as usize] || selected[b as usize]) {
                    continue;
                }
                let d: V3 = mesh.positions[a as usize] - mesh.positions[b as usize];
                c.loss += scale * d.norm_squared();
                c.used += 1;
                let g = d * (2.0 * scale);
                if selected[a as usize] {
                    c.grad.push((a, g));
                }
                if selected[b as usize] {
                    c.grad.push((b, -g));
                }
            }
            c
        })
        .collect();
    chunks.push(Contributions {
        weight: mesh.positions.len() as f64,
        ..Contributions::default()
    });
    acc.add(&chunks);
}

/// Replaces each vector of `grad` by its component along the unit vertex normal of the same
/// index in `normals`: the gradient of a term with respect to each vertex's offset along its
/// normal (the normals held fixed), as a position gradient.
pub fn along_normals(grad: &mut [V3], normals: &[V3]) {
    for (g, n) in grad.iter_mut().zip(normals) {
        *g = n * n.dot(g);
    }
}
