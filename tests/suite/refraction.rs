//! The refraction tracer against closed forms: Snell's law, Fresnel at normal incidence, total
//! internal reflection at the critical angle, a ball lens, a slab's lateral shift, at object
//! scales from 1 mm to 10 m.

use glasscan::mesh::shapes::cuboid;
use glasscan::trace::path::{
    trace_paths, MeshSurface, NormalModel, PathEnd, PathSettings, Surface, SurfaceHit,
};
use glasscan::trace::refract::refract;
use glasscan::trace::{Ray, TraceError};
use nalgebra::{Point3, Vector3};

fn close(a: f64, b: f64, rel: f64) -> bool {
    (a - b).abs() <= rel * a.abs().max(b.abs()).max(1e-300)
}

#[test]
fn snell_fresnel_and_the_critical_angle() {
    let n = Vector3::new(0.0, 1.0, 0.0);
    for &(n1, n2) in &[
        (1.00029, 1.5),
        (1.0001, 2.42),
        (1.5, 1.00029),
        (1.0, 1.0001),
    ] {
        for k in 1..=89 {
            let th = (k as f64).to_radians();
            let d = Vector3::new(th.sin(), -th.cos(), 0.0);
            let sin_t = n1 / n2 * th.sin();
            match refract(&d, &n, n1, n2) {
                Some(r) => {
                    assert!(sin_t <= 1.0);
                    assert!(close(r.dir.norm(), 1.0, 1e-14));
                    // n1 sin θi = n2 sin θt, same plane, transmitted side.
                    assert!(
                        close(n1 * th.sin(), n2 * r.dir.x, 1e-13),
                        "{n1}->{n2} at {k}°"
                    );
                    assert!(r.dir.y < 0.0 && r.dir.z == 0.0);
                    assert!(close(r.cos_t, (1.0 - sin_t * sin_t).sqrt(), 1e-12));
                    assert!(r.transmittance > 0.0 && r.transmittance <= 1.0);
                }
                None => assert!(
                    sin_t > 1.0,
                    "TIR below the critical angle: {n1}->{n2} at {k}°"
                ),
            }
        }
        // Normal incidence: undeviated, T = 1 − ((n1 − n2)/(n1 + n2))².
        let r = refract(&-n, &n, n1, n2).unwrap();
        assert!((r.dir + n).norm() < 1e-15);
        assert!(close(
            r.transmittance,
            1.0 - ((n1 - n2) / (n1 + n2)).powi(2),
            1e-14
        ));
    }
    // Exactly past the critical angle, and just before it.
    for &(n1, n2) in &[(1.5f64, 1.00029f64), (2.42, 1.0001), (1.0001, 1.0)] {
        let crit = (n2 / n1).asin();
        for (th, tir) in [(crit * (1.0 - 1e-9), false), (crit * (1.0 + 1e-9), true)] {
            let d = Vector3::new(th.sin(), -th.cos(), 0.0);
            assert_eq!(
                refract(&d, &n, n1, n2).is_none(),
                tir,
                "{n1}->{n2} at critical × {}",
                th / crit
            );
        }
    }
}

/// An exact sphere (centre c, radius r) as a surface, for closed-form checks of the path logic.
struct Sphere {
    c: Point3<f64>,
    r: f64,
}

impl Surface for Sphere {
    fn intersect_serial(
        &self,
        rays: &[Ray],
        out: &mut [Option<SurfaceHit>],
        _coherent: bool,
    ) -> Result<(), TraceError> {
        for (ray, o) in rays.iter().zip(out.iter_mut()) {
            let oc = ray.origin - self.c;
            let b = oc.dot(&ray.dir);
            let disc = b * b - (oc.norm_squared() - self.r * self.r);
            *o = None;
            if disc < 0.0 {
                continue;
            }
            let s = disc.sqrt();
            for t in [-b - s, -b + s] {
                if t > ray.tnear {
                    let point = ray.origin + ray.dir * t;
                    let n = (point - self.c) / self.r;
                    *o = Some(SurfaceHit {
                        point,
                        geometric_normal: n,
                        shading_normal: n,
                        prim: 0,
                    });
                    break;
                }
            }
        }
        Ok(())
    }
    fn offset(&self) -> f64 {
        1e-9 * self.r
    }
}

