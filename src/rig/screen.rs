//! The monitor: a plane of `width_px` × `height_px` pixels of `pitch_mm`, posed in the camera frame.
//!
//! Monitor frame: origin at the centre of pixel (0, 0), x along pixel columns, y along pixel
//! rows (mm), z = x × y. A point of the monitor frame maps to the camera frame as `R·p + t`, so
//! pixel (u, v) sits at `t + u·pitch·R[:,0] + v·pitch·R[:,1]` (docs/architecture.md §2).

use nalgebra::{Isometry3, Point2, Point3, Vector3};

/// A monitor and its pose.
#[derive(Clone, Debug, PartialEq)]
pub struct Screen {
    pub width_px: u32,
    pub height_px: u32,
    pub pitch_mm: f64,
    /// Monitor frame → camera frame.
    pub pose: Isometry3<f64>,
}

impl Screen {
    /// Position (camera frame, mm) of monitor pixel coordinates (u, v).
    pub fn point(&self, u: f64, v: f64) -> Point3<f64> {
        self.pose * Point3::new(u * self.pitch_mm, v * self.pitch_mm, 0.0)
    }

    /// The screen as seen in another frame: `to_frame` maps camera coordinates to that frame.
    pub fn transformed(&self, to_frame: &Isometry3<f64>) -> Self {
        Self {
            pose: to_frame * self.pose,
            ..self.clone()
        }
    }

    /// Where the ray `origin + t·dir` (t > 0, same frame as the pose) meets the monitor plane:
    /// the point (mm) and its monitor pixel coordinates; `None` if it runs parallel, points away
    /// or lands outside the pixel area.
    pub fn intersect(
        &self,
        origin: &Point3<f64>,
        dir: &Vector3<f64>,
    ) -> Option<(Point3<f64>, Point2<f64>)> {
        let inv = self.pose.inverse();
        let (o, d) = (inv * origin, inv * dir);
        if d.z.abs() < 1e-300 {
            return None;
        }
        let t = -o.z / d.z;
        if t.is_nan() || t <= 0.0 {
            return None;
        }
        let q = o + d * t;
        let px = Point2::new(q.x / self.pitch_mm, q.y / self.pitch_mm);
        let inside = (-0.5..self.width_px as f64 - 0.5).contains(&px.x)
            && (-0.5..self.height_px as f64 - 0.5).contains(&px.y);
        inside.then(|| (self.pose * Point3::new(q.x, q.y, 0.0), px))
    }
}
