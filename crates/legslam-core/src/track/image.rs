//! Prepared RGB-D views: image pyramids built once per frame / reference.
//!
//! Level `l` has half the width and height of level `l-1` (floor), built by 2x2 block
//! averaging, so its intrinsics follow the pixel-centre convention of `cv2.resize`
//! (`f' = f/2`, `c' = (c + 0.5)/2 - 0.5`).

use rayon::prelude::*;

use super::TrackerConfig;
use crate::camera::Intrinsics;
use crate::camera::{se3, Pose};

/// Colour input of a view: interleaved RGB, row-major, `height * width * 3` values.
#[derive(Clone, Copy, Debug)]
pub enum Color<'a> {
    /// 8-bit RGB (what the Python side and the dataset loaders hold).
    Rgb8(&'a [u8]),
    /// Float RGB in [0, 1] (the engine's convention; e.g. colour rendered from the map).
    RgbF32(&'a [f32]),
}

/// One pyramid level of a view.
#[derive(Clone, Debug)]
pub(crate) struct Level {
    pub w: usize,
    pub h: usize,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// `(x - cx) / fx` per column and `(y - cy) / fy` per row: back-projection tables.
    pub xr: Vec<f32>,
    pub yr: Vec<f32>,
    /// Intensity (luma of the RGB in [0, 1]).
    pub intensity: Vec<f32>,
    /// Depth in metres, 0 = invalid (also outside the configured depth range).
    pub depth: Vec<f32>,
}

impl Level {
    fn new(w: usize, h: usize, fx: f64, fy: f64, cx: f64, cy: f64) -> Level {
        Level {
            w,
            h,
            fx: fx as f32,
            fy: fy as f32,
            cx: cx as f32,
            cy: cy as f32,
            xr: (0..w).map(|x| ((x as f64 - cx) / fx) as f32).collect(),
            yr: (0..h).map(|y| ((y as f64 - cy) / fy) as f32).collect(),
            intensity: vec![0.0; w * h],
            depth: vec![0.0; w * h],
        }
    }

    fn half(&self) -> Level {
        let (w, h) = (self.w / 2, self.h / 2);
        let mut out = Level::new(
            w,
            h,
            self.fx as f64 * 0.5,
            self.fy as f64 * 0.5,
            (self.cx as f64 + 0.5) * 0.5 - 0.5,
            (self.cy as f64 + 0.5) * 0.5 - 0.5,
        );
        let sw = self.w;
        out.intensity
            .par_chunks_mut(w)
            .zip(out.depth.par_chunks_mut(w))
            .enumerate()
            .for_each(|(y, (irow, drow))| {
                let r0 = 2 * y * sw;
                let r1 = r0 + sw;
                for x in 0..w {
                    let (a, b) = (r0 + 2 * x, r1 + 2 * x);
                    let i = &self.intensity;
                    irow[x] = 0.25 * (i[a] + i[a + 1] + i[b] + i[b + 1]);
                    let d = [
                        self.depth[a],
                        self.depth[a + 1],
                        self.depth[b],
                        self.depth[b + 1],
                    ];
                    drow[x] = block_depth(d);
                }
            });
        out
    }

    /// A level that is not stored (below the finest used level, never read).
    fn skipped(w: usize, h: usize) -> Level {
        Level {
            w,
            h,
            fx: 0.0,
            fy: 0.0,
            cx: 0.0,
            cy: 0.0,
            xr: Vec::new(),
            yr: Vec::new(),
            intensity: Vec::new(),
            depth: Vec::new(),
        }
    }

    /// Camera-space point of pixel `(x, y)` with depth `z`.
    #[inline(always)]
    pub fn point(&self, x: usize, y: usize, z: f32) -> [f32; 3] {
        [self.xr[x] * z, self.yr[y] * z, z]
    }
}

/// A new RGB-D frame to be aligned, prepared once (intensity and depth pyramids).
#[derive(Clone, Debug)]
pub struct Frame {
    pub(crate) levels: Vec<Level>,
    pub(crate) intrinsics: Intrinsics,
    /// Number of valid depth pixels (after the depth-range cut) at the first stored level
    /// (full resolution if `finest_level == 0`, else half resolution).
    pub(crate) valid_pixels: usize,
}

/// A reference RGB-D view with a known pose `T_wr` (camera-to-world): a previous (key)frame
/// or colour + depth rendered from the map. Holds, per used pyramid level, the intensity
/// with its gradients and the normal map; reusable for any number of [`super::track`] calls.
#[derive(Clone, Debug)]
pub struct Reference {
    pub(crate) frame: Frame,
    pub(crate) pose: Pose,
    /// Per level (empty below the finest used level): `(I, dI/dx, dI/dy, depth)` per pixel.
    pub(crate) igd: Vec<Vec<[f32; 4]>>,
    /// Per level: unit normal in the reference camera frame facing the camera, `w = 1` if
    /// valid, all zero if not.
    pub(crate) normals: Vec<Vec<[f32; 4]>>,
}

/// Depth of a 2x2 block: the average of the valid samples on the nearest surface, so that
/// depth edges are not blurred into points floating in between.
#[inline(always)]
fn block_depth(d: [f32; 4]) -> f32 {
    let mut zmin = f32::INFINITY;
    for &z in &d {
        if z > 0.0 && z < zmin {
            zmin = z;
        }
    }
    if !zmin.is_finite() {
        return 0.0;
    }
    let lim = zmin * 1.03;
    let (mut sum, mut n) = (0.0, 0.0);
    for &z in &d {
        if z > 0.0 && z <= lim {
            sum += z;
            n += 1.0;
        }
    }
    sum / n
}

#[inline(always)]
fn luma(r: f32, g: f32, b: f32) -> f32 {
    0.299 * r + 0.587 * g + 0.114 * b
}

impl Frame {
    /// Builds the pyramids of a frame. `depth` is metres with 0 = invalid; non-finite values
    /// and values outside `[config.min_depth, config.max_depth]` are treated as invalid.
    pub fn new(
        color: Color<'_>,
        depth: &[f32],
        k: &Intrinsics,
        config: &TrackerConfig,
    ) -> Result<Frame, String> {
        config.validate()?;
        k.validate()?;
        let (w, h) = (k.width, k.height);
        let n = w * h;
        if depth.len() != n {
            return Err(format!(
                "depth has {} values but the intrinsics say {}x{} = {}",
                depth.len(),
                w,
                h,
                n
            ));
        }
        let clen = match color {
            Color::Rgb8(c) => c.len(),
            Color::RgbF32(c) => c.len(),
        };
        if clen != 3 * n {
            return Err(format!(
                "colour has {clen} values but an {w}x{h} RGB image needs {}",
                3 * n
            ));
        }
        let nl = config.finest_level + config.levels;
        let shift = nl - 1;
        if (w >> shift) < 8 || (h >> shift) < 8 {
            return Err(format!(
                "a {w}x{h} image is too small for {nl} pyramid levels \
                 (the coarsest level must be at least 8x8)"
            ));
        }
        if let Color::RgbF32(c) = color {
            if c.iter().any(|v| !v.is_finite()) {
                return Err("colour contains non-finite values".into());
            }
        }
        let (zmin, zmax) = (config.min_depth as f32, config.max_depth as f32);
        let sane = |z: f32| {
            if z.is_finite() && z >= zmin && z <= zmax {
                z
            } else {
                0.0
            }
        };
        // Intensity of input pixel `i` (row-major index).
        let lum = |i: usize| -> f32 {
            let p = 3 * i;
            match color {
                Color::Rgb8(c) => {
                    const S: f32 = 1.0 / 255.0;
                    S * luma(c[p] as f32, c[p + 1] as f32, c[p + 2] as f32)
                }
                Color::RgbF32(c) => luma(c[p], c[p + 1], c[p + 2]),
            }
        };
        let mut levels = Vec::with_capacity(nl);
        if config.finest_level == 0 {
            let mut l0 = Level::new(w, h, k.fx, k.fy, k.cx, k.cy);
            l0.intensity
                .par_chunks_mut(w)
                .zip(l0.depth.par_chunks_mut(w))
                .enumerate()
                .for_each(|(y, (irow, drow))| {
                    let o = y * w;
                    for x in 0..w {
                        irow[x] = lum(o + x);
                        drow[x] = sane(depth[o + x]);
                    }
                });
            levels.push(l0);
        } else {
            // Level 0 is never used: build level 1 straight from the input (half the memory
            // traffic of storing level 0 first).
            levels.push(Level::skipped(w, h));
            let (w1, h1) = (w / 2, h / 2);
            let mut l1 = Level::new(
                w1,
                h1,
                k.fx * 0.5,
                k.fy * 0.5,
                (k.cx + 0.5) * 0.5 - 0.5,
                (k.cy + 0.5) * 0.5 - 0.5,
            );
            l1.intensity
                .par_chunks_mut(w1)
                .zip(l1.depth.par_chunks_mut(w1))
                .enumerate()
                .for_each(|(y, (irow, drow))| {
                    let r0 = 2 * y * w;
                    let r1 = r0 + w;
                    for x in 0..w1 {
                        let (a, b) = (r0 + 2 * x, r1 + 2 * x);
                        irow[x] = 0.25 * (lum(a) + lum(a + 1) + lum(b) + lum(b + 1));
                        drow[x] = block_depth([
                            sane(depth[a]),
                            sane(depth[a + 1]),
                            sane(depth[b]),
                            sane(depth[b + 1]),
                        ]);
                    }
                });
            levels.push(l1);
        }
        let valid_pixels = levels
            .last()
            .map(|l| l.depth.iter().filter(|&&z| z > 0.0).count())
            .unwrap_or(0);
        for l in levels.len()..nl {
            let next = levels[l - 1].half();
            levels.push(next);
        }
        Ok(Frame {
            levels,
            intrinsics: *k,
            valid_pixels,
        })
    }

    /// Full-resolution intrinsics of the frame.
    pub fn intrinsics(&self) -> &Intrinsics {
        &self.intrinsics
    }

    /// Number of pixels with valid depth at full (`finest_level == 0`) or half resolution.
    pub fn valid_pixels(&self) -> usize {
        self.valid_pixels
    }

    pub(crate) fn num_levels(&self) -> usize {
        self.levels.len()
    }
}

impl Reference {
    /// Prepares a reference view from colour, depth, intrinsics and its pose `T_wr` (a
    /// rotation off by up to 1e-2 is projected onto SO(3)).
    pub fn new(
        color: Color<'_>,
        depth: &[f32],
        k: &Intrinsics,
        pose: &Pose,
        config: &TrackerConfig,
    ) -> Result<Reference, String> {
        let frame = Frame::new(color, depth, k, config)?;
        Reference::from_frame(frame, pose, config)
    }

    /// Turns an already prepared frame into a reference (adds gradients and normals), e.g.
    /// the frame just tracked in frame-to-frame odometry, at its estimated pose.
    pub fn from_frame(
        frame: Frame,
        pose: &Pose,
        config: &TrackerConfig,
    ) -> Result<Reference, String> {
        config.validate()?;
        se3::validate_pose(pose, "reference pose")?;
        if frame.num_levels() != config.finest_level + config.levels {
            return Err(format!(
                "frame was prepared with {} pyramid levels, the config needs {}",
                frame.num_levels(),
                config.finest_level + config.levels
            ));
        }
        let nl = frame.num_levels();
        let mut igd = vec![Vec::new(); nl];
        let mut normals = vec![Vec::new(); nl];
        for l in config.finest_level..nl {
            let lev = &frame.levels[l];
            igd[l] = gradients(lev);
            normals[l] = normal_map(lev);
        }
        Ok(Reference {
            frame,
            pose: se3::orthonormalize(pose),
            igd,
            normals,
        })
    }

    /// The reference pose `T_wr` (camera-to-world).
    pub fn pose(&self) -> &Pose {
        &self.pose
    }

    /// Full-resolution intrinsics of the reference view.
    pub fn intrinsics(&self) -> &Intrinsics {
        &self.frame.intrinsics
    }
}

/// `(I, dI/dx, dI/dy, depth)` with central differences (zero gradient on the border).
fn gradients(lev: &Level) -> Vec<[f32; 4]> {
    let (w, h) = (lev.w, lev.h);
    let mut out = vec![[0.0f32; 4]; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let i = &lev.intensity;
        let o = y * w;
        for x in 0..w {
            let (mut gx, mut gy) = (0.0, 0.0);
            if x > 0 && x + 1 < w && y > 0 && y + 1 < h {
                gx = 0.5 * (i[o + x + 1] - i[o + x - 1]);
                gy = 0.5 * (i[o + x + w] - i[o + x - w]);
            }
            row[x] = [i[o + x], gx, gy, lev.depth[o + x]];
        }
    });
    out
}

