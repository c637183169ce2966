//! The rasterizer's numerical constants, in one place (the values gsplat and 3DGS use, but
//! for the alpha cut-off).

use crate::Real;

/// Cut-offs of projection and compositing. `Default` is what users get; tests may loosen the
/// cut-offs to make the rendered image a smooth function of the parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RasterConfig {
    /// A Gaussian contributes to a pixel only where its alpha reaches this value. 3DGS and
    /// gsplat use 1/255; 1/100 leaves out the faintest rim of every Gaussian, which made
    /// SLAM runs 10-19% faster with maps as good (README, "The engine's speed").
    pub alpha_min: Real,
    /// Alpha is capped here so that one Gaussian never makes a pixel fully opaque.
    pub alpha_max: Real,
    /// A pixel stops compositing once its transmittance would fall below this value.
    pub transmittance_min: Real,
    /// Gaussians whose centre is nearer than this (metres, camera z) are culled.
    pub near: Real,
    /// Gaussians whose centre is farther than this are culled.
    pub far: Real,
    /// Added to the diagonal of every 2D covariance (pixels^2): the EWA low-pass filter.
    pub dilation: Real,
    /// The projection Jacobian is evaluated with x/z, y/z clamped to the field of view widened
    /// by this fraction, which keeps Gaussians near the camera and off-screen from exploding.
    pub fov_margin: Real,
}

impl Default for RasterConfig {
    fn default() -> Self {
        RasterConfig {
            alpha_min: 0.01,
            alpha_max: 0.99,
            transmittance_min: 1e-4,
            near: 0.01,
            far: 1e4,
            dilation: 0.3,
            fov_margin: 0.3,
        }
    }
}

impl RasterConfig {
    pub fn validate(&self) -> Result<(), String> {
        let ok = self.alpha_min > 0.0
            && self.alpha_min < self.alpha_max
            && self.alpha_max < 1.0
            && self.transmittance_min >= 0.0
            && self.transmittance_min < 1.0
            && self.near > 0.0
            && self.far > self.near
            && self.dilation >= 0.0
            && self.fov_margin >= 0.0;
        if ok {
            Ok(())
        } else {
            Err(format!("invalid rasterizer configuration: {self:?}"))
        }
    }
}

/// Side of the square screen tiles that Gaussians are binned into, in pixels.
pub const TILE: usize = 16;
