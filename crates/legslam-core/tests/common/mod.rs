//! Shared by the rasterizer tests: random scenes and a plain per-pixel reference renderer.
#![allow(dead_code)]

use legslam_core::camera::{se3, Intrinsics, Pose};
use legslam_core::raster::{
    backward, render, sh, vector_paths, Camera, Gaussians, Gradients, ImageGrads, RasterConfig,
    RenderOptions, Rendered, Simd,
};
use legslam_core::Real;
use nalgebra::{Matrix2, Matrix3, Quaternion, Rotation3, UnitQuaternion, Vector3};

pub use legslam_core::rng::Rng;

#[derive(Clone, Debug)]
pub struct Scene {
    pub means: Vec<Real>,
    pub log_scales: Vec<Real>,
    pub quats: Vec<Real>,
    pub opacity_logits: Vec<Real>,
    pub sh: Vec<Real>,
    pub sh_coeffs: usize,
    pub features: Vec<Real>,
    pub k: usize,
    pub intr: Intrinsics,
    /// World-to-camera.
    pub w2c: Pose,
}

impl Scene {
    pub fn gaussians(&self) -> Gaussians<'_> {
        Gaussians {
            means: &self.means,
            log_scales: &self.log_scales,
            quats: &self.quats,
            opacity_logits: &self.opacity_logits,
            sh: &self.sh,
            sh_coeffs: self.sh_coeffs,
            features: &self.features,
            num_features: self.k,
        }
    }
    pub fn camera(&self) -> Camera {
        Camera::new(self.intr, &self.w2c).unwrap()
    }
    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    /// Adds one Gaussian at camera-space position `pc` (metres).
    #[allow(clippy::too_many_arguments)]
    pub fn push(&mut self, rng: &mut Rng, pc: [f64; 3], log_scale: [f64; 3], logit: f64) {
        let (r, t) = self.rt();
        let pw = r.transpose() * (Vector3::from(pc) - t);
        self.means.extend(pw.iter().map(|v| *v as Real));
        self.log_scales.extend(log_scale.iter().map(|v| *v as Real));
        let q = UnitQuaternion::from_quaternion(Quaternion::new(
            rng.normal(),
            rng.normal(),
            rng.normal(),
            rng.normal(),
        ));
        self.quats
            .extend([q.w, q.i, q.j, q.k].iter().map(|v| *v as Real));
        self.opacity_logits.push(logit as Real);
        for _ in 0..self.sh_coeffs * 3 {
            self.sh.push((0.4 * rng.normal()) as Real);
        }
        for _ in 0..self.k {
            self.features.push(rng.normal() as Real);
        }
    }

    fn rt(&self) -> (Matrix3<f64>, Vector3<f64>) {
        (se3::rotation(&self.w2c), se3::translation(&self.w2c))
    }
}

/// An empty scene seen by a randomly posed small camera.
pub fn empty_scene(
    rng: &mut Rng,
    width: usize,
    height: usize,
    sh_degree: usize,
    k: usize,
) -> Scene {
    let rot = Rotation3::from_euler_angles(
        rng.uniform(-0.3, 0.3),
        rng.uniform(-0.3, 0.3),
        rng.uniform(-0.3, 0.3),
    );
    let t = Vector3::new(
        rng.uniform(-1., 1.),
        rng.uniform(-1., 1.),
        rng.uniform(-1., 1.),
    );
    let w2c = se3::from_rt(rot.matrix(), &t);
    let f = 0.9 * width as f64;
    Scene {
        means: vec![],
        log_scales: vec![],
        quats: vec![],
        opacity_logits: vec![],
        sh: vec![],
        sh_coeffs: sh::num_coeffs(sh_degree),
        features: vec![],
        k,
        intr: Intrinsics {
            fx: f,
            fy: f * 1.05,
            cx: width as f64 / 2.0 - 0.5 + rng.uniform(-2.0, 2.0),
            cy: height as f64 / 2.0 - 0.5 + rng.uniform(-2.0, 2.0),
            width,
            height,
        },
        w2c,
    }
}

/// `n` Gaussians spread over the view at 1-4 m, overlapping each other.
pub fn random_scene(
    seed: u64,
    n: usize,
    width: usize,
    height: usize,
    sh_degree: usize,
    k: usize,
) -> Scene {
    scene_between(seed, n, width, height, sh_degree, k, |_| {
        ([-0.6, 0.6], [-0.5, 0.5])
    })
}

