//! A truncated signed distance volume that fuses tracked frames' depth, and the depth it
//! ray-casts from any pose: the tracker's reference surface (frame-to-model tracking, as
//! KinectFusion's). Against the last frame's depth alone each frame inherits the last one's
//! error; against the fused surface the noise of many frames averages out and a camera that
//! comes back meets what it saw before.
//!
//! Voxels live in blocks of 8^3 allocated around measured surfaces only, so memory follows the
//! surface area seen, not the volume; a hash map from chunk coordinates finds a chunk's table
//! of its 4^3 blocks. Values are signed distances along the optical axis, divided by the
//! truncation distance and clamped to [-1, 1], averaged over frames with a weight capped at
//! `max_weight` (so the surface can still move).

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use glam::{Mat3, Vec3};
use rayon::prelude::*;

use crate::camera::{se3, Intrinsics, Pose};

/// Voxels along a block's side (`locate` divides by shifting).
const SIDE: usize = 8;
const BLOCK_VOXELS: usize = SIDE * SIDE * SIDE;
/// Blocks along a chunk's side (`chunk_key` divides by shifting): the ray-cast crosses empty
/// space a chunk at a time.
const CHUNK: i32 = 4;
const CHUNK_BLOCKS: usize = (CHUNK * CHUNK * CHUNK) as usize;
/// A chunk table's entry for a block not allocated.
const NO_BLOCK: u32 = u32::MAX;

/// Volume settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TsdfConfig {
    /// Voxel edge (m).
    pub voxel: f64,
    /// Truncation distance (m): how far in front of and behind a measured surface a frame
    /// updates voxels.
    pub truncation: f64,
    /// Cap on a voxel's accumulated weight (frames).
    pub max_weight: f32,
    /// Depth range (m) that is fused and ray-cast (a zero minimum: every positive depth).
    pub min_depth: f64,
    pub max_depth: f64,
}

impl Default for TsdfConfig {
    fn default() -> Self {
        TsdfConfig {
            voxel: 0.01,
            truncation: 0.04,
            max_weight: 64.0,
            min_depth: 0.1,
            max_depth: 10.0,
        }
    }
}

impl TsdfConfig {
    pub fn validate(&self) -> Result<(), String> {
        let pos = |v: f64| v.is_finite() && v > 0.0;
        if !pos(self.voxel) || !pos(self.truncation) {
            return Err(format!(
                "voxel and truncation must be positive, got {} and {}",
                self.voxel, self.truncation
            ));
        }
        if self.truncation < self.voxel {
            return Err(format!(
                "truncation ({}) must be at least one voxel ({})",
                self.truncation, self.voxel
            ));
        }
        if !(1.0..=255.0).contains(&self.max_weight) || self.max_weight.fract() != 0.0 {
            return Err(format!(
                "max_weight must be a whole number of frames from 1 to 255, got {}",
                self.max_weight
            ));
        }
        if !(self.min_depth >= 0.0 && self.max_depth.is_finite() && self.max_depth > self.min_depth)
        {
            return Err(format!(
                "need 0 <= min_depth < max_depth, got {} and {}",
                self.min_depth, self.max_depth
            ));
        }
        Ok(())
    }
}

/// Per voxel (x fastest) its normalised signed distance, quantised ([`UNSEEN`] until a frame
/// observes it), and apart from the distances its weight (frames): the ray-cast reads the
/// distances only, two bytes a voxel. Against f32 distance and weight side by side: a third
/// of the memory, a ray-cast ~10% faster (its voxel reads miss the cache).
#[derive(Clone)]
struct Block {
    sdf: [i16; BLOCK_VOXELS],
    weight: [u8; BLOCK_VOXELS],
}

impl Block {
    fn empty() -> Self {
        Block {
            sdf: [UNSEEN; BLOCK_VOXELS],
            weight: [0; BLOCK_VOXELS],
        }
    }
}

/// The distance of a voxel no frame has observed.
const UNSEEN: i16 = i16::MIN;
/// A normalised distance in [-1, 1] is stored times this (steps of 1/32767 truncation).
const SDF_SCALE: f32 = i16::MAX as f32;

fn quantise(f: f32) -> i16 {
    (f * SDF_SCALE + 0.5f32.copysign(f)) as i16
}

