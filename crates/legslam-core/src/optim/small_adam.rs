//! Adam over a handful of parameters (a keyframe's pose or exposure), in f64.

/// Adam over a few parameters, in f64.
#[derive(Clone, Debug)]
pub struct SmallAdam<const N: usize> {
    m: [f64; N],
    v: [f64; N],
    steps: u64,
}

impl<const N: usize> Default for SmallAdam<N> {
    fn default() -> Self {
        SmallAdam {
            m: [0.0; N],
            v: [0.0; N],
            steps: 0,
        }
    }
}

impl<const N: usize> SmallAdam<N> {
    /// Steps taken so far.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// The step `-lr m_hat / (sqrt(v_hat) + eps)` for gradient `grad`.
    pub fn step(&mut self, grad: &[f64; N], lr: &[f64; N]) -> [f64; N] {
        const BETA1: f64 = 0.9;
        const BETA2: f64 = 0.999;
        const EPS: f64 = 1e-15;
        self.steps += 1;
        let t = self.steps as f64;
        let (b1, b2) = (1.0 - BETA1.powf(t), 1.0 - BETA2.powf(t));
        std::array::from_fn(|a| {
            self.m[a] = BETA1 * self.m[a] + (1.0 - BETA1) * grad[a];
            self.v[a] = BETA2 * self.v[a] + (1.0 - BETA2) * grad[a] * grad[a];
            -lr[a] * (self.m[a] / b1) / ((self.v[a] / b2).sqrt() + EPS)
        })
    }
}
