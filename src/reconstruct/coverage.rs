//! What the refraction data of a stage has seen: the vertices that no compared ray's path has
//! touched (a face seen only edge-on, such as the top of a block on a level rig, where every ray
//! through it grazes or is totally reflected) get the membrane term
//! ([`crate::loss::membrane`]), so that a prior, not the start mesh's accident, decides their
//! shape. The silhouettes do not count as seeing a vertex: the visual hull bulges such a face
//! into a dome that lies on the outline in many views, consistent with every mask and as much
//! as the flat face is.

use nalgebra::Vector3;

use crate::mesh::InteriorEdge;

type V3 = Vector3<f64>;

/// The smallest unseen patch the membrane term acts on, as a share of the mesh's vertices: a
/// face seen only edge-on makes a patch of thousands of vertices, while a few vertices that no
/// sampled ray happened to touch (a crease, a small hidden hollow) are left to the data terms
/// around them — on a curved patch the membrane pulls inward with the curvature, which only a
/// face large enough to have been flattened by the hull's cones should feel.
pub const MIN_PATCH_SHARE: f64 = 0.01;

/// Per vertex of a stage's mesh (fixed within the stage), whether the refraction term has had
/// no gradient on it in any iteration so far.
pub struct Coverage {
    unseen: Vec<bool>,
    iterations: usize,
    /// Iterations before the record is trusted: enough for every fitted view to be sampled
    /// about once.
    warm_in: usize,
}

impl Coverage {
    /// A record for a mesh of `vertices` vertices, trusted after `warm_in` iterations.
    pub fn new(vertices: usize, warm_in: usize) -> Self {
        Self {
            unseen: vec![true; vertices],
            iterations: 0,
            warm_in: warm_in.max(1),
        }
    }

    /// Records an iteration's refraction gradient (per vertex, ∂E/∂position).
    pub fn record(&mut self, refraction_grad: &[V3]) {
        for (u, g) in self.unseen.iter_mut().zip(refraction_grad) {
            *u &= *g == V3::zeros();
        }
        self.iterations += 1;
    }

    /// Per vertex, whether no compared ray has touched it; `None` while the record is younger
    /// than its warm-in.
    pub fn unseen(&self) -> Option<&[bool]> {
        (self.iterations >= self.warm_in).then_some(self.unseen.as_slice())
    }

    /// Per vertex, whether it lies in a patch of unseen vertices (connected by `edges` with both
    /// ends unseen) of at least [`MIN_PATCH_SHARE`] of the mesh's vertices; `None` while the
    /// record is younger than its warm-in.
    pub fn unseen_patches(&self, edges: &[InteriorEdge]) -> Option<Vec<bool>> {
        let unseen = self.unseen()?;
        let mut root: Vec<u32> = (0..unseen.len() as u32).collect();
        fn find(root: &mut [u32], mut v: u32) -> u32 {
            while root[v as usize] != v {
                root[v as usize] = root[root[v as usize] as usize];
                v = root[v as usize];
            }
            v
        }
        for e in edges
            .iter()
            .filter(|e| e.verts.iter().all(|&v| unseen[v as usize]))
        {
            let (a, b) = (find(&mut root, e.verts[0]), find(&mut root, e.verts[1]));
            root[a.max(b) as usize] = a.min(b);
        }
        let mut size = vec![0usize; unseen.len()];
        let roots: Vec<u32> = (0..unseen.len() as u32)
            .map(|v| find(&mut root, v))
            .collect();
        for (v, &r) in roots.iter().enumerate() {
            size[r as usize] += unseen[v] as usize;
        }
        let min = (MIN_PATCH_SHARE * unseen.len() as f64).ceil() as usize;
        Some(
            (0..unseen.len())
                .map(|v| unseen[v] && size[roots[v] as usize] >= min.max(1))
                .collect(),
        )
    }

    /// Share of the vertices no compared ray has touched.
    pub fn unseen_share(&self) -> f64 {
        let n = self.unseen.iter().filter(|u| **u).count();
        n as f64 / self.unseen.len().max(1) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_vertex_is_unseen_until_a_ray_touches_it_and_the_record_counts_once_warm() {
        let touched = |k: usize| -> Vec<V3> {
            (0..4)
                .map(|v| {
                    if v == k {
                        V3::new(0.0, 1e-9, 0.0)
                    } else {
                        V3::zeros()
                    }
                })
                .collect()
        };
        let mut coverage = Coverage::new(4, 2);
        coverage.record(&touched(1));
        assert!(coverage.unseen().is_none(), "too young");
        coverage.record(&touched(3));
        assert_eq!(coverage.unseen().unwrap(), &[true, false, true, false]);
        coverage.record(&touched(9));
        assert_eq!(
            coverage.unseen().unwrap(),
            &[true, false, true, false],
            "seen stays seen"
        );
        assert_eq!(coverage.unseen_share(), 0.5);
    }

    #[test]
    fn only_patches_of_at_least_the_minimum_share_count() {
        // A strip of 300 vertices in a row: the first 10 and the last 150 unseen, split by seen
        // ones; the minimum patch is 3 vertices (1 % of 300).
        let n = 300u32;
        let edges: Vec<InteriorEdge> = (0..n - 1)
            .map(|v| InteriorEdge {
                verts: [v, v + 1],
                faces: [0, 0],
            })
            .collect();
        let mut coverage = Coverage::new(n as usize, 1);
        let seen = |v: usize| (10..150).contains(&v) || v == 1 || v == 5;
        let grad: Vec<V3> = (0..n as usize)
            .map(|v| {
                if seen(v) {
                    V3::new(1.0, 0.0, 0.0)
                } else {
                    V3::zeros()
                }
            })
            .collect();
        coverage.record(&grad);
        let patches = coverage.unseen_patches(&edges).unwrap();
        // 0 alone and 2..=4 and 6..=9 (sizes 1, 3, 4), then 150..300.
        let expected: Vec<bool> = (0..n as usize)
            .map(|v| (2..5).contains(&v) || (6..10).contains(&v) || v >= 150)
            .collect();
        assert_eq!(patches, expected);
    }
}
