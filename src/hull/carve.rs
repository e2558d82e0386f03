//! Space carving against the silhouettes, coarse to fine, into the block-sparse field that
//! marching cubes reads.
//!
//! The carving field at a world point is the (k+1)-th smallest of the views' signed distances
//! (mm, see [`Silhouette::signed_distance_mm`]): > 0 where the point projects inside the mask in
//! all views but at most k. It changes by about as much as the point moves (a projection moves
//! by f·δ/z pixels when the point moves by δ mm), which is what lets a whole cell be classified
//! from its centre.
//!
//! 1. Coarse: cells of about 1/64 of a box around the turntable axis spanned by the camera's
//!    field of view; cells whose centre is far outside are dropped; the rest bound the fine box.
//! 2. Fine: the fine box is cut into blocks of `block`³ voxels; a block is inside, outside, or on
//!    the surface from the field at its centre (two bitsets); only surface blocks are sampled at
//!    every voxel corner. A block whose class disagrees with a sampled value on a shared face,
//!    edge or corner becomes a surface block too, until none does — so every cell that changes
//!    sign is sampled, and marching cubes gets a closed surface.

use crate::util::progress::StepProgress;
use anyhow::{bail, Result};
use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use crate::mesh::marching_cubes::{FieldBlock, Grid};
use crate::scan::silhouette::Silhouette;

/// The carving field over a set of silhouettes.
pub struct Field<'a> {
    pub silhouettes: &'a [&'a Silhouette],
    /// Views a point may fall outside of and still be kept (mask errors).
    pub tolerance: usize,
}

impl Field<'_> {
    /// The field at `p` (mm, world frame); stops early, returning a value ≤ `floor`, once the
    /// point is known to be further outside than `floor` (< 0).
    pub fn value(&self, p: &Point3<f64>, floor: f64) -> f64 {
        let k = self.tolerance;
        let mut smallest = [f64::INFINITY; 8];
        let keep = (k + 1).min(smallest.len());
        for s in self.silhouettes {
            let d = s.signed_distance_mm(p);
            if d < smallest[keep - 1] {
                let mut i = keep - 1;
                while i > 0 && smallest[i - 1] > d {
                    smallest[i] = smallest[i - 1];
                    i -= 1;
                }
                smallest[i] = d;
                if smallest[keep - 1] < floor {
                    break;
                }
            }
        }
        smallest[keep - 1]
    }
}

/// Figures of a carve.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct CarveStats {
    /// The fine grid: voxel size (mm), voxels per axis, origin (mm, world frame).
    pub voxel_mm: f64,
    pub dims: [usize; 3],
    pub origin: [f64; 3],
    pub blocks: usize,
    pub inside_blocks: usize,
    pub surface_blocks: usize,
    /// Surface blocks added because a neighbour's samples disagreed with their class.
    pub promoted_blocks: usize,
    /// Field evaluations (points × views, before early exits: points only).
    pub evaluated_points: usize,
}

/// The most fine voxels along any axis of the hull's grid (0.05 mm over 200 mm).
pub const MAX_VOXELS_PER_AXIS: usize = 4096;

/// Carves the fine field: returns the grid, the sampled surface blocks, and figures.
pub fn carve(
    field: &Field,
    camera_centre_mm: Point3<f64>,
    half_fov_tan: f64,
    voxel_mm: f64,
    block: usize,
    progress: &dyn StepProgress,
) -> Result<(Grid, Vec<FieldBlock>, CarveStats)> {
    let mut stats = CarveStats {
        voxel_mm,
        ..Default::default()
    };
    progress.phase("coarse carve", 0);
    let (lo, hi) = coarse_bounds(field, camera_centre_mm, half_fov_tan, voxel_mm, &mut stats)?;
    let fine = FineGrid::new(lo, hi, voxel_mm, block)?;
    stats.dims = fine.dims;
    stats.origin = [lo.x, lo.y, lo.z];
    stats.blocks = fine.blocks();
    progress.phase("classify blocks", 0);
    let (mut inside, mut surface) = classify_blocks(field, &fine);
    stats.evaluated_points += fine.blocks();
    let blocks = sample_surface(
        field,
        &fine,
        &mut inside,
        &mut surface,
        &mut stats,
        progress,
    );
    stats.surface_blocks = blocks.len();
    stats.inside_blocks = inside.count();
    let grid = Grid {
        origin: lo,
        step: voxel_mm,
        block,
    };
    Ok((grid, blocks, stats))
}

