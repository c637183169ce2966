//! Differentiable Gaussian rasterizer.
