//! Hand-written reverse-mode derivatives of the geometric steps of a refraction path (f64).
//!
//! Each forward function returns its value and whatever its adjoint needs; each `*_adjoint`
//! takes the adjoint of the output (∂L/∂output) and adds ∂L/∂input to the input adjoints.
//! Every one is checked against central finite differences in `tests/suite/gradients.rs`.

use nalgebra::{Point3, Vector3};

type V3 = Vector3<f64>;

/// Adjoint of `u = v / |v|`: returns ∂L/∂v given `u`, `|v|` and ∂L/∂u.
#[inline]
pub fn normalize_adjoint(u: &V3, norm: f64, gu: &V3) -> V3 {
    (gu - u * u.dot(gu)) / norm
}

/// Adjoint of `c = a × b`: adds to ∂L/∂a and ∂L/∂b given ∂L/∂c.
#[inline]
pub fn cross_adjoint(a: &V3, b: &V3, gc: &V3, ga: &mut V3, gb: &mut V3) {
    *ga += b.cross(gc);
    *gb += gc.cross(a);
}

/// Adjoint of the unnormalised triangle normal `N = (b − a) × (c − a)`: adds ∂L/∂(a, b, c).
#[inline]
pub fn face_cross_adjoint(tri: &[Point3<f64>; 3], gn: &V3, g: &mut [V3; 3]) {
    let (e1, e2) = (tri[1] - tri[0], tri[2] - tri[0]);
    let (mut g1, mut g2) = (V3::zeros(), V3::zeros());
    cross_adjoint(&e1, &e2, gn, &mut g1, &mut g2);
    g[1] += g1;
    g[2] += g2;
    g[0] -= g1 + g2;
}

/// Where the ray `o + t·d` meets the plane of a triangle.
#[derive(Clone, Copy, Debug)]
pub struct PlaneHit {
    pub t: f64,
    pub point: Point3<f64>,
    /// Unnormalised normal (b − a) × (c − a).
    pub n: V3,
    /// d · n (< 0: the ray enters through the triangle's front).
    pub den: f64,
}

/// The ray–plane hit; `None` when the ray runs parallel to the plane.
#[inline]
pub fn plane_hit(o: &Point3<f64>, d: &V3, tri: &[Point3<f64>; 3]) -> Option<PlaneHit> {
    plane_hit_on(o, d, &tri[0], &crate::mesh::triangle_cross(tri))
}

/// [`plane_hit`] on the plane through `a` with the unnormalised normal `n` of its triangle.
#[inline]
pub fn plane_hit_on(o: &Point3<f64>, d: &V3, a: &Point3<f64>, n: &V3) -> Option<PlaneHit> {
    let den = d.dot(n);
    if den == 0.0 || !den.is_finite() {
        return None;
    }
    let t = (a - o).dot(n) / den;
    Some(PlaneHit {
        t,
        point: o + d * t,
        n: *n,
        den,
    })
}

/// Adjoint of [`plane_hit`]: given ∂L/∂point and ∂L/∂n (from the normal's later use), adds
/// ∂L/∂o, ∂L/∂d and ∂L/∂(a, b, c).
#[allow(clippy::too_many_arguments)]
#[inline]
pub fn plane_hit_adjoint(
    h: &PlaneHit,
    d: &V3,
    tri: &[Point3<f64>; 3],
    gp: &V3,
    gn_extra: &V3,
    go: &mut V3,
    gd: &mut V3,
    gtri: &mut [V3; 3],
) {
    // p = o + t d;  t = ((a − o)·N) / (d·N).
    *go += gp;
    *gd += gp * h.t;
    let s = gp.dot(d) / h.den;
    gtri[0] += h.n * s;
    *go -= h.n * s;
    *gd -= h.n * (s * h.t);
    let gn = (tri[0] - h.point) * s + gn_extra;
    face_cross_adjoint(tri, &gn, gtri);
}

/// Barycentric coordinates (w1, w2) of `p` (in the triangle's plane) for vertices b and c;
/// w0 = 1 − w1 − w2.
#[inline]
pub fn barycentric(p: &Point3<f64>, tri: &[Point3<f64>; 3], n: &V3) -> (f64, f64) {
    let (e1, e2, ep) = (tri[1] - tri[0], tri[2] - tri[0], p - tri[0]);
    let b = n.dot(n);
    (ep.cross(&e2).dot(n) / b, e1.cross(&ep).dot(n) / b)
}

