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

/// The fine voxel of a hull: given, or chosen from the object's size.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum VoxelSize {
    /// Chosen from the diagonal of the box the coarse pass leaves (see [`Self::for_diagonal`]).
    Auto,
    /// This edge, mm.
    Mm(f64),
}

impl VoxelSize {
    /// From the diagonal of the coarse pass's box (mm; a few coarse cells larger than the
    /// object's, so that the shared pig's is about 290 mm): under 50 mm a fiftieth of it, over
    /// 500 mm a five-hundredth (about as many voxels across as DRT's objects get, which the
    /// optimiser's steps are set for), 1 mm between; rounded down to two significant digits.
    pub fn for_diagonal(diag_mm: f64) -> f64 {
        round_down_to_digits((diag_mm / 50.0).min(1.0).max(diag_mm / 500.0), 2)
    }
}

/// Carves the fine field: returns the grid, the sampled surface blocks, and figures.
pub fn carve(
    field: &Field,
    camera_centre_mm: Point3<f64>,
    half_fov_tan: f64,
    voxel: VoxelSize,
    block: usize,
    progress: &dyn StepProgress,
) -> Result<(Grid, Vec<FieldBlock>, CarveStats)> {
    let mut stats = CarveStats::default();
    progress.phase("coarse carve", 0);
    let coarse = CoarseGrid::around_axis(camera_centre_mm, half_fov_tan);
    let (lo, hi, voxel_mm) = coarse_bounds(field, &coarse, voxel, &mut stats)?;
    stats.voxel_mm = voxel_mm;
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

/// Step 1's grid: 64³ cells over a cube around the axis point nearest the camera, as wide as the
/// field of view at that distance (mm, world frame).
struct CoarseGrid {
    lo: Point3<f64>,
    /// Cell edge, mm.
    cell: f64,
    /// The field of view's width at the axis, mm.
    view_width: f64,
}

impl CoarseGrid {
    const N: usize = 64;

    fn around_axis(camera_centre_mm: Point3<f64>, half_fov_tan: f64) -> Self {
        let axis_centre = Point3::new(0.0, camera_centre_mm.y, 0.0);
        let dist = (camera_centre_mm - axis_centre).norm();
        let half = 1.2 * dist * half_fov_tan;
        Self {
            lo: axis_centre - Vector3::repeat(half),
            cell: 2.0 * half / Self::N as f64,
            view_width: 2.0 * half / 1.2,
        }
    }

    fn corner(&self, c: [usize; 3]) -> Point3<f64> {
        self.lo + self.cell * Vector3::from(c.map(|x| x as f64))
    }

    /// The lowest and highest cell (per axis) whose centre is within reach of the silhouettes'
    /// intersection, for fine voxels of `voxel_mm`.
    fn alive_range(
        &self,
        field: &Field,
        voxel_mm: f64,
        stats: &mut CarveStats,
    ) -> Option<([usize; 3], [usize; 3])> {
        let n = Self::N;
        let reach = 0.9 * self.cell + 2.0 * voxel_mm;
        let alive: Vec<[usize; 3]> = (0..n * n * n)
            .into_par_iter()
            .filter_map(|idx| {
                let c = [idx % n, (idx / n) % n, idx / (n * n)];
                let p = self.corner(c) + Vector3::repeat(0.5 * self.cell);
                (field.value(&p, -reach) > -reach).then_some(c)
            })
            .collect();
        stats.evaluated_points += n * n * n;
        let first = *alive.first()?;
        let fold = |pick: fn(usize, usize) -> usize| {
            alive
                .iter()
                .fold(first, |m, c| std::array::from_fn(|a| pick(m[a], c[a])))
        };
        Some((fold(usize::min), fold(usize::max)))
    }
}

/// Step 1: the box (mm, world frame) of the coarse cells not far outside, with a voxel of margin,
/// and the fine voxel (mm).
fn coarse_bounds(
    field: &Field,
    coarse: &CoarseGrid,
    voxel: VoxelSize,
    stats: &mut CarveStats,
) -> Result<(Point3<f64>, Point3<f64>, f64)> {
    let provisional = match voxel {
        VoxelSize::Mm(v) => v,
        VoxelSize::Auto => (coarse.cell / 4.0).min(1.0),
    };
    let mut range = bounded_range(field, coarse, provisional, stats)?;
    let voxel_mm = match voxel {
        VoxelSize::Mm(v) => v,
        VoxelSize::Auto => {
            let cells = Vector3::from(std::array::from_fn(|a| {
                (range.1[a] + 1 - range.0[a]) as f64
            }));
            let chosen = VoxelSize::for_diagonal(coarse.cell * cells.norm());
            if chosen > provisional {
                range = bounded_range(field, coarse, chosen, stats)?;
            }
            chosen
        }
    };
    let margin = Vector3::repeat(voxel_mm);
    Ok((
        coarse.corner(range.0) - margin,
        coarse.corner(range.1.map(|x| x + 1)) + margin,
        voxel_mm,
    ))
}

/// The alive cells' range for `voxel_mm`; errors when there is none or when it reaches the grid's
/// border (the object is not bounded, or the voxel is too coarse for it).
fn bounded_range(
    field: &Field,
    coarse: &CoarseGrid,
    voxel_mm: f64,
    stats: &mut CarveStats,
) -> Result<([usize; 3], [usize; 3])> {
    let Some((cmin, cmax)) = coarse.alive_range(field, voxel_mm, stats) else {
        bail!("the silhouettes leave nothing: no point of space projects inside every mask (are the masks and the calibration of the same scan?)");
    };
    let last = CoarseGrid::N - 1;
    if (0..3).any(|a| cmin[a] == 0 || cmax[a] == last) {
        if 2.0 * voxel_mm > coarse.cell {
            // The voxel margin, not the masks, reached the border: a small object.
            bail!(
                "the hull's voxels ({} mm) are too coarse for this scan: the camera sees only \
                 {:.3} mm across at the turntable axis; use --voxel-mm {} or finer, or auto \
                 (reconstruct: --hull-voxel-mm)",
                crate::util::short_number(voxel_mm),
                coarse.view_width,
                crate::util::short_number(round_down_to_digits(coarse.cell / 4.0, 1))
            );
        }
        bail!("the hull is not bounded inside the camera's field of view: too few views from different directions, or masks that reach the image border");
    }
    Ok((cmin, cmax))
}

/// `x` (> 0, finite) rounded down to `digits` significant digits, as the double nearest the
/// decimal (0.0137, 1 → 0.01; 0.005125, 2 → 0.0051).
fn round_down_to_digits(x: f64, digits: i32) -> f64 {
    let exponent = x.log10().floor() as i32 - (digits - 1);
    let mantissa = (x / 10f64.powi(exponent)).floor();
    format!("{mantissa}e{exponent}").parse().unwrap_or(x)
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_automatic_voxel_follows_small_and_huge_objects_only() {
        assert_eq!(VoxelSize::for_diagonal(50.0), 1.0);
        assert_eq!(VoxelSize::for_diagonal(234.0), 1.0);
        assert_eq!(VoxelSize::for_diagonal(500.0), 1.0);
        assert_eq!(VoxelSize::for_diagonal(11.6), 0.23);
        assert_eq!(VoxelSize::for_diagonal(0.2563), 0.0051);
        assert_eq!(VoxelSize::for_diagonal(9_600.0), 19.0);
        // Never more voxels across than the grid allows, however large.
        for diag in [3e3, 1e4, 1e5, 1e6] {
            assert!(diag / VoxelSize::for_diagonal(diag) < MAX_VOXELS_PER_AXIS as f64);
        }
    }

    #[test]
    fn sizes_are_rounded_down_to_their_digits() {
        assert_eq!(round_down_to_digits(0.0137, 1), 0.01);
        assert_eq!(round_down_to_digits(0.0999, 2), 0.099);
        assert_eq!(round_down_to_digits(123.4, 2), 120.0);
        assert_eq!(round_down_to_digits(1.0, 2), 1.0);
    }
}