fn dequantise(s: i16) -> f32 {
    s as f32 * (1.0 / SDF_SCALE)
}

/// Block coordinates packed 21 bits each (blocks of 8 cm reach +-84 km).
type Key = u64;

fn key(b: [i32; 3]) -> Key {
    let m = (1u64 << 21) - 1;
    ((b[0] as u64 & m) << 42) | ((b[1] as u64 & m) << 21) | (b[2] as u64 & m)
}

/// SplitMix64's finaliser over the packed key: the hash table indexes by the low bits, which
/// of the key alone would be the z coordinate's.
#[derive(Default)]
struct KeyHasher(u64);

impl Hasher for KeyHasher {
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(self.0.rotate_left(8) ^ b as u64);
        }
    }
    fn write_u64(&mut self, v: u64) {
        let mut z = v.wrapping_add(0x9e37_79b9_7f4a_7c15);
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        self.0 = z ^ (z >> 31);
    }
    fn finish(&self) -> u64 {
        self.0
    }
}

type Index = HashMap<Key, u32, BuildHasherDefault<KeyHasher>>;

/// A chunk looked up: its key and its table's number (None: no block allocated in it).
type ChunkCache = (Key, Option<u32>);

/// The fused volume.
pub struct Tsdf {
    cfg: TsdfConfig,
    /// The chunks holding at least one block, by chunk key: each one's table in `chunks`.
    index: Index,
    /// Per chunk, its blocks' numbers ([`NO_BLOCK`] where not allocated), indexed by
    /// [`block_in_chunk`]. Against a hash map of blocks: one lookup a chunk a ray crosses
    /// instead of one a block, and whether a chunk is empty comes with it.
    chunks: Vec<[u32; CHUNK_BLOCKS]>,
    blocks: Vec<Block>,
    /// Each block's coordinates (in blocks).
    coords: Vec<[i32; 3]>,
}

/// A camera for the volume's loops: world-to-camera rotation and translation, the centre and
/// the pinhole, in f32.
struct View {
    r_cw: Mat3,
    t_cw: Vec3,
    r_wc: Mat3,
    centre: Vec3,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
}

impl View {
    fn new(k: &Intrinsics, pose: &Pose) -> Result<View, String> {
        k.validate()?;
        se3::validate_pose(pose, "pose")?;
        let pose = se3::orthonormalize(pose);
        let r = Mat3::from_cols_array(&[
            pose[(0, 0)] as f32,
            pose[(1, 0)] as f32,
            pose[(2, 0)] as f32,
            pose[(0, 1)] as f32,
            pose[(1, 1)] as f32,
            pose[(2, 1)] as f32,
            pose[(0, 2)] as f32,
            pose[(1, 2)] as f32,
            pose[(2, 2)] as f32,
        ]);
        let centre = Vec3::new(
            pose[(0, 3)] as f32,
            pose[(1, 3)] as f32,
            pose[(2, 3)] as f32,
        );
        Ok(View {
            r_cw: r.transpose(),
            t_cw: -(r.transpose() * centre),
            r_wc: r,
            centre,
            fx: k.fx as f32,
            fy: k.fy as f32,
            cx: k.cx as f32,
            cy: k.cy as f32,
        })
    }

    /// World direction of pixel (u, v)'s ray, scaled so that its camera z is 1: a point at
    /// `centre + t * dir` has depth `t`.
    fn ray(&self, u: f32, v: f32) -> Vec3 {
        let d = Vec3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0);
        self.r_wc * d
    }
}

impl Tsdf {
    pub fn new(cfg: TsdfConfig) -> Result<Tsdf, String> {
        cfg.validate()?;
        Ok(Tsdf {
            cfg,
            index: Index::default(),
            chunks: Vec::new(),
            blocks: Vec::new(),
            coords: Vec::new(),
        })
    }

    pub fn config(&self) -> &TsdfConfig {
        &self.cfg
    }

    /// Allocated blocks.
    pub fn blocks(&self) -> usize {
        self.blocks.len()
    }

    /// Bytes held by the voxels and the chunk tables.
    pub fn memory_bytes(&self) -> usize {
        self.blocks.len() * std::mem::size_of::<Block>()
            + self.chunks.len() * std::mem::size_of::<[u32; CHUNK_BLOCKS]>()
    }