/// Step 1: a 64³ grid over a cube around the axis point nearest the camera, as wide as the field
/// of view at that distance; the box (mm, world frame) of the cells not far outside, with a
/// voxel of margin.
fn coarse_bounds(
    field: &Field,
    camera_centre_mm: Point3<f64>,
    half_fov_tan: f64,
    voxel_mm: f64,
    stats: &mut CarveStats,
) -> Result<(Point3<f64>, Point3<f64>)> {
    let axis_centre = Point3::new(0.0, camera_centre_mm.y, 0.0);
    let dist = (camera_centre_mm - axis_centre).norm();
    let half = 1.2 * dist * half_fov_tan;
    let n0 = 64usize;
    let cell0 = 2.0 * half / n0 as f64;
    let lo0 = axis_centre - Vector3::repeat(half);
    let reach0 = 0.9 * cell0 + 2.0 * voxel_mm;
    let corner = |c: [usize; 3]| lo0 + cell0 * Vector3::from(c.map(|x| x as f64));
    let alive: Vec<[usize; 3]> = (0..n0 * n0 * n0)
        .into_par_iter()
        .filter_map(|idx| {
            let c = [idx % n0, (idx / n0) % n0, idx / (n0 * n0)];
            let p = corner(c) + Vector3::repeat(0.5 * cell0);
            (field.value(&p, -reach0) > -reach0).then_some(c)
        })
        .collect();
    stats.evaluated_points += n0 * n0 * n0;
    if alive.is_empty() {
        bail!("the silhouettes leave nothing: no point of space projects inside every mask (are the masks and the calibration of the same scan?)");
    }
    let cmin: [usize; 3] = std::array::from_fn(|a| alive.iter().map(|c| c[a]).min().unwrap_or(0));
    let cmax: [usize; 3] = std::array::from_fn(|a| alive.iter().map(|c| c[a]).max().unwrap_or(0));
    if (0..3).any(|a| cmin[a] == 0 || cmax[a] == n0 - 1) {
        if 2.0 * voxel_mm > cell0 {
            // The voxel margin, not the masks, reached the border: a small object.
            bail!(
                "the hull's voxels ({} mm) are too coarse for this scan: the camera sees only \
                 {:.3} mm across at the turntable axis; use --voxel-mm {} or finer \
                 (reconstruct: --hull-voxel-mm)",
                crate::util::short_number(voxel_mm),
                2.0 * half / 1.2,
                one_digit_below(cell0 / 4.0)
            );
        }
        bail!("the hull is not bounded inside the camera's field of view: too few views from different directions, or masks that reach the image border");
    }
    let margin = Vector3::repeat(voxel_mm);
    Ok((corner(cmin) - margin, corner(cmax.map(|x| x + 1)) + margin))
}

/// `x` (> 0) rounded down to one significant digit, written out (0.0137 → "0.01").
fn one_digit_below(x: f64) -> String {
    let exponent = x.log10().floor();
    let digit = (x / 10f64.powf(exponent)).floor();
    let decimals = (-exponent).max(0.0) as usize;
    format!("{:.decimals$}", digit * 10f64.powf(exponent))
}

/// The fine grid: a whole number of blocks of `block`³ voxels from `lo` (mm, world frame).
struct FineGrid {
    lo: Point3<f64>,
    voxel_mm: f64,
    block: usize,
    /// Blocks per axis.
    nb: [usize; 3],
    /// Voxels per axis.
    dims: [usize; 3],
}