#[test]
fn ball_lens_matches_the_analytic_exit_ray_at_every_scale() {
    let ior = 1.5;
    let settings = PathSettings::new(ior, 2);
    for scale in [1.0, 50.0, 10_000.0] {
        let sphere = Sphere {
            c: Point3::new(0.0, 0.0, 0.0),
            r: 0.5 * scale,
        };
        let r = sphere.r;
        // Rays along +x at heights h.
        let heights = [0.0, 0.1, 0.5, 0.9, 0.99];
        let rays: Vec<Ray> = heights
            .iter()
            .map(|f| {
                Ray::new(
                    Point3::new(-3.0 * r, f * r, 0.0),
                    Vector3::new(1.0, 0.0, 0.0),
                )
            })
            .collect();
        let paths = trace_paths(&sphere, &rays, &settings).unwrap();
        for (f, p) in heights.iter().zip(&paths) {
            assert_eq!((p.end, p.refractions), (PathEnd::Left, 2), "h = {f}");
            let th_i = f64::asin(*f);
            let th_t = (settings.ior_air / ior * th_i.sin()).asin();
            let phi = 2.0 * th_t - th_i; // polar angle of the exit point
            let exit = Point3::new(r * phi.cos(), r * phi.sin(), 0.0);
            let dev = 2.0 * (th_i - th_t);
            let dir = Vector3::new(dev.cos(), -dev.sin(), 0.0);
            // The path's origin is the exit point moved along the exit ray until it is the
            // offset away from the tangent plane.
            let n = (exit - sphere.c) / r;
            let back = p.origin - p.dir * (sphere.offset() / p.dir.dot(&n).abs().max(1e-3));
            assert!(
                (back - exit).norm() <= 1e-9 * r,
                "scale {scale}, h {f}: exit {back:?} vs {exit:?}"
            );
            assert!(
                (p.dir - dir).norm() <= 1e-9,
                "scale {scale}, h {f}: dir {:?} vs {dir:?}",
                p.dir
            );
        }
        // The central ray is undeviated.
        assert!((paths[0].dir - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-15);
    }
}

#[test]
fn slab_gives_the_textbook_lateral_shift_and_boxes_reflect_totally() {
    let ior = 1.5;
    let settings = PathSettings::new(ior, 2);
    for scale in [1.0, 100.0, 10_000.0] {
        // A slab of thickness t (y), wide in x and z.
        let t = scale;
        let slab = cuboid(Vector3::new(40.0 * scale, t, 40.0 * scale), 1);
        let surface = MeshSurface::new(&slab, NormalModel::Face).unwrap();
        for deg in [0.0f64, 20.0, 45.0, 70.0] {
            let th = deg.to_radians();
            let d = Vector3::new(th.sin(), -th.cos(), 0.0);
            // Aim at (x0, t/2, z0), off the faces' diagonals.
            let target = Point3::new(-3.1 * scale, 0.5 * t, 1.7 * scale);
            let ray = Ray::new(target - d * (2.0 * scale), d);
            let p = trace_paths(&surface, &[ray], &settings).unwrap()[0];
            assert_eq!(
                (p.end, p.refractions),
                (PathEnd::Left, 2),
                "scale {scale}, {deg}°"
            );
            assert!(
                (p.dir - d).norm() < 1e-12,
                "exit ray not parallel: {:?}",
                p.dir
            );
            let th_t = (settings.ior_air / ior * th.sin()).asin();
            let shift = t * (th - th_t).sin() / th_t.cos();
            // Distance between the exit line and the incident line.
            let measured = (p.origin - target).cross(&d).norm();
            assert!(
                close(measured, shift, 1e-9) || shift < 1e-12 && measured < 1e-9 * t,
                "scale {scale}, {deg}°: {measured} vs {shift}"
            );
        }
        // A box: in through the top at 60°, the inner ray meets the side face beyond the critical
        // angle and is totally reflected.
        let cube = cuboid(Vector3::new(scale, scale, scale), 1);
        let surface = MeshSurface::new(&cube, NormalModel::Face).unwrap();
        let th = 60f64.to_radians();
        let d = Vector3::new(th.sin(), -th.cos(), 0.0);
        let target = Point3::new(0.3 * scale, 0.5 * scale, 0.11 * scale);
        let p = trace_paths(&surface, &[Ray::new(target - d * scale, d)], &settings).unwrap()[0];
        assert_eq!(
            (p.end, p.refractions),
            (PathEnd::TotalInternalReflection, 1),
            "scale {scale}"
        );
    }
}

#[test]
fn paths_report_misses_and_too_many_interfaces() {
    let sphere = Sphere {
        c: Point3::new(0.0, 0.0, 0.0),
        r: 1.0,
    };
    let miss = Ray::new(Point3::new(-3.0, 2.0, 0.0), Vector3::new(1.0, 0.0, 0.0));
    let through = Ray::new(Point3::new(-3.0, 0.3, 0.0), Vector3::new(1.0, 0.0, 0.0));
    let p = trace_paths(&sphere, &[miss, through], &PathSettings::new(1.5, 1)).unwrap();
    assert_eq!((p[0].end, p[0].refractions), (PathEnd::Left, 0));
    assert_eq!(
        (p[1].end, p[1].refractions),
        (PathEnd::TooManyInterfaces, 1)
    );
    let p = trace_paths(&sphere, &[through], &PathSettings::new(1.5, 2)).unwrap();
    assert!(p[0].transmittance > 0.9 && p[0].transmittance < 1.0);
}
