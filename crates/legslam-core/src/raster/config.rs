//! The rasterizer's numerical constants, in one place (the values gsplat and 3DGS use, but
//! for the alpha cut-off and the features' transmittance cut-off).

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
    /// The same for the features' own, coarser layer (`RenderOptions::feature_scale` > 1).
    /// What the default 1/100 leaves out weighs under 1% of a pixel's feature, which the
    /// cosine loss hardly sees, yet it was 36% of that layer's contributions on the mapper
    /// bench's map: the iteration 9% cheaper, maps and language as good (README, "The
    /// engine's speed"). Colour and depth keep 1e-4: a depth short of 1% is centimetres.
    pub feature_transmittance_min: Real,
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
            feature_transmittance_min: 0.01,
            near: 0.01,
            far: 1e4,
            dilation: 0.3,
            fov_margin: 0.3,
        }
    }
}

impl RasterConfig {
    /// The configuration the features' own layer composites with.
    pub(crate) fn for_features(&self) -> Self {
        RasterConfig {
            transmittance_min: self.feature_transmittance_min,
            ..*self
        }
    }

    /// Checks the values; the message names the first one out of range.
    pub fn validate(&self) -> Result<(), String> {
        let checks = [
            (
                "alpha_min",
                self.alpha_min > 0.0 && self.alpha_min < self.alpha_max,
            ),
            ("alpha_max", self.alpha_max < 1.0),
            (
                "transmittance_min",
                (0.0..1.0).contains(&self.transmittance_min),
            ),
            (
                "feature_transmittance_min",
                (0.0..1.0).contains(&self.feature_transmittance_min),
            ),
            ("near", self.near > 0.0),
            ("far", self.far > self.near),
            ("dilation", self.dilation >= 0.0),
            ("fov_margin", self.fov_margin >= 0.0),
        ];
        match checks.iter().find(|(_, ok)| !ok) {
            None => Ok(()),
            Some((name, _)) => Err(format!(
                "invalid rasterizer configuration: {name} out of range in {self:?}"
            )),
        }
    }
}

/// Side of the square screen tiles that Gaussians are binned into, in pixels.
pub const TILE: usize = 16;