/// Normals from the cross product of central differences of the vertex map; invalid where a
/// neighbour is missing or across a depth discontinuity.
fn normal_map(lev: &Level) -> Vec<[f32; 4]> {
    let (w, h) = (lev.w, lev.h);
    let mut out = vec![[0.0f32; 4]; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        if y == 0 || y + 1 >= h {
            return;
        }
        let d = &lev.depth;
        #[allow(clippy::needless_range_loop)] // x indexes the row and the neighbours
        for x in 1..w.saturating_sub(1) {
            let c = y * w + x;
            let z = d[c];
            if z <= 0.0 {
                continue;
            }
            let (zl, zr, zu, zd) = (d[c - 1], d[c + 1], d[c - w], d[c + w]);
            let lim = 0.05 * z;
            if [zl, zr, zu, zd]
                .iter()
                .any(|&q| q <= 0.0 || (q - z).abs() > lim)
            {
                continue;
            }
            let pl = lev.point(x - 1, y, zl);
            let pr = lev.point(x + 1, y, zr);
            let pu = lev.point(x, y - 1, zu);
            let pd = lev.point(x, y + 1, zd);
            let a = [pr[0] - pl[0], pr[1] - pl[1], pr[2] - pl[2]];
            let b = [pd[0] - pu[0], pd[1] - pu[1], pd[2] - pu[2]];
            let mut n = [
                a[1] * b[2] - a[2] * b[1],
                a[2] * b[0] - a[0] * b[2],
                a[0] * b[1] - a[1] * b[0],
            ];
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            if len.is_nan() || len <= 0.0 || !len.is_finite() {
                continue;
            }
            let p = lev.point(x, y, z);
            let s = if n[0] * p[0] + n[1] * p[1] + n[2] * p[2] > 0.0 {
                -1.0 / len
            } else {
                1.0 / len
            };
            n = [n[0] * s, n[1] * s, n[2] * s];
            row[x] = [n[0], n[1], n[2], 1.0];
        }
    });
    out
}
