//! Adding chunks' (vertex, vector) gradient entries into per-vertex sums on every thread, in the
//! same order for every vertex whatever the thread count.
//!
//! The vertex range is split into one part per thread, each part adding, in chunk order, the
//! entries that fall in it. With more than two parts, each chunk's entries are first sorted by
//! part, stably and in parallel over the chunks, so that a part reads only its own: the entries
//! are read twice in all, however many parts. (A part that reads every entry and keeps its own
//! reads them once per part: on 16 threads the sum would take as long as on one. With two parts
//! that is cheaper than sorting: `bench gradient`, 2 cores, 1–3 % faster.)

use nalgebra::Vector3;
use rayon::prelude::*;

type V3 = Vector3<f64>;

/// One chunk's entries sorted by part: `entries[starts[p]..starts[p + 1]]` are part p's, in
/// the chunk's order.
#[derive(Clone, Debug, Default)]
pub struct PartSorted {
    entries: Vec<(u32, V3)>,
    starts: Vec<usize>,
}

/// Adds the entries `entries(c)` of every chunk `c` of `chunks` into `target` (entries of
/// vertices outside it are ignored), in chunk order, then entry order, for every vertex; the
/// vertex range split into `parts` parts. `sorted` holds one [`PartSorted`] per chunk from call
/// to call, so that the sorting reuses memory already touched.
pub fn scatter<C: Sync>(
    target: &mut [V3],
    chunks: &[C],
    entries: impl Fn(&C) -> &[(u32, V3)] + Sync,
    parts: usize,
    sorted: &mut Vec<PartSorted>,
) {
    let parts = parts.max(1);
    let block = target.len().div_ceil(parts).max(1);
    if parts <= 2 {
        target
            .par_chunks_mut(block)
            .enumerate()
            .for_each(|(p, part)| {
                add_entries(part, p * block, chunks.iter().map(&entries));
            });
        return;
    }
    if sorted.len() < chunks.len() {
        sorted.resize_with(chunks.len(), PartSorted::default);
    }
    let sorted = &mut sorted[..chunks.len()];
    sorted
        .par_iter_mut()
        .zip(chunks)
        .for_each(|(s, c)| sort_by_part(entries(c), block, parts, s));
    let sorted = &*sorted;
    target
        .par_chunks_mut(block)
        .enumerate()
        .for_each(|(p, part)| {
            let own = sorted
                .iter()
                .map(|s| &s.entries[s.starts[p]..s.starts[p + 1]]);
            add_entries(part, p * block, own);
        });
}

/// Sorts `entries` by part (vertex / `block`, the last part taking any beyond), stably, into
/// `out`.
fn sort_by_part(entries: &[(u32, V3)], block: usize, parts: usize, out: &mut PartSorted) {
    let part_of = |v: u32| (v as usize / block).min(parts - 1);
    out.starts.clear();
    out.starts.resize(parts + 1, 0);
    for &(v, _) in entries {
        out.starts[part_of(v) + 1] += 1;
    }
    for p in 0..parts {
        out.starts[p + 1] += out.starts[p];
    }
    out.entries.clear();
    out.entries.resize(entries.len(), (0, V3::zeros()));
    let mut next = out.starts.clone();
    for &e in entries {
        let p = part_of(e.0);
        out.entries[next[p]] = e;
        next[p] += 1;
    }
}

/// Adds the entries of `lists`, in order, that fall in `part` (vertices from `lo`).
pub fn add_entries<'a>(part: &mut [V3], lo: usize, lists: impl Iterator<Item = &'a [(u32, V3)]>) {
    for list in lists {
        for &(v, x) in list {
            if let Some(t) = (v as usize).checked_sub(lo).and_then(|i| part.get_mut(i)) {
                *t += x;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Entries spread over 50 vertices (some beyond them), summed with 1 to 7 parts: the same
    /// bits every time, and the sums in order.
    #[test]
    fn sums_do_not_depend_on_the_parts() {
        let chunks: Vec<Vec<(u32, V3)>> = (0..5)
            .map(|c| {
                (0..40u32)
                    .map(|i| {
                        let v = (i * 7 + c * 13) % 53;
                        let x = 1.0 / (1.0 + f64::from(i) + 0.37 * f64::from(c));
                        (v, V3::new(x, -x * 1e-9, x * 1e9))
                    })
                    .collect()
            })
            .collect();
        let mut serial = vec![V3::zeros(); 50];
        for (v, x) in chunks.iter().flatten() {
            if let Some(t) = serial.get_mut(*v as usize) {
                *t += x;
            }
        }
        let mut sorted = Vec::new();
        for parts in 1..=7 {
            let mut target = vec![V3::zeros(); 50];
            scatter(&mut target, &chunks, |c| c, parts, &mut sorted);
            let bits = |g: &[V3]| -> Vec<u64> {
                g.iter()
                    .flat_map(|x| x.iter().map(|y| y.to_bits()))
                    .collect()
            };
            assert_eq!(bits(&target), bits(&serial), "{parts} parts");
        }
    }
}