    /// Block and voxel of a world point, in voxel units `g = p / voxel`.
    fn locate(g: Vec3) -> ([i32; 3], usize) {
        Self::split([floor(g.x), floor(g.y), floor(g.z)])
    }

    /// Block of voxel `v` (integer voxel coordinates) and its index within the block.
    fn split(v: [i32; 3]) -> ([i32; 3], usize) {
        // SIDE is 8: shifting floors towards minus infinity, the mask is the remainder.
        let b = v.map(|c| c >> 3);
        let l = v.map(|c| (c & 7) as usize);
        (b, l[0] + SIDE * (l[1] + SIDE * l[2]))
    }

    /// Fuses a depth image (metres, 0 or non-finite = no measurement; row-major, the size of
    /// `k`) seen from `pose` (camera-to-world).
    pub fn integrate(&mut self, depth: &[f32], k: &Intrinsics, pose: &Pose) -> Result<(), String> {
        let view = View::new(k, pose)?;
        let (w, h) = (k.width, k.height);
        if depth.len() != w * h {
            return Err(format!(
                "depth has {} values, the intrinsics say {w}x{h}",
                depth.len()
            ));
        }
        let inv_voxel = (1.0 / self.cfg.voxel) as f32;
        let trunc = self.cfg.truncation as f32;
        // The blocks the band [d - trunc, d + trunc] of each measured pixel passes through,
        // sampled at half a block along the ray (and at both ends).
        let step = 0.5 * SIDE as f32 * self.cfg.voxel as f32;
        let samples = (2.0 * trunc / step).ceil() as usize;
        let mut keys: Vec<Key> = (0..h)
            .into_par_iter()
            .flat_map_iter(|v| {
                let mut row = Vec::new();
                for u in 0..w {
                    let d = depth[v * w + u];
                    if !depth_ok(&self.cfg, d) {
                        continue;
                    }
                    let dir = view.ray(u as f32, v as f32);
                    for s in 0..=samples {
                        let t = (d - trunc + s as f32 * (2.0 * trunc / samples as f32)).max(0.0);
                        let (b, _) = Self::locate((view.centre + t * dir) * inv_voxel);
                        let kb = key(b);
                        if row.last() != Some(&kb) {
                            row.push(kb);
                        }
                    }
                }
                row
            })
            .collect();
        keys.par_sort_unstable();
        keys.dedup();
        let mut touched = vec![false; self.blocks.len()];
        for kb in keys {
            let b = unkey(kb);
            let chunks = &mut self.chunks;
            let c = *self.index.entry(chunk_key(b)).or_insert_with(|| {
                chunks.push([NO_BLOCK; CHUNK_BLOCKS]);
                (chunks.len() - 1) as u32
            });
            let slot = &mut chunks[c as usize][block_in_chunk(b)];
            if *slot == NO_BLOCK {
                *slot = self.blocks.len() as u32;
                self.blocks.push(Block::empty());
                self.coords.push(b);
                touched.push(true);
            } else {
                touched[*slot as usize] = true;
            }
        }
        let voxel = self.cfg.voxel as f32;
        let (max_w, cfg) = (self.cfg.max_weight as u8, self.cfg);
        let inv_trunc = 1.0 / trunc;
        self.blocks
            .par_iter_mut()
            .zip(self.coords.par_iter())
            .zip(touched.par_iter())
            .for_each(|((block, b), &touched)| {
                if !touched {
                    return;
                }
                let origin = Vec3::new(b[0] as f32, b[1] as f32, b[2] as f32) * SIDE as f32;
                // Camera coordinates of the first voxel's centre, and a voxel's step along
                // each world axis.
                let c0 = view.r_cw * ((origin + 0.5) * voxel) + view.t_cw;
                let step = view.r_cw * voxel;
                let (wf, hf) = (w as f32, h as f32);
                // A row of voxels along x at a time: their pixels first, in a loop without
                // branches, then the updates (this and the compact voxels together took 7-Scenes'
                // fusion from 10.2 to 7.2 ms a frame, from one loop doing both per voxel).
                for row in 0..SIDE * SIDE {
                    let c_row =
                        c0 + step.y_axis * (row % SIDE) as f32 + step.z_axis * (row / SIDE) as f32;
                    let mut pixel = [usize::MAX; SIDE];
                    let mut cz = [0.0f32; SIDE];
                    for x in 0..SIDE {
                        let c = c_row + step.x_axis * x as f32;
                        let inv_z = 1.0 / c.z;
                        // The nearest pixel (libm's roundf is a call per voxel).
                        let u = view.fx * c.x * inv_z + view.cx + 0.5;
                        let v = view.fy * c.y * inv_z + view.cy + 0.5;
                        let inside = c.z > 0.0 && u >= 0.0 && v >= 0.0 && u < wf && v < hf;
                        pixel[x] = if inside {
                            v as usize * w + u as usize
                        } else {
                            usize::MAX
                        };
                        cz[x] = c.z;
                    }
                    let j0 = row * SIDE;
                    for x in 0..SIDE {
                        let Some(&d) = depth.get(pixel[x]) else {
                            continue;
                        };
                        let dist = d - cz[x];
                        if !depth_ok(&cfg, d) || dist < -trunc {
                            continue;
                        }
                        let f = (dist * inv_trunc).min(1.0);
                        let (sdf, wt) = (&mut block.sdf[j0 + x], &mut block.weight[j0 + x]);
                        let old = if *wt == 0 { 0.0 } else { dequantise(*sdf) };
                        let n = *wt as f32;
                        *sdf = quantise((old * n + f) / (n + 1.0));
                        *wt = wt.saturating_add(1).min(max_w);
                    }
                }
            });
        Ok(())
    }