/// Adjoint of [`barycentric`] (n = (b − a) × (c − a) given): adds ∂L/∂p, ∂L/∂(a, b, c) and
/// ∂L/∂n given ∂L/∂w1, ∂L/∂w2.
#[allow(clippy::too_many_arguments)]
#[inline]
pub fn barycentric_adjoint(
    p: &Point3<f64>,
    tri: &[Point3<f64>; 3],
    n: &V3,
    (w1, w2): (f64, f64),
    (g1, g2): (f64, f64),
    gp: &mut V3,
    gtri: &mut [V3; 3],
    gn: &mut V3,
) {
    let (e1, e2, ep) = (tri[1] - tri[0], tri[2] - tri[0], p - tri[0]);
    let b = n.dot(n);
    let (a1, a2) = (g1 / b, g2 / b);
    let gb = -(g1 * w1 + g2 * w2) / b;
    let gep = e2.cross(n) * a1 + n.cross(&e1) * a2;
    let ge2 = n.cross(&ep) * a1;
    let ge1 = ep.cross(n) * a2;
    *gn += ep.cross(&e2) * a1 + e1.cross(&ep) * a2 + n * (2.0 * gb);
    *gp += gep;
    gtri[1] += ge1;
    gtri[2] += ge2;
    gtri[0] -= gep + ge1 + ge2;
}

/// Snell's law with the values its adjoint needs: `out = η d + (η cos_i − cos_t) n`, n unit and
/// facing the incident side, η = n_i / n_t.
#[derive(Clone, Copy, Debug)]
pub struct Snell {
    pub eta: f64,
    pub cos_i: f64,
    pub cos_t: f64,
    pub out: V3,
}

/// Why Snell's law gives no usable derivative.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SnellFailure {
    /// The normal faces away from the ray.
    Grazing,
    /// Total internal reflection.
    Total,
    /// So close to total internal reflection that cos θt ≈ 0 (derivative unbounded).
    Critical,
}

/// Smallest cos θt with a usable derivative (∝ 1/cos θt): 1e-6 of the critical angle still
/// passes (cos θt ≈ 1e-3 there).
pub const MIN_COS_T: f64 = 1e-7;

#[inline]
pub fn snell(d: &V3, n: &V3, eta: f64) -> Result<Snell, SnellFailure> {
    let cos_i = -d.dot(n);
    if cos_i.is_nan() || cos_i <= 0.0 {
        return Err(SnellFailure::Grazing);
    }
    let sin2_t = eta * eta * (1.0 - cos_i * cos_i);
    if sin2_t >= 1.0 {
        return Err(SnellFailure::Total);
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    if cos_t < MIN_COS_T {
        return Err(SnellFailure::Critical);
    }
    Ok(Snell {
        eta,
        cos_i,
        cos_t,
        out: d * eta + n * (eta * cos_i - cos_t),
    })
}

/// ∂L/∂η of [`snell`] given ∂L/∂out: ∂out/∂η = d + n (cos θi − ∂cos θt/∂η), with
/// ∂cos θt/∂η = −η sin²θi / cos θt.
#[inline]
pub fn snell_eta_adjoint(s: &Snell, d: &V3, n: &V3, gout: &V3) -> f64 {
    let dcos_t = -s.eta * (1.0 - s.cos_i * s.cos_i) / s.cos_t;
    gout.dot(&(d + n * (s.cos_i - dcos_t)))
}

/// Adjoint of [`snell`]: adds ∂L/∂d and ∂L/∂n given ∂L/∂out.
#[inline]
pub fn snell_adjoint(s: &Snell, d: &V3, n: &V3, gout: &V3, gd: &mut V3, gn: &mut V3) {
    let k = s.eta * s.cos_i - s.cos_t;
    *gd += gout * s.eta;
    *gn += gout * k;
    let gk = gout.dot(n);
    // d cos_t / d cos_i = η² cos_i / cos_t.
    let gci = gk * (s.eta - s.eta * s.eta * s.cos_i / s.cos_t);
    // cos_i = −d·n.
    *gd -= n * gci;
    *gn -= d * gci;
}
