//! Small helpers shared by every stage: atomic file, folder and image output, a median.

pub mod atomic;
pub mod budget;
pub mod fixed;
pub mod folder;
pub mod image;
pub mod paths;

/// The median of `v` (the upper one for an even count); NaN for an empty list.
pub fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}
