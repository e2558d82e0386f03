//! Small helpers shared by every stage: atomic file, folder and image output, a median, the
//! scattering of a user's seed.

pub mod atomic;
pub mod budget;
pub mod fixed;
pub mod folder;
pub mod image;
pub mod lock;
pub mod paths;
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

/// The median of `v` (the upper one for an even count); NaN for an empty list.
pub fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// A user's `--seed` scattered over the 64-bit integers before small stream numbers (a view, a
/// stage, an iteration) are mixed into it: multiplied by an odd constant, a bijection that keeps
/// 0 at 0, so seed 0 draws what it always drew. Mixed in bare, seeds s and s + 1 would share
/// their streams shifted by one (view k + 1 of one, view k of the other).
pub fn scatter_seed(seed: u64) -> u64 {
    seed.wrapping_mul(0x9e37_79b9_7f4a_7c15)
}