    /// The fused signed distance (m, positive in front of surfaces) at world point `p`,
    /// interpolated between voxel centres; `None` where a voxel around it is unobserved.
    pub fn distance(&self, p: [f64; 3]) -> Option<f64> {
        let g = Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32) / self.cfg.voxel as f32;
        let f = self.trilinear(g, &mut (Key::MAX, None))?;
        Some(f as f64 * self.cfg.truncation)
    }

    /// The signed distance (m) of the voxel holding world point `p`; `None` where it is
    /// unobserved. What the ray-cast marches through.
    pub fn voxel_distance(&self, p: [f64; 3]) -> Option<f64> {
        let g = Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32) / self.cfg.voxel as f32;
        match self.voxel_at(g, &mut (Key::MAX, None))? {
            UNSEEN => None,
            s => Some(dequantise(s) as f64 * self.cfg.truncation),
        }
    }

    /// Quantised distance of the voxel holding voxel-unit point `g` ([`UNSEEN`] if no frame
    /// observed it), if its block is allocated. `cache` holds the last chunk looked up: after
    /// the call `g`'s, whose table tells an unallocated block from empty space.
    fn voxel_at(&self, g: Vec3, cache: &mut ChunkCache) -> Option<i16> {
        let (b, j) = Self::locate(g);
        self.block(b, cache).map(|i| self.blocks[i].sdf[j])
    }

    /// The number of block `b` if it is allocated, its chunk looked up in `cache` (and left
    /// there) unless already there.
    #[inline]
    fn block(&self, b: [i32; 3], cache: &mut ChunkCache) -> Option<usize> {
        let kc = chunk_key(b);
        if cache.0 != kc {
            *cache = (kc, self.index.get(&kc).copied());
        }
        self.block_in(b, cache.1)
    }

    /// The number of block `b` in chunk table `chunk` (b's), if both exist.
    #[inline]
    fn block_in(&self, b: [i32; 3], chunk: Option<u32>) -> Option<usize> {
        let i = self.chunks[chunk? as usize][block_in_chunk(b)];
        (i != NO_BLOCK).then_some(i as usize)
    }

    /// Trilinear distance at voxel-unit point `g` (voxel centres at half-integers); `None`
    /// where any of the eight voxels is unobserved.
    fn trilinear(&self, g: Vec3, cache: &mut ChunkCache) -> Option<f32> {
        let a = g - 0.5;
        let v = [floor(a.x), floor(a.y), floor(a.z)];
        let f = a - Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32);
        // The corners lie in one chunk, or in two to eight where they straddle boundaries:
        // each chunk is looked up once (corners alternate between chunks).
        let mut seen = [*cache; 9];
        let mut n_seen = 1;
        let mut acc = 0.0;
        for c in 0..8 {
            let o = [c & 1, (c >> 1) & 1, c >> 2];
            let (b, j) = Self::split([v[0] + o[0], v[1] + o[1], v[2] + o[2]]);
            let kc = chunk_key(b);
            let chunk = match seen[..n_seen].iter().find(|s| s.0 == kc) {
                Some(s) => s.1,
                None => {
                    let s = (kc, self.index.get(&kc).copied());
                    seen[n_seen] = s;
                    n_seen += 1;
                    s.1
                }
            };
            let s = self.blocks[self.block_in(b, chunk)?].sdf[j];
            if s == UNSEEN {
                return None;
            }
            let wx = if o[0] == 1 { f.x } else { 1.0 - f.x };
            let wy = if o[1] == 1 { f.y } else { 1.0 - f.y };
            let wz = if o[2] == 1 { f.z } else { 1.0 - f.z };
            acc += wx * wy * wz * s as f32;
        }
        *cache = seen[n_seen - 1];
        Some(acc * (1.0 / SDF_SCALE))
    }

    /// Depth (m, along the optical axis) of the fused surface seen from `pose` through `k`,
    /// into `out` (row-major, the size of `k`); 0 where no surface is found.
    pub fn raycast(&self, k: &Intrinsics, pose: &Pose, out: &mut [f32]) -> Result<(), String> {
        self.cast_all(k, pose, None, out)
    }

    /// As [`Tsdf::raycast`], but each ray through a pixel where `near` (a depth image the size
    /// of `k`) has depth d starts at d - 2 truncation: the surface near what a frame measured,
    /// without marching through the space in front of it (where the fused surface lies farther
    /// in front of d, that ray finds none). The rays through its holes march only over the
    /// depths it measured, 2 truncation either side: most of them find no surface, and
    /// marched to `max_depth` they cost most of a full ray-cast. The holes are cast in cells of
    /// `hole_cell` x `hole_cell` pixels, one ray through each cell's centre giving the depth of
    /// the cell's holes: a ray through a hole marches far, and the holes (a registered depth
    /// image's empty border) come in patches.
    pub fn raycast_near(
        &self,
        k: &Intrinsics,
        pose: &Pose,
        near: &[f32],
        hole_cell: usize,
        out: &mut [f32],
    ) -> Result<(), String> {
        if near.len() != k.width * k.height {
            return Err(format!(
                "near has {} values, the intrinsics say {}x{}",
                near.len(),
                k.width,
                k.height
            ));
        }
        if hole_cell == 0 {
            return Err("hole_cell must be at least 1".into());
        }
        self.cast_all(k, pose, Some((near, hole_cell)), out)
    }

    fn cast_all(
        &self,
        k: &Intrinsics,
        pose: &Pose,
        near: Option<(&[f32], usize)>,
        out: &mut [f32],
    ) -> Result<(), String> {
        let view = View::new(k, pose)?;
        let w = k.width;
        if out.len() != w * k.height {
            return Err(format!(
                "output has {} values, the intrinsics say {w}x{}",
                out.len(),
                k.height
            ));
        }
        let Some((near, cell)) = near else {
            out.par_chunks_mut(w).enumerate().for_each(|(v, row)| {
                let rays = (0..w).map(|u| (u, u as f32, v as f32, (0.0, f32::INFINITY)));
                self.cast_many(&view, rays, row);
            });
            return Ok(());
        };
        let two_trunc = 2.0 * self.cfg.truncation as f32;
        let ok = |d: f32| depth_ok(&self.cfg, d);
        // The depths `near` measured, widened by 2 truncation (none when it has none).
        let (lo, hi) = near
            .iter()
            .copied()
            .filter(|&d| ok(d))
            .fold((f32::INFINITY, 0.0f32), |(lo, hi), d| {
                (lo.min(d), hi.max(d))
            });
        let measured = (lo <= hi).then_some((lo - two_trunc, hi + two_trunc));
        // Rows in bands of `cell`, so that each thread has whole cells.
        out.par_chunks_mut(w * cell)
            .enumerate()
            .for_each(|(band, rows)| {
                let v0 = band * cell;
                let n_rows = rows.len() / w;
                rows.fill(0.0);
                let rays = (0..rows.len()).filter_map(|i| {
                    let (u, v) = (i % w, v0 + i / w);
                    let d = near[v * w + u];
                    ok(d).then_some((i, u as f32, v as f32, (d - two_trunc, f32::INFINITY)))
                });
                self.cast_many(&view, rays, rows);
                let Some(range) = measured else { return };
                for u0 in (0..w).step_by(cell) {
                    let n_cols = cell.min(w - u0);
                    let holes = |i: usize| {
                        let (u, v) = (u0 + i % n_cols, v0 + i / n_cols);
                        (!ok(near[v * w + u])).then_some((v - v0) * w + u)
                    };
                    if (0..n_cols * n_rows).all(|i| holes(i).is_none()) {
                        continue;
                    }
                    let centre = |first: usize, n: usize| first as f32 + 0.5 * (n - 1) as f32;
                    let d = self.cast(&view, centre(u0, n_cols), centre(v0, n_rows), range);
                    for j in (0..n_cols * n_rows).filter_map(holes) {
                        rows[j] = d;
                    }
                }
            });
        Ok(())
    }

    /// The depth [`March`] finds along the ray through pixel (u, v), within `(from, to)`.
    fn cast(&self, view: &View, u: f32, v: f32, range: (f32, f32)) -> f32 {
        let mut m = March::new(self, view, u, v, range);
        loop {
            if let Some(d) = m.advance(self) {
                return d;
            }
        }
    }

    /// The depth [`March`] finds along each of `rays` ((index into `out`, u, v, range)), into
    /// `out`. Several rays march at once, a sample of each in turn: each of a ray's samples
    /// waits on the one before (how far it steps depends on the voxel read), and the samples
    /// of other rays fill that wait.
    fn cast_many(
        &self,
        view: &View,
        mut rays: impl Iterator<Item = (usize, f32, f32, (f32, f32))>,
        out: &mut [f32],
    ) {
        const IN_FLIGHT: usize = 4;
        let mut flight: [Option<(usize, March)>; IN_FLIGHT] = [None; IN_FLIGHT];
        loop {
            let mut busy = false;
            for slot in &mut flight {
                if slot.is_none() {
                    *slot = rays
                        .next()
                        .map(|(i, u, v, range)| (i, March::new(self, view, u, v, range)));
                }
                if let Some((i, m)) = slot {
                    busy = true;
                    if let Some(d) = m.advance(self) {
                        out[*i] = d;
                        *slot = None;
                    }
                }
            }
            if !busy {
                return;
            }
        }
    }
}