impl FineGrid {
    /// The grid over [`lo`, `hi`], checked against [`MAX_VOXELS_PER_AXIS`] and the memory budget.
    fn new(lo: Point3<f64>, hi: Point3<f64>, voxel_mm: f64, block: usize) -> Result<Self> {
        let nb: [usize; 3] =
            std::array::from_fn(|a| ((hi[a] - lo[a]) / (voxel_mm * block as f64)).ceil() as usize);
        let widest = nb.iter().map(|&n| n * block).max().unwrap_or(0);
        if widest > MAX_VOXELS_PER_AXIS {
            bail!(
                "--voxel-mm {voxel_mm} is too fine for an object this size: {widest} voxels \
                 across, at most {MAX_VOXELS_PER_AXIS}; use at least {:.4} mm",
                voxel_mm * widest as f64 / MAX_VOXELS_PER_AXIS as f64
            );
        }
        // A class byte per block, and the corner values of the surface blocks (about the area
        // of the grid's six faces in blocks).
        let nb_max = *nb.iter().max().unwrap_or(&0) as u128;
        crate::util::budget::check(
            &format!("a {nb_max}³-block grid (--voxel-mm {voxel_mm})"),
            nb.iter().map(|&n| n as u128).product::<u128>()
                + 6 * nb_max * nb_max * 4 * ((block + 1) as u128).pow(3),
            1,
            "use a larger --voxel-mm",
        )?;
        Ok(Self {
            lo,
            voxel_mm,
            block,
            nb,
            dims: nb.map(|n| n * block),
        })
    }

    fn blocks(&self) -> usize {
        self.nb[0] * self.nb[1] * self.nb[2]
    }

    /// Block coordinates of block index `b`.
    fn block_coords(&self, b: usize) -> [usize; 3] {
        let nb = self.nb;
        [b % nb[0], (b / nb[0]) % nb[1], b / (nb[0] * nb[1])]
    }

    /// The position of grid point `g` (mm).
    fn point(&self, g: [usize; 3]) -> Point3<f64> {
        self.lo + self.voxel_mm * Vector3::from(g.map(|x| x as f64))
    }

    /// True for a grid point on the grid's outer faces (forced outside).
    fn on_border(&self, g: [usize; 3]) -> bool {
        (0..3).any(|a| g[a] == 0 || g[a] == self.dims[a])
    }
}

/// What a block is, from the field at its centre.
#[derive(Clone, Copy, PartialEq)]
enum BlockClass {
    Outside,
    Inside,
    Surface,
}

/// Step 2: every block's class; returns the inside and surface sets.
fn classify_blocks(field: &Field, fine: &FineGrid) -> (BitSet, BitSet) {
    let bsize = fine.voxel_mm * fine.block as f64;
    let reach = 1.5 * (3f64.sqrt() / 2.0) * bsize + 2.0 * fine.voxel_mm;
    let classes: Vec<BlockClass> = (0..fine.blocks())
        .into_par_iter()
        .map(|b| {
            let c = fine.block_coords(b);
            let centre = fine.point(c.map(|x| x * fine.block)) + Vector3::repeat(0.5 * bsize);
            let v = field.value(&centre, -reach);
            let touches_grid_border = (0..3).any(|a| c[a] == 0 || c[a] == fine.nb[a] - 1);
            if v < -reach {
                BlockClass::Outside
            } else if v > reach && !touches_grid_border {
                BlockClass::Inside
            } else {
                BlockClass::Surface
            }
        })
        .collect();
    let mut inside = BitSet::new(fine.blocks());
    let mut surface = BitSet::new(fine.blocks());
    for (b, &c) in classes.iter().enumerate() {
        match c {
            BlockClass::Inside => inside.set(b),
            BlockClass::Surface => surface.set(b),
            BlockClass::Outside => {}
        }
    }
    (inside, surface)
}

/// The field at every corner of block `b` (grid-border points forced outside).
fn sample_block(field: &Field, fine: &FineGrid, b: usize) -> FieldBlock {
    let n1 = fine.block + 1;
    let corner = fine.block_coords(b).map(|x| x * fine.block);
    let mut values = Vec::with_capacity(n1 * n1 * n1);
    for k in 0..n1 {
        for j in 0..n1 {
            for i in 0..n1 {
                let g = [corner[0] + i, corner[1] + j, corner[2] + k];
                let v = field.value(&fine.point(g), -2.0 * fine.voxel_mm);
                let v = if fine.on_border(g) {
                    v.min(-0.01 * fine.voxel_mm)
                } else {
                    v
                };
                values.push(v as f32);
            }
        }
    }
    FieldBlock { corner, values }
}

