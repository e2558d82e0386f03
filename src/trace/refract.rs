//! Snell's law and Fresnel transmission at one interface, in f64.
//!
//! Directions are unit vectors in any frame; the normal passed in faces the incident side
//! (`d · n < 0`). The transmitted direction is `η d + (η cos θi − cos θt) n` with η = n_i / n_t,
//! cos θi = −d·n and cos θt = √(1 − η² (1 − cos² θi)): the cosine of the *transmitted* angle
//! (DRT's released code used √(1 − sin² θi) here, a bug worth 0.25 mm of accuracy; docs/architecture.md §4).

use nalgebra::Vector3;

/// Refractive index of air at room conditions.
pub const IOR_AIR: f64 = 1.00029;

/// A refracted ray leaving an interface.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Refraction {
    /// Unit direction of the transmitted ray.
    pub dir: Vector3<f64>,
    /// Cosine of the angle of incidence (0..1].
    pub cos_i: f64,
    /// Cosine of the angle of transmission (0..1].
    pub cos_t: f64,
    /// Fresnel transmittance for unpolarised light (0..1).
    pub transmittance: f64,
}

/// Refracts unit direction `d` at a surface with unit normal `n` facing the incident side,
/// going from index `n_i` to `n_t`. `None` on total internal reflection (or when `d` does not
/// reach the surface from `n`'s side).
pub fn refract(d: &Vector3<f64>, n: &Vector3<f64>, n_i: f64, n_t: f64) -> Option<Refraction> {
    let cos_i = -d.dot(n);
    if cos_i.is_nan() || cos_i <= 0.0 {
        return None;
    }
    let cos_i = cos_i.min(1.0);
    let eta = n_i / n_t;
    let sin2_t = eta * eta * (1.0 - cos_i * cos_i);
    if sin2_t > 1.0 {
        return None;
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    let dir = d * eta + n * (eta * cos_i - cos_t);
    let rs = ((n_i * cos_i - n_t * cos_t) / (n_i * cos_i + n_t * cos_t)).powi(2);
    let rp = ((n_i * cos_t - n_t * cos_i) / (n_i * cos_t + n_t * cos_i)).powi(2);
    Some(Refraction {
        dir,
        cos_i,
        cos_t,
        transmittance: 1.0 - 0.5 * (rs + rp),
    })
}