/// A march along a ray over samples a voxel apart (`t = min_depth + n step`): a block at a
/// time through unallocated space and by the distance the volume guarantees free inside
/// blocks; at the first crossing from in front of a surface to behind it, back over every
/// sample since the last one in front, so that what is found is what a march over every sample
/// finds. The crossing is interpolated between the trilinear distances at its two samples.
/// The march covers the samples at depths within `(from, to)`.
#[derive(Clone, Copy)]
struct March {
    /// The camera centre and the ray's direction per unit of t, in voxels.
    g0: Vec3,
    g_dir: Vec3,
    /// t from one sample to the next.
    step: f32,
    t_min: f32,
    trunc_voxels: f32,
    /// The next sample and the last one to take.
    n: usize,
    last: usize,
    /// The last sample in front of a surface: (n, normalised distance).
    prev: Option<(usize, f32)>,
    /// Walking every sample (back over skipped ones).
    fine: bool,
    cache: ChunkCache,
}

impl March {
    fn new(tsdf: &Tsdf, view: &View, u: f32, v: f32, (from, to): (f32, f32)) -> March {
        let cfg = &tsdf.cfg;
        let inv_voxel = (1.0 / cfg.voxel) as f32;
        let dir = view.ray(u, v);
        let step = cfg.voxel as f32 / dir.length();
        let (t_min, t_max) = (cfg.min_depth as f32, cfg.max_depth as f32);
        March {
            g0: view.centre * inv_voxel,
            g_dir: dir * inv_voxel,
            step,
            t_min,
            trunc_voxels: (cfg.truncation / cfg.voxel) as f32,
            n: (-floor(-(from - t_min) / step)).max(0) as usize,
            last: ((t_max.min(to) - t_min) / step).floor() as usize,
            prev: None,
            fine: false,
            cache: (Key::MAX, None),
        }
    }