/// Step 3: samples the surface blocks, promoting to the surface every block whose class a shared
/// sample contradicts, until none does; blocks in a deterministic order.
fn sample_surface(
    field: &Field,
    fine: &FineGrid,
    inside: &mut BitSet,
    surface: &mut BitSet,
    stats: &mut CarveStats,
    progress: &dyn StepProgress,
) -> Vec<FieldBlock> {
    let n1 = fine.block + 1;
    let mut todo: Vec<usize> = surface.iter().collect();
    let mut blocks: Vec<FieldBlock> = Vec::new();
    progress.phase("sample surface blocks", todo.len() as u64);
    while !todo.is_empty() {
        let sampled: Vec<FieldBlock> = todo
            .par_iter()
            .map(|&b| {
                let s = sample_block(field, fine, b);
                progress.advance(1);
                s
            })
            .collect();
        stats.evaluated_points += sampled.len() * n1 * n1 * n1;
        let promote = contradicted_blocks(&sampled, fine, inside, surface);
        blocks.extend(sampled);
        stats.promoted_blocks += promote.len();
        progress.grow(promote.len() as u64);
        todo = promote;
    }
    blocks.sort_unstable_by_key(|b| (b.corner[2], b.corner[1], b.corner[0]));
    blocks
}

/// Blocks (moved to the surface set here) whose class disagrees with a sample of `sampled` on a
/// face, edge or corner they share.
fn contradicted_blocks(
    sampled: &[FieldBlock],
    fine: &FineGrid,
    inside: &mut BitSet,
    surface: &mut BitSet,
) -> Vec<usize> {
    let (block, n1) = (fine.block, fine.block + 1);
    let mut promote = Vec::new();
    for blk in sampled {
        let bc = blk.corner.map(|x| x / block);
        for k in 0..n1 {
            for j in 0..n1 {
                for i in 0..n1 {
                    let l = [i, j, k];
                    if l.iter().all(|&x| x > 0 && x < block) {
                        continue;
                    }
                    let positive = blk.values[i + n1 * (j + n1 * k)] > 0.0;
                    for_each_block_sharing(l, bc, block, fine.nb, |nbk| {
                        if !surface.get(nbk) && inside.get(nbk) != positive {
                            surface.set(nbk);
                            inside.clear(nbk);
                            promote.push(nbk);
                        }
                    });
                }
            }
        }
    }
    promote
}

/// Calls `f` with every other block (index) containing the sample at local position `l` of the
/// block at block coordinates `bc`.
fn for_each_block_sharing(
    l: [usize; 3],
    bc: [usize; 3],
    block: usize,
    nb: [usize; 3],
    mut f: impl FnMut(usize),
) {
    let options = |a: usize| -> [Option<isize>; 2] {
        if l[a] == 0 {
            [Some(0), Some(-1)]
        } else if l[a] == block {
            [Some(0), Some(1)]
        } else {
            [Some(0), None]
        }
    };
    for dz in options(2).into_iter().flatten() {
        for dy in options(1).into_iter().flatten() {
            for dx in options(0).into_iter().flatten() {
                if (dx, dy, dz) == (0, 0, 0) {
                    continue;
                }
                let c = [
                    bc[0] as isize + dx,
                    bc[1] as isize + dy,
                    bc[2] as isize + dz,
                ];
                if (0..3).all(|a| c[a] >= 0 && (c[a] as usize) < nb[a]) {
                    f(c[0] as usize + nb[0] * (c[1] as usize + nb[1] * c[2] as usize));
                }
            }
        }
    }
}

/// A fixed-size bitset (one bit per block).
struct BitSet(Vec<u64>);

impl BitSet {
    fn new(n: usize) -> Self {
        Self(vec![0; n.div_ceil(64)])
    }
    fn get(&self, i: usize) -> bool {
        self.0[i / 64] >> (i % 64) & 1 == 1
    }
    fn set(&mut self, i: usize) {
        self.0[i / 64] |= 1 << (i % 64);
    }
    fn clear(&mut self, i: usize) {
        self.0[i / 64] &= !(1 << (i % 64));
    }
    fn count(&self) -> usize {
        self.0.iter().map(|w| w.count_ones() as usize).sum()
    }
    fn iter(&self) -> impl Iterator<Item = usize> + '_ {
        self.0.iter().enumerate().flat_map(|(w, &bits)| {
            (0..64)
                .filter(move |b| bits >> b & 1 == 1)
                .map(move |b| w * 64 + b)
        })
    }
}