/// [`random_scene`] with every Gaussian's centre inside the image: the projection's Jacobian
/// clamps none of them (a camera with another principal point would clamp others).
pub fn random_scene_in_view(
    seed: u64,
    n: usize,
    width: usize,
    height: usize,
    sh_degree: usize,
    k: usize,
) -> Scene {
    scene_between(seed, n, width, height, sh_degree, k, |i| {
        let span = |c: f64, f: f64, size: usize| [-(c + 0.5) / f, (size as f64 - 0.5 - c) / f];
        (span(i.cx, i.fx, width), span(i.cy, i.fy, height))
    })
}

/// `n` Gaussians at 1-4 m whose centres' x / z and y / z lie in the spans `spans` gives for
/// the camera.
fn scene_between(
    seed: u64,
    n: usize,
    width: usize,
    height: usize,
    sh_degree: usize,
    k: usize,
    spans: impl Fn(&Intrinsics) -> ([f64; 2], [f64; 2]),
) -> Scene {
    let mut rng = Rng::new(seed);
    let mut s = empty_scene(&mut rng, width, height, sh_degree, k);
    let ([x0, x1], [y0, y1]) = spans(&s.intr);
    for _ in 0..n {
        let z = rng.uniform(1.0, 4.0);
        let x = z * rng.uniform(x0, x1);
        let y = z * rng.uniform(y0, y1);
        let ls = [
            rng.uniform(-3.0, -1.5),
            rng.uniform(-3.0, -1.5),
            rng.uniform(-3.0, -1.5),
        ];
        let logit = rng.uniform(-1.0, 3.0);
        s.push(&mut rng, [x, y, z], ls, logit);
    }
    s
}

/// Calls `f(seed, scene, sh_degree, simd)` for the scenes the path tests share: per seed 0-3 a
/// random scene (SH degree 3) and a hard one (degree 1), at sizes that leave partial tiles and
/// with 0, 5, 8 and 19 feature channels, through every compositing implementation the machine
/// has (the portable one first).
pub fn each_scene_and_path(mut f: impl FnMut(u64, &Scene, usize, Simd)) {
    let simds: Vec<Simd> = [Simd::Portable].into_iter().chain(vector_paths()).collect();
    for seed in 0..4u64 {
        let (w, h) = [(64, 48), (37, 29), (100, 17), (16, 16)][seed as usize];
        let k = [0, 5, 8, 19][seed as usize];
        for (s, deg) in [
            (random_scene(seed, 400, w, h, 3, k), 3),
            (hard_scene(seed + 10, w, h, 1, k), 1),
        ] {
            for &simd in &simds {
                f(seed, &s, deg, simd);
            }
        }
    }
}

/// The hard cases: near the camera, partly off-screen (with the Jacobian clamped), nearly
/// degenerate, stacked on one pixel, and opaque enough for alpha to be capped.
pub fn hard_scene(seed: u64, width: usize, height: usize, sh_degree: usize, k: usize) -> Scene {
    let mut rng = Rng::new(seed);
    let mut s = empty_scene(&mut rng, width, height, sh_degree, k);
    // near the camera, large on screen
    s.push(&mut rng, [0.02, -0.01, 0.15], [-3.5, -3.2, -3.4], 0.5);
    // centre beyond the image edge, tail on screen (depths stay distinct from the others:
    // the fast path orders exact ties by index, the reference by rounding noise)
    s.push(&mut rng, [0.8, 0.1, 1.1], [-1.6, -1.7, -1.5], 1.0);
    // centre far outside the field of view (clamped Jacobian) but large enough to reach in
    s.push(&mut rng, [0.9, -0.2, 0.5], [-1.2, -1.3, -1.1], 0.0);
    // nearly degenerate: a needle and a disc
    s.push(&mut rng, [-0.2, 0.1, 2.0], [-9.0, -2.0, -2.2], 1.5);
    s.push(&mut rng, [0.1, 0.15, 1.5], [-2.0, -2.1, -10.0], 1.0);
    // a stack on one line of sight
    for d in 0..4 {
        let z = 1.0 + 0.3 * d as f64;
        s.push(&mut rng, [0.05 * z, -0.05 * z, z], [-2.0, -2.3, -2.1], 2.0);
    }
    // opaque: alpha capped near its centre
    s.push(&mut rng, [-0.3, -0.2, 2.5], [-2.0, -2.0, -2.0], 7.0);
    s
}

