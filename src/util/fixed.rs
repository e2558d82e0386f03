//! Monitor coordinates as 16-bit fixed point, as the ground-truth and decoded PNGs store them:
//! a coordinate x (monitor pixels, ≥ −1) is stored as round((x + 1)·s); 65535 means "none".

/// The "no value" marker.
pub const NONE: u16 = u16::MAX;

/// The largest image or monitor side glasscan accepts, pixels (a 16K monitor is 15,360 wide;
/// up to here the fixed-point monitor coordinates keep at least 3 steps per pixel).
pub const MAX_SIDE_PX: u32 = 16_384;

/// A fixed-point scale s.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FixedPoint {
    pub scale: f64,
}

impl FixedPoint {
    /// As fine as 16 bits allow for a monitor of this size (34 for 1920×1080).
    pub fn for_screen(width: u32, height: u32) -> Self {
        Self {
            scale: (65534.0 / (width.max(height) as f64 + 1.0)).floor(),
        }
    }

    /// Encodes `x` (monitor pixels); non-finite values become [`NONE`].
    pub fn encode(&self, x: f64) -> u16 {
        if x.is_finite() {
            ((x + 1.0) * self.scale).round().clamp(0.0, 65534.0) as u16
        } else {
            NONE
        }
    }

    /// Decodes a stored value; `None` for [`NONE`].
    pub fn decode(&self, v: u16) -> Option<f64> {
        (v != NONE).then(|| v as f64 / self.scale - 1.0)
    }
}
