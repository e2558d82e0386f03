//! Pinhole camera with OpenCV's distortion model (k1 k2 p1 p2 k3).
//!
//! Camera frame: x right, y down, z forward (OpenCV), mm. Pixel coordinates: integer values are
//! pixel centres, (0, 0) the centre of the top-left pixel (OpenCV's convention).

use nalgebra::{Matrix2, Matrix2x3, Point2, Point3, Vector3};

/// Intrinsics of a camera: image size (pixels), focal lengths and principal point (pixels),
/// distortion coefficients [k1, k2, p1, p2, k3].
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub dist: [f64; 5],
}

impl Camera {
    /// OpenCV's forward distortion of normalised image coordinates (x, y) = (X/Z, Y/Z).
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.dist;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        (
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// Inverts [`Self::distort`] by Newton's method with a numerical Jacobian (converges to
    /// ~1e-15 in a few steps for realistic lenses); `None` if it does not converge.
    pub fn undistort(&self, xd: f64, yd: f64) -> Option<(f64, f64)> {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..50 {
            let (fx, fy) = self.distort(x, y);
            let (ex, ey) = (fx - xd, fy - yd);
            if ex.abs().max(ey.abs()) < 1e-15 {
                return Some((x, y));
            }
            let h = 1e-7;
            let (ax, ay) = self.distort(x + h, y);
            let (bx, by) = self.distort(x, y + h);
            let (j11, j21, j12, j22) = ((ax - fx) / h, (ay - fy) / h, (bx - fx) / h, (by - fy) / h);
            let det = j11 * j22 - j12 * j21;
            if det.abs() < 1e-12 {
                return None;
            }
            x -= (j22 * ex - j12 * ey) / det;
            y -= (j11 * ey - j21 * ex) / det;
        }
        let (fx, fy) = self.distort(x, y);
        ((fx - xd).abs().max((fy - yd).abs()) < 1e-10).then_some((x, y))
    }

    /// Projects a point in the camera frame (mm) to pixel coordinates; `None` behind the camera.
    pub fn project(&self, p: &Point3<f64>) -> Option<Point2<f64>> {
        if p.z <= 0.0 {
            return None;
        }
        let (xd, yd) = self.distort(p.x / p.z, p.y / p.z);
        Some(Point2::new(self.fx * xd + self.cx, self.fy * yd + self.cy))
    }

    /// [`Self::project`] and its Jacobian ∂(u, v)/∂p (pixels per mm, camera frame).
    pub fn project_jacobian(&self, p: &Point3<f64>) -> Option<(Point2<f64>, Matrix2x3<f64>)> {
        if p.z <= 0.0 {
            return None;
        }
        let (x, y) = (p.x / p.z, p.y / p.z);
        let [k1, k2, p1, p2, k3] = self.dist;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);
        let (xd, yd) = self.distort(x, y);
        // ∂(xd, yd)/∂(x, y) of OpenCV's model.
        let d = Matrix2::new(
            radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x,
            2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y,
            2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y,
            radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x,
        );
        let jn = Matrix2x3::new(1.0 / p.z, 0.0, -x / p.z, 0.0, 1.0 / p.z, -y / p.z);
        let j = Matrix2::new(self.fx, 0.0, 0.0, self.fy) * d * jn;
        Some((
            Point2::new(self.fx * xd + self.cx, self.fy * yd + self.cy),
            j,
        ))
    }

    /// Unit direction (camera frame) of the ray through pixel coordinates (u, v).
    pub fn pixel_ray(&self, u: f64, v: f64) -> Option<Vector3<f64>> {
        let (x, y) = self.undistort((u - self.cx) / self.fx, (v - self.cy) / self.fy)?;
        Some(Vector3::new(x, y, 1.0).normalize())
    }
}