    /// Takes the next sample: the depth found (0 for none) once the march ends.
    #[inline]
    fn advance(&mut self, tsdf: &Tsdf) -> Option<f32> {
        let n = self.n;
        if n > self.last {
            return Some(0.0);
        }
        let t = self.t_min + n as f32 * self.step;
        let g = self.g0 + t * self.g_dir;
        match tsdf.voxel_at(g, &mut self.cache) {
            None if !self.fine => {
                self.prev = None;
                // `cache` holds g's chunk: a missing block in it, or none of its blocks.
                let cell = if self.cache.1.is_some() {
                    SIDE
                } else {
                    SIDE * CHUNK as usize
                };
                let exit = cell_exit(g, self.g_dir, t, cell as f32);
                self.n = (n + 1).max(-floor(-(exit - self.t_min) / self.step) as usize);
                return None;
            }
            Some(s) if s > 0 => {
                let f = dequantise(s);
                self.prev = Some((n, f));
                self.n += if self.fine {
                    1
                } else {
                    ((0.8 * f * self.trunc_voxels) as usize).max(1)
                };
                return None;
            }
            Some(s) if s != UNSEEN => match self.prev {
                Some((np, _)) if !self.fine && np + 1 < n => {
                    // Skipped samples may hold the first crossing: walk them.
                    self.fine = true;
                    self.n = np + 1;
                    return None;
                }
                Some((np, fp)) => {
                    let tp = self.t_min + np as f32 * self.step;
                    let gp = self.g0 + tp * self.g_dir;
                    let fp = tsdf.trilinear(gp, &mut self.cache).unwrap_or(fp);
                    let f = tsdf.trilinear(g, &mut self.cache).unwrap_or(dequantise(s));
                    let ts = if fp > f {
                        tp + (t - tp) * fp / (fp - f)
                    } else {
                        t
                    };
                    return Some(ts.clamp(tp, t));
                }
                // Behind a surface from the start, or seen from its back: no surface in
                // front.
                None if s < 0 => return Some(0.0),
                None => {}
            },
            // Unallocated (while walking back) or unobserved.
            _ => self.prev = None,
        }
        self.n += 1;
        None
    }
}

