//! Keyframe exposure: an affine colour transform per channel between what the map renders and
//! what the camera recorded, trained beside the map so that it learns one radiance from frames
//! the camera exposed differently (7-Scenes' Kinect adjusts exposure as it moves).

use crate::optim::SmallAdam;
use crate::Real;

/// A keyframe's exposure: the camera saw `exp(log_gain) * colour + bias`, per channel, of the
/// colour the map renders.
#[derive(Clone, Debug, Default)]
pub struct Exposure {
    pub log_gain: [Real; 3],
    pub bias: [Real; 3],
    adam: SmallAdam<6>,
}

impl Exposure {
    pub fn is_identity(&self) -> bool {
        self.log_gain == [0.0; 3] && self.bias == [0.0; 3]
    }

    /// `out` = the exposed colour of `color` ([h, w, 3]).
    pub fn apply(&self, color: &[Real], out: &mut Vec<Real>) {
        let gain = self.log_gain.map(Real::exp);
        out.clear();
        out.extend(
            color
                .chunks_exact(3)
                .flat_map(|c| [0, 1, 2].map(|k| gain[k] * c[k] + self.bias[k])),
        );
    }

    /// Given `color` and d(loss)/d(exposed colour) in `grad`, turns `grad` into
    /// d(loss)/d(colour) and returns d(loss)/d(log_gain, bias).
    pub fn backward(&self, color: &[Real], grad: &mut [Real]) -> [f64; 6] {
        let gain = self.log_gain.map(Real::exp);
        let mut out = [0.0f64; 6];
        for (c, g) in color.chunks_exact(3).zip(grad.chunks_exact_mut(3)) {
            for k in 0..3 {
                let g_exposed = f64::from(g[k]);
                out[k] += g_exposed * f64::from(gain[k] * c[k]);
                out[3 + k] += g_exposed;
                g[k] *= gain[k];
            }
        }
        out
    }

    /// One Adam step with learning rate `lr` on every parameter.
    pub fn step(&mut self, grad: &[f64; 6], lr: f64) {
        let delta = self.adam.step(grad, &[lr; 6]);
        for k in 0..3 {
            self.log_gain[k] += delta[k] as Real;
            self.bias[k] += delta[3 + k] as Real;
        }
    }

    pub fn steps(&self) -> u64 {
        self.adam.steps()
    }
}