/// Images rendered by the reference.
pub struct RefImages {
    pub color: Vec<f64>,
    pub depth: Vec<f64>,
    pub alpha: Vec<f64>,
    pub features: Vec<f64>,
    /// Per Gaussian: its blending weights alpha * T summed over the image.
    pub weights: Vec<f64>,
}

/// Plain per-pixel reference in f64: every Gaussian against every pixel in global depth order,
/// no tiles, no bounding boxes; the same cut-offs as the configuration asks for.
pub fn reference_render(s: &Scene, sh_degree: usize, cfg: &RasterConfig) -> RefImages {
    let (r, t) = s.rt();
    let k = &s.intr;
    let (w, h) = (k.width, k.height);
    let cam_pos = -(r.transpose() * t);
    struct P {
        xy: [f64; 2],
        conic: Matrix2<f64>,
        o: f64,
        z: f64,
        c: [f64; 3],
        idx: usize,
    }
    let f = |v: Real| v as f64;
    let mut ps = Vec::new();
    for i in 0..s.len() {
        let mu = Vector3::new(
            f(s.means[3 * i]),
            f(s.means[3 * i + 1]),
            f(s.means[3 * i + 2]),
        );
        let pc = r * mu + t;
        if pc.z <= f(cfg.near) || pc.z >= f(cfg.far) {
            continue;
        }
        let q = &s.quats[4 * i..4 * i + 4];
        let rq =
            UnitQuaternion::from_quaternion(Quaternion::new(f(q[0]), f(q[1]), f(q[2]), f(q[3])))
                .to_rotation_matrix();
        let sc = Matrix3::from_diagonal(&Vector3::new(
            f(s.log_scales[3 * i]).exp(),
            f(s.log_scales[3 * i + 1]).exp(),
            f(s.log_scales[3 * i + 2]).exp(),
        ));
        let m = r * rq.matrix() * sc;
        let cov = m * m.transpose();
        let margin_x = f(cfg.fov_margin) * 0.5 * w as f64 / k.fx;
        let margin_y = f(cfg.fov_margin) * 0.5 * h as f64 / k.fy;
        let tx = (pc.x / pc.z).clamp(
            -(k.cx + 0.5) / k.fx - margin_x,
            (w as f64 - 0.5 - k.cx) / k.fx + margin_x,
        );
        let ty = (pc.y / pc.z).clamp(
            -(k.cy + 0.5) / k.fy - margin_y,
            (h as f64 - 0.5 - k.cy) / k.fy + margin_y,
        );
        let j = nalgebra::Matrix2x3::new(
            k.fx / pc.z,
            0.0,
            -k.fx * tx / pc.z,
            0.0,
            k.fy / pc.z,
            -k.fy * ty / pc.z,
        );
        let cov2 = j * cov * j.transpose() + Matrix2::identity() * f(cfg.dilation);
        let Some(conic) = cov2.try_inverse() else {
            continue;
        };
        let dir = (mu - cam_pos).normalize();
        let mut b = [0.0 as Real; 16];
        sh::basis(sh_degree, legslam_core_vec(dir), &mut b);
        let mut c = [0.5; 3];
        for (kk, bk) in b.iter().enumerate().take(sh::num_coeffs(sh_degree)) {
            for (ch, cv) in c.iter_mut().enumerate() {
                *cv += f(*bk) * f(s.sh[i * s.sh_coeffs * 3 + 3 * kk + ch]);
            }
        }
        ps.push(P {
            xy: [k.fx * pc.x / pc.z + k.cx, k.fy * pc.y / pc.z + k.cy],
            conic,
            o: 1.0 / (1.0 + (-f(s.opacity_logits[i])).exp()),
            z: pc.z,
            c: c.map(|v| v.max(0.0)),
            idx: i,
        });
    }
    ps.sort_by(|a, b| a.z.partial_cmp(&b.z).unwrap().then(a.idx.cmp(&b.idx)));
    let kk = s.k;
    let mut out = RefImages {
        color: vec![0.0; w * h * 3],
        depth: vec![0.0; w * h],
        alpha: vec![0.0; w * h],
        features: vec![0.0; w * h * kk],
        weights: vec![0.0; s.len()],
    };
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            let mut tr = 1.0;
            for g in &ps {
                let d = nalgebra::Vector2::new(x as f64 - g.xy[0], y as f64 - g.xy[1]);
                let sigma = 0.5 * (d.transpose() * g.conic * d)[(0, 0)];
                let a_raw = g.o * (-sigma).exp();
                if sigma < 0.0 || a_raw < f(cfg.alpha_min) {
                    continue;
                }
                let a = a_raw.min(f(cfg.alpha_max));
                let next = tr * (1.0 - a);
                if next < f(cfg.transmittance_min) {
                    break;
                }
                let wgt = a * tr;
                out.weights[g.idx] += wgt;
                for ch in 0..3 {
                    out.color[3 * p + ch] += wgt * g.c[ch];
                }
                out.depth[p] += wgt * g.z;
                for c in 0..kk {
                    out.features[p * kk + c] += wgt * f(s.features[g.idx * kk + c]);
                }
                tr = next;
            }
            out.alpha[p] = 1.0 - tr;
        }
    }
    out
}

