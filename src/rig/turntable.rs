//! The turntable: a rotation axis (point and direction in the camera frame, mm) and the angles at
//! which views were taken. It defines the world (object) frame and each view's world → camera
//! transform.
//!
//! World frame (docs/architecture.md §2): origin at the axis point, +y along the axis, +z towards the camera
//! (perpendicular to the axis), x = y × z. View k sees the object rotated by θk about +y:
//! `p_cam = M · R_y(θk) · p_world`, with M the world → camera transform at θ = 0.

use nalgebra::{
    Isometry3, Matrix3, Point3, Rotation3, Translation3, Unit, UnitQuaternion, Vector3,
};

/// A turntable axis and the view angles.
#[derive(Clone, Debug, PartialEq)]
pub struct Turntable {
    /// A point of the axis, camera frame, mm.
    pub axis_point: Point3<f64>,
    /// Unit direction of the axis (world +y), camera frame.
    pub axis_dir: Unit<Vector3<f64>>,
    /// View angles, degrees (positive: right-handed about +y).
    pub angles_deg: Vec<f64>,
}

impl Turntable {
    /// The world → camera transform at angle 0; `None` if the camera lies on the axis.
    pub fn base_pose(&self) -> Option<Isometry3<f64>> {
        let y = self.axis_dir.into_inner();
        let to_cam = Point3::origin() - self.axis_point;
        let z = (to_cam - y * y.dot(&to_cam)).try_normalize(1e-12)?;
        let x = y.cross(&z);
        let rot = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
        Some(Isometry3::from_parts(
            Translation3::from(self.axis_point.coords),
            UnitQuaternion::from_rotation_matrix(&rot),
        ))
    }

    /// The world → camera transform of each view.
    pub fn view_poses(&self) -> Option<Vec<Isometry3<f64>>> {
        let base = self.base_pose()?;
        Some(
            self.angles_deg
                .iter()
                .map(|a| base * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), a.to_radians()))
                .collect(),
        )
    }

    /// `n` views evenly spaced over 360°, starting at 0.
    pub fn even_angles(n: usize) -> Vec<f64> {
        (0..n).map(|k| 360.0 * k as f64 / n as f64).collect()
    }
}