/// A measured depth within the range (0 is never one: it marks a pixel without depth).
fn depth_ok(cfg: &TsdfConfig, d: f32) -> bool {
    d > 0.0 && d as f64 >= cfg.min_depth && d as f64 <= cfg.max_depth
}

fn unkey(k: Key) -> [i32; 3] {
    // Sign-extend each 21-bit field.
    let f = |s: u32| (((k >> s) as i64) << 43 >> 43) as i32;
    [f(42), f(21), f(0)]
}

/// `x.floor()` as an integer, without libm's call (|x| < 2^31).
#[inline]
fn floor(x: f32) -> i32 {
    let i = x as i32;
    i - (x < i as f32) as i32
}

/// The chunk holding block `b`.
fn chunk_key(b: [i32; 3]) -> Key {
    const { assert!(CHUNK == 4) };
    // Shifting floors towards minus infinity.
    key(b.map(|c| c >> 2))
}

/// Block `b`'s entry in its chunk's table.
fn block_in_chunk(b: [i32; 3]) -> usize {
    let l = b.map(|c| (c & (CHUNK - 1)) as usize);
    l[0] + CHUNK as usize * (l[1] + CHUNK as usize * l[2])
}

/// The ray parameter at which voxel-unit point `g = g0 + t g_dir` leaves its cell of the grid
/// of `s` voxels.
fn cell_exit(g: Vec3, g_dir: Vec3, t: f32, s: f32) -> f32 {
    let c = g / s;
    let lo = Vec3::new(floor(c.x) as f32, floor(c.y) as f32, floor(c.z) as f32) * s;
    let mut dt = f32::INFINITY;
    for a in 0..3 {
        let d = g_dir[a];
        if d > 1e-12 {
            dt = dt.min((lo[a] + s - g[a]) / d);
        } else if d < -1e-12 {
            dt = dt.min((lo[a] - g[a]) / d);
        }
    }
    t + dt.max(0.0)
}