#[cfg(not(feature = "f64"))]
fn legslam_core_vec(v: Vector3<f64>) -> glam::Vec3 {
    glam::Vec3::new(v.x as f32, v.y as f32, v.z as f32)
}
#[cfg(feature = "f64")]
fn legslam_core_vec(v: Vector3<f64>) -> glam::DVec3 {
    glam::DVec3::new(v.x, v.y, v.z)
}

/// Renders `s` with `opts` and runs the backward pass of random image gradients (normal, from
/// `seed`) on every output.
pub fn render_and_backward(s: &Scene, opts: &RenderOptions, seed: u64) -> (Rendered, Gradients) {
    let r = render(&s.gaussians(), &s.camera(), opts).unwrap();
    let npix = r.width * r.height;
    let mut rng = Rng::new(seed);
    let mut noise = |n: usize| -> Vec<Real> { (0..n).map(|_| rng.normal() as Real).collect() };
    let feature_pix = r.feature_width * r.feature_height;
    let (dc, dd, da, df) = (
        noise(npix * 3),
        noise(npix),
        noise(npix),
        noise(feature_pix * s.k),
    );
    let grads = ImageGrads {
        color: Some(&dc),
        depth: Some(&dd),
        alpha: Some(&da),
        features: (s.k > 0).then_some(&df[..]),
    };
    let g = backward(&s.gaussians(), &s.camera(), &r, &grads).unwrap();
    (r, g)
}

/// The values' bit patterns, to compare results exactly.
pub fn bits(v: &[Real]) -> Vec<u64> {
    v.iter().map(|x| x.to_bits() as u64).collect()
}

/// Asserts that two renders give the same bits in every image (`what` names the case).
pub fn assert_same_images(a: &Rendered, b: &Rendered, what: &str) {
    for (name, x, y) in [
        ("color", &a.color, &b.color),
        ("depth", &a.depth, &b.depth),
        ("alpha", &a.alpha, &b.alpha),
        ("features", &a.features, &b.features),
    ] {
        assert_eq!(bits(x), bits(y), "{what}: {name}");
    }
}

/// Asserts that two backward passes give the same bits in every gradient array.
pub fn assert_same_gradients(a: &Gradients, b: &Gradients, what: &str) {
    for ((name, x), (_, y)) in gradient_arrays(a).into_iter().zip(gradient_arrays(b)) {
        assert_eq!(bits(x), bits(y), "{what}: {name}");
    }
}

/// Every gradient array of `g` by name.
pub fn gradient_arrays(g: &Gradients) -> [(&'static str, &[Real]); 9] {
    [
        ("means", &g.means),
        ("log_scales", &g.log_scales),
        ("quats", &g.quats),
        ("opacity_logits", &g.opacity_logits),
        ("sh", &g.sh),
        ("features grad", &g.features),
        ("means2d", &g.means2d),
        ("contribution", &g.contribution),
        ("pose", &g.pose),
    ]
}
