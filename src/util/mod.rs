//! Small helpers shared by every stage: atomic file and folder output, image input and output,
//! means and medians, the scattering of a user's seed.

pub mod atomic;
pub mod budget;
pub mod fixed;
pub mod folder;
pub mod image;
pub mod lock;
pub mod paths;
pub mod prefetch;
pub mod progress;

/// `v` as a user reads it in a message: plain for ordinary magnitudes, in exponent form beyond
/// (so that `1e300` is not echoed as 301 digits).
pub fn short_number(v: f64) -> String {
    if v == 0.0 || (1e-4..1e6).contains(&v.abs()) {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// A length `v` (mm) with `decimals` decimals, or as many more as keep two significant digits
/// (`mm(0.00045, 3)` = "0.00045": a small object's figures do not print as 0.000).
pub fn mm(v: f64, decimals: usize) -> String {
    let a = v.abs();
    let decimals = if a > 0.0 && a.is_finite() && a < 10f64.powi(1 - decimals as i32) {
        (1 - a.log10().floor() as i32) as usize
    } else {
        decimals
    };
    format!("{v:.decimals$}")
}

/// The mean of `xs`; NaN for an empty list.
pub fn mean(xs: &[f64]) -> f64 {
    xs.iter().sum::<f64>() / xs.len() as f64
}

/// The median of `v` (the upper one for an even count); NaN for an empty list.
pub fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The weighted median of `values` (value, weight ≥ 0), interpolated: each value stands at the
/// middle of its weight on the cumulative scale, and the median is read between the two values
/// that straddle half the total. `None` without weight.
pub fn interpolated_median(mut values: Vec<(f64, f64)>) -> Option<f64> {
    let total: f64 = values.iter().map(|v| v.1).sum();
    if !(total > 0.0 && total.is_finite()) {
        return None;
    }
    values.sort_by(|a, b| a.0.total_cmp(&b.0));
    let half = 0.5 * total;
    let (mut below, mut before) = (0.0, None::<(f64, f64)>);
    for &(x, w) in &values {
        let at = below + 0.5 * w;
        below += w;
        if at >= half {
            return Some(match before {
                Some((bx, b_at)) if at > b_at => bx + (x - bx) * (half - b_at) / (at - b_at),
                _ => x,
            });
        }
        before = Some((x, at));
    }
    values.last().map(|v| v.0)
}

/// The weighted median of `(value, weight)` pairs: the first value, in ascending order (ties in
/// the given order), at which the weights reach half their sum; `None` for no pairs.
pub fn weighted_median(mut pairs: Vec<(f64, f64)>) -> Option<f64> {
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let half = 0.5 * pairs.iter().map(|p| p.1).sum::<f64>();
    let mut seen = 0.0;
    pairs.into_iter().find_map(|(v, w)| {
        seen += w;
        (seen >= half).then_some(v)
    })
}

/// A user's `--seed` scattered over the 64-bit integers before small stream numbers (a view, a
/// stage, an iteration) are mixed into it: multiplied by an odd constant, a bijection that keeps
/// 0 at 0, so seed 0 draws what it always drew. Mixed in bare, seeds s and s + 1 would share
/// their streams shifted by one (view k + 1 of one, view k of the other).
pub fn scatter_seed(seed: u64) -> u64 {
    seed.wrapping_mul(0x9e37_79b9_7f4a_7c15)
}

/// A key's place in [0, 1), scattered by a multiplicative hash: a deterministic draw that keeps
/// a share of items (those below the share) without a random stream.
pub fn hash_share(key: u64) -> f64 {
    (key.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 11) as f64 / (1u64 << 53) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lengths_keep_two_significant_digits() {
        assert_eq!(mm(0.025, 3), "0.025");
        assert_eq!(mm(0.00045146, 3), "0.00045");
        assert_eq!(mm(0.0039, 2), "0.0039");
        assert_eq!(mm(1.25, 2), "1.25");
        assert_eq!(mm(0.0, 3), "0.000");
        assert_eq!(mm(-0.0042, 3), "-0.0042");
    }

    #[test]
    fn the_interpolated_median_reads_between_the_middle_values() {
        let m = |v: &[(f64, f64)]| interpolated_median(v.to_vec());
        assert_eq!(m(&[(3.0, 1.0)]), Some(3.0));
        // Four equal weights: halfway between the second and third values, in any order.
        assert_eq!(
            m(&[(4.0, 1.0), (1.0, 1.0), (3.0, 1.0), (2.0, 1.0)]),
            Some(2.5)
        );
        // A heavy value holds the median.
        assert_eq!(m(&[(0.0, 1.0), (10.0, 5.0), (20.0, 1.0)]), Some(10.0));
        assert_eq!(m(&[(1.0, 0.0)]), None);
        assert_eq!(m(&[]), None);
    }

    #[test]
    fn the_weighted_median_is_where_the_weights_reach_half() {
        let pairs = |w: [f64; 3]| vec![(1.0, w[0]), (3.0, w[1]), (2.0, w[2])];
        assert_eq!(weighted_median(pairs([1.0, 1.0, 1.0])), Some(2.0));
        assert_eq!(weighted_median(pairs([1.0, 5.0, 1.0])), Some(3.0));
        assert_eq!(weighted_median(pairs([5.0, 1.0, 1.0])), Some(1.0));
        assert_eq!(weighted_median(Vec::new()), None);
    }
}
