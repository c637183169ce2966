//! The mapper: owns the map, its optimiser and the keyframes, and trains the map against
//! keyframes drawn in random order from a window of recent ones, each coarse-to-fine through
//! its image pyramid (as LEG-SLAM does), with periodic densification and pruning.

use std::time::Instant;

use super::densify::{add_screen_grads, densify, DensifyConfig};
use super::grow::{assign_features, grow, GrowConfig, RenderedView};
use super::order::spatial_order;
use super::pose::step_pose;
use super::prune::{add_contributions, keep_mask, PruneConfig};
use super::tally::Tally;
use super::{FeatureGrid, GaussianMap, Keyframe};
use crate::camera::{se3, Intrinsics, Pose};
use crate::loss::{
    Blend, DepthInputs, FeatureInputs, FeatureTarget, Loss, LossGrads, LossInputs, LossTerms,
    LossWeights,
};
use crate::optim::{normalize_quats, Adam, AdamConfig, Groups, LR_NAMES};
use crate::raster::{
    backward_into, render, render_into, BackwardScratch, Camera, Gradients, ImageGrads,
    RenderOptions, Rendered, Simd,
};
use crate::rng::Rng;
use crate::Real;

#[derive(Clone, Debug)]
pub struct MapperConfig {
    /// Pyramid levels per keyframe (3: full, 1/2, 1/4 resolution).
    pub levels: usize,
    /// The finest level trained (0 = full resolution, 1 = half: a CPU's budget).
    pub finest_level: usize,
    /// A keyframe's first `uses_per_level` uses are at the coarsest level, the next at the
    /// level below, and so on down to `finest_level`.
    pub uses_per_level: usize,
    /// Features are trained this many pyramid levels below the colour (coarser), at most at
    /// the coarsest level.
    pub feature_level_offset: usize,
    /// The features' coarser pixels point-sample the colour level's image (its footprints) at
    /// a place in their block drawn afresh each iteration, the target sampled there too. Off,
    /// each coarse pixel renders its block with the footprints dilated again at the coarse
    /// scale: a blur that cost 7-Scenes' held-out feature agreement at 80x60 (README, *The
    /// engine's speed*).
    pub feature_jitter: bool,
    /// Keyframes drawn from: the most recent this many ...
    pub window: usize,
    /// ... and in this share of iterations one older keyframe, so that the map a camera
    /// comes back to keeps its shape instead of being painted over by the new views alone.
    pub revisit: Real,
    /// Pyramid level at which a new keyframe's depth seeds new Gaussians.
    pub grow_level: usize,
    pub sh_degree: usize,
    pub num_features: usize,
    pub loss: LossWeights,
    pub adam: AdamConfig,
    pub grow: GrowConfig,
    pub prune: PruneConfig,
    pub densify: DensifyConfig,
    /// At every refinement, put the rows in spatial order ([`super::order`]) as pruning
    /// compacts them: the same map, walked with fewer cache misses.
    pub spatial_order: bool,
    /// Learning rates of keyframe poses (metres and radians per step; 0 keeps poses fixed).
    /// The first keyframe never moves: it anchors the map.
    pub pose_lr_translation: Real,
    pub pose_lr_rotation: Real,
    /// Learning rate of keyframe exposures (per-channel log gain and bias; 0 disables). The
    /// first keyframe's exposure is the map's.
    pub exposure_lr: Real,
    pub seed: u64,
    /// The rasterizer's implementation (default: the CPU's best; every one gives the same
    /// bits).
    pub simd: Simd,
}

impl Default for MapperConfig {
    fn default() -> Self {
        MapperConfig {
            levels: 3,
            finest_level: 1,
            uses_per_level: 2,
            feature_level_offset: 1,
            feature_jitter: true,
            window: 10,
            // 7-Scenes, 1000 frames, the camera coming back: 21.75 dB and ATE 4.5 cm against
            // 20.3 dB and 5.0 cm without (21.3 dB with 0.3).
            revisit: 0.5,
            grow_level: 1,
            sh_degree: 0,
            num_features: 0,
            loss: LossWeights::default(),
            // Features and colour sparse, the geometry dense: SLAM results as good, the step
            // 2.4 and 2 ms cheaper on the mapper bench (README, *The engine's speed*).
            adam: AdamConfig {
                sparse_features: true,
                sparse_sh: true,
                ..AdamConfig::default()
            },
            grow: GrowConfig {
                stride: 1,
                ..Default::default()
            },
            prune: PruneConfig::default(),
            densify: DensifyConfig::default(),
            spatial_order: true,
            pose_lr_translation: 0.0,
            pose_lr_rotation: 0.0,
            exposure_lr: 0.0,
            seed: 0,
            simd: Simd::Auto,
        }
    }
}

impl MapperConfig {
    /// Checks the options' values; the message names the offending one.
    pub fn validate(&self) -> Result<(), String> {
        crate::options::check_finite("mapper", self)?;
        if self.sh_degree > 3 {
            return Err(format!("sh_degree must be 0-3, got {}", self.sh_degree));
        }
        if self.finest_level >= self.levels.max(1) || self.grow_level >= self.levels.max(1) {
            return Err(format!(
                "finest_level ({}) and grow_level ({}) must be below levels ({})",
                self.finest_level, self.grow_level, self.levels
            ));
        }
        for (name, v) in [
            ("pose_lr_translation", self.pose_lr_translation),
            ("pose_lr_rotation", self.pose_lr_rotation),
            ("exposure_lr", self.exposure_lr),
            ("grow_merge_tolerance", self.grow.merge_tolerance),
            (
                "grow_merge_depth_tolerance",
                self.grow.merge_depth_tolerance,
            ),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{name} must be finite and >= 0, got {v}"));
            }
        }
        if !(self.grow.flatness > 0.0 && self.grow.flatness <= 1.0) {
            return Err(format!(
                "grow_flatness must lie in (0, 1], got {}",
                self.grow.flatness
            ));
        }
        if !(0.0..=1.0).contains(&self.revisit) {
            return Err(format!("revisit must lie in [0, 1], got {}", self.revisit));
        }
        Ok(())
    }
}

/// What `train` did.
#[derive(Clone, Copy, Debug, Default)]
pub struct TrainReport {
    pub iterations: usize,
    /// Loss terms of the last iteration.
    pub last: LossTerms,
    pub cloned: usize,
    pub split: usize,
    pub pruned: usize,
    /// Seconds spent rendering, in the loss, in the backward pass, and in the optimiser.
    pub render_s: f64,
    pub loss_s: f64,
    pub backward_s: f64,
    pub step_s: f64,
}

pub struct Mapper {
    pub config: MapperConfig,
    pub map: GaussianMap,
    pub keyframes: Vec<Keyframe>,
    adam: Adam,
    loss: Loss,
    queue: Vec<usize>,
    /// The window the queue was drawn from.
    queue_window: usize,
    rng: Rng,
    /// Draws the features' sample points: a stream of its own, so that `feature_jitter` on or
    /// off draws the same keyframes.
    jitter_rng: Rng,
    /// Since the last refinement: screen-space gradient norms (densification) and
    /// contributions to the views (pruning), per Gaussian.
    stats: Tally,
    seen: Tally,
    iteration: usize,
    scratch: Scratch,
    /// The first keyframe's median depth at full resolution (metres): the smallest scene
    /// extent.
    first_depth_median: f64,
}

/// Per-iteration buffers, kept between iterations.
#[derive(Default)]
struct Scratch {
    d_color: Vec<Real>,
    d_depth: Vec<Real>,
    d_feat: Vec<Real>,
    /// The feature target, as the loss reads it (`FeatureGrid::blended_into`).
    target_rows: Vec<Real>,
    target_blends: Vec<Blend>,
    /// The render under the keyframe's exposure.
    exposed: Vec<Real>,
    backward: BackwardScratch,
    /// The iteration's render.
    rendered: Rendered,
    /// Its gradients.
    grads: Gradients,
}

/// The median of the valid depths, 1 when there is none.
fn median_depth(depth: &[Real]) -> f64 {
    let mut depths: Vec<Real> = depth.iter().copied().filter(|d| *d > 0.0).collect();
    if depths.is_empty() {
        return 1.0;
    }
    let m = depths.len() / 2;
    *depths.select_nth_unstable_by(m, |a, b| a.total_cmp(b)).1 as f64
}

fn camera(pose: &Pose, intr: Intrinsics) -> Result<Camera, String> {
    Camera::new(intr, &se3::inverse(pose))
}

impl Mapper {
    pub fn new(config: MapperConfig) -> Result<Self, String> {
        config.validate()?;
        let coeffs = crate::raster::sh::num_coeffs(config.sh_degree);
        let adam = Adam::new(config.adam, 0, coeffs, config.num_features)?;
        Ok(Mapper {
            map: GaussianMap::new(coeffs, config.num_features),
            keyframes: Vec::new(),
            adam,
            loss: Loss::new(config.loss),
            queue: Vec::new(),
            queue_window: 0,
            rng: Rng::new(config.seed),
            jitter_rng: Rng::new(config.seed ^ 0x6a09_e667_f3bc_c908),
            stats: Tally::default(),
            seen: Tally::default(),
            iteration: 0,
            scratch: Scratch::default(),
            first_depth_median: 1.0,
            config,
        })
    }

    fn options(&self, color: bool, features: bool) -> RenderOptions {
        RenderOptions {
            sh_degree: self.config.sh_degree,
            color,
            depth: true,
            alpha: true,
            features,
            simd: self.config.simd,
            ..Default::default()
        }
    }

    /// Renders the map from a camera-to-world pose. Without `color`, depth and alpha only
    /// (the same bits as with it): the Gaussians' colours are neither evaluated nor composited.
    pub fn render(
        &self,
        pose: &Pose,
        intr: Intrinsics,
        color: bool,
        features: bool,
    ) -> Result<Rendered, String> {
        let opts = self.options(color, features && self.map.num_features > 0);
        render(&self.map.view(), &camera(pose, intr)?, &opts)
    }

    /// Adds a keyframe (colour [h, w, 3] in [0, 1], depth [h, w] metres, camera-to-world
    /// pose) and grows the map where it does not yet explain the keyframe's depth. Returns the
    /// keyframe's id and the number of Gaussians added.
    pub fn add_keyframe(
        &mut self,
        rgb: Vec<Real>,
        depth: Vec<Real>,
        intr: Intrinsics,
        pose: Pose,
    ) -> Result<(u32, usize), String> {
        let id = self.keyframes.len() as u32;
        let mut kf = Keyframe::new(id, rgb, depth, intr, pose, self.config.levels)?;
        let level = &kf.levels[self.config.grow_level.min(kf.levels.len() - 1)];
        let rendered = if self.map.is_empty() {
            None
        } else {
            let opts = self.options(false, false);
            Some(render(
                &self.map.view(),
                &camera(&pose, level.intrinsics)?,
                &opts,
            )?)
        };
        let view = rendered.as_ref().map(|r| RenderedView {
            alpha: &r.alpha,
            depth: &r.depth,
        });
        let added = grow(
            &mut self.map,
            level,
            &pose,
            view,
            None,
            id,
            &self.config.grow,
        );
        let added = self.cap_growth(added);
        self.adam.append(added);
        if id == 0 {
            self.first_depth_median = median_depth(&kf.levels[0].depth);
        }
        kf.release_below(self.config.finest_level.min(self.config.grow_level));
        self.keyframes.push(kf);
        self.update_extent();
        Ok((id, added))
    }

    /// Keeps the map within `max_gaussians`: of the `added` newest rows, keeps an evenly spread
    /// subset that fits. Returns how many were kept.
    fn cap_growth(&mut self, added: usize) -> usize {
        let n = self.map.len();
        let old = n - added;
        let budget = self.config.densify.max_gaussians.saturating_sub(old);
        if added <= budget {
            return added;
        }
        let keep: Vec<bool> = (0..n)
            .map(|i| i < old || ((i - old) * budget) % added < budget)
            .collect();
        self.map.retain(&keep);
        self.map.len() - old
    }

    /// Sets a keyframe's feature target (its compressed patch grid) and gives the Gaussians it
    /// created their initial features.
    pub fn set_features(&mut self, id: u32, grid: FeatureGrid) -> Result<(), String> {
        if grid.k != self.map.num_features {
            return Err(format!(
                "the map holds {} feature channels, the grid has {}",
                self.map.num_features, grid.k
            ));
        }
        let kf = self
            .keyframes
            .get_mut(id as usize)
            .ok_or_else(|| format!("no keyframe {id}"))?;
        let grow_level = self.config.grow_level.min(kf.levels.len() - 1);
        let level = &kf.levels[grow_level.max(kf.finest_kept())];
        assign_features(&mut self.map, level, &kf.pose, id, &grid);
        kf.features = Some(grid);
        Ok(())
    }

    /// Scene extent for learning rates and size limits: the spread of keyframe centres, at
    /// least the median depth of the first keyframe.
    fn update_extent(&mut self) {
        let centres: Vec<[f64; 3]> = self
            .keyframes
            .iter()
            .map(|k| se3::translation(&k.pose).into())
            .collect();
        let n = centres.len() as f64;
        let mean = [0, 1, 2].map(|a| centres.iter().map(|c| c[a]).sum::<f64>() / n);
        let spread = centres
            .iter()
            .map(|c| (0..3).map(|a| (c[a] - mean[a]).powi(2)).sum::<f64>().sqrt())
            .fold(0.0, f64::max);
        self.adam.config.scene_extent = (1.1 * spread).max(self.first_depth_median) as Real;
    }

    pub fn extent(&self) -> Real {
        self.adam.config.scene_extent
    }

    /// Scales the Gaussians' learning rates (every group) to `scale` times the configured
    /// ones, until set again: a refinement at the end of a run anneals them.
    pub fn set_lr_scale(&mut self, scale: Real) -> Result<(), String> {
        self.set_lr_scales(Groups::splat(scale))
    }

    /// Scales each group's learning rate to its `scales` times the configured one, until set
    /// again.
    pub fn set_lr_scales(&mut self, scales: Groups<Real>) -> Result<(), String> {
        for (name, s) in LR_NAMES.iter().zip(scales.into_array()) {
            if !(s.is_finite() && s > 0.0) {
                return Err(format!(
                    "the learning-rate scale of {name} must be > 0, got {s}"
                ));
            }
        }
        self.adam.config.lr = self.config.adam.lr.zip(scales, |lr, s| lr * s);
        Ok(())
    }

    /// The next keyframe to train on: a shuffled pass over the most recent `window`.
    /// With probability `revisit`, a keyframe older than the window instead, drawn uniformly.
    fn next_keyframe(&mut self, window: usize) -> usize {
        let older = self.keyframes.len().saturating_sub(window);
        if older > 0 && self.rng.next_f64() < f64::from(self.config.revisit) {
            return self.rng.below(older);
        }
        if self.queue.is_empty() || window != self.queue_window {
            let n = self.keyframes.len();
            self.queue = (n.saturating_sub(window)..n).collect();
            self.rng.shuffle(&mut self.queue);
            self.queue_window = window;
        }
        self.queue.pop().unwrap()
    }

    /// The pyramid level keyframe `ki`'s next iteration trains at: its first `uses_per_level`
    /// uses at the coarsest, the next at the level below, down to `finest_level` (or the
    /// finest it kept).
    pub fn training_level(&self, ki: usize) -> usize {
        let (c, kf) = (&self.config, &self.keyframes[ki]);
        let coarsest = kf.levels.len() - 1;
        coarsest
            .saturating_sub(kf.uses / c.uses_per_level.max(1))
            .max(c.finest_level.min(coarsest))
            .max(kf.finest_kept())
    }

    /// Runs `iterations` mapping iterations over the configured window of keyframes.
    pub fn train(&mut self, iterations: usize) -> Result<TrainReport, String> {
        self.train_window(iterations, self.config.window)
    }

    /// Runs `iterations` mapping iterations on keyframes drawn from the most recent `window`
    /// (all of them for `usize::MAX`, e.g. to refine the whole map at the end).
    pub fn train_window(
        &mut self,
        iterations: usize,
        window: usize,
    ) -> Result<TrainReport, String> {
        let mut report = TrainReport::default();
        if self.keyframes.is_empty() || self.map.is_empty() || window == 0 {
            return Ok(report);
        }
        for _ in 0..iterations {
            self.iterate(&mut report, window)?;
            report.iterations += 1;
        }
        Ok(report)
    }

    fn iterate(&mut self, report: &mut TrainReport, window: usize) -> Result<(), String> {
        let ki = self.next_keyframe(window);
        let li = self.training_level(ki);
        let c = &self.config;
        let kf = &mut self.keyframes[ki];
        let coarsest = kf.levels.len() - 1;
        // Features are rendered `feature_level_offset` levels coarser, from the colour pass's
        // projection: their target is an upsampled patch grid, and K channels cost K times a
        // colour channel.
        let lf = (li + c.feature_level_offset).min(coarsest);
        kf.uses += 1;
        let kf = &self.keyframes[ki];
        let with_features = kf.features.is_some() && self.map.num_features > 0;
        let level = &kf.levels[li];
        let intr = level.intrinsics;
        let (w, h) = (intr.width, intr.height);

        let t = Instant::now();
        let cam = camera(&kf.pose, intr)?;
        let fs = 1usize << (lf - li);
        let origin = (c.feature_jitter && fs > 1 && with_features).then(|| {
            let s = fs as f64;
            [
                self.jitter_rng.uniform(-0.5, s - 0.5) as Real,
                self.jitter_rng.uniform(-0.5, s - 0.5) as Real,
            ]
        });
        let opts = RenderOptions {
            feature_scale: fs,
            feature_origin: origin,
            for_backward: true,
            ..self.options(true, with_features)
        };
        // The render's buffers are the scratch's, taken for the iteration and put back.
        let mut r = std::mem::take(&mut self.scratch.rendered);
        render_into(&self.map.view(), &cam, &opts, &mut r)?;
        report.render_s += t.elapsed().as_secs_f64();

        let t = Instant::now();
        // Image-sized buffers reused across iterations; the loss overwrites the gradients.
        let k = self.map.num_features;
        let (fw, fh) = (r.feature_width, r.feature_height);
        let target = kf.levels[lf].intrinsics;
        debug_assert!(!with_features || (fw, fh) == (target.width, target.height));
        let sc = &mut self.scratch;
        sc.d_color.resize(w * h * 3, 0.0);
        sc.d_depth.resize(w * h, 0.0);
        sc.d_feat
            .resize(if with_features { fw * fh * k } else { 0 }, 0.0);
        if let (true, Some(g)) = (with_features, kf.features.as_ref()) {
            let at = origin.map(|o| (fs as Real, o, [w, h]));
            g.sampled_into(fw, fh, at, &mut sc.target_rows, &mut sc.target_blends);
        }
        // The loss sees the render as this keyframe's exposure makes it (the first keyframe's
        // exposure is the map's own).
        let exposed = c.exposure_lr > 0.0 && ki != 0;
        if exposed {
            kf.exposure.apply(&r.color, &mut sc.exposed);
        }
        let inputs = LossInputs {
            width: w,
            height: h,
            color: if exposed { &sc.exposed } else { &r.color },
            target_color: &level.rgb,
            color_mask: None,
            depth: Some(DepthInputs {
                rendered: &r.depth,
                target: &level.depth,
            }),
            features: with_features.then(|| FeatureInputs {
                rendered: &r.features,
                target: FeatureTarget::Blended {
                    rows: &sc.target_rows,
                    blends: &sc.target_blends,
                },
                channels: k,
                mask: None,
            }),
        };
        let terms = self.loss.evaluate(
            &inputs,
            LossGrads {
                color: &mut sc.d_color,
                depth: Some(&mut sc.d_depth),
                features: with_features.then_some(&mut sc.d_feat[..]),
            },
        )?;
        let exposure_grad = exposed.then(|| kf.exposure.backward(&r.color, &mut sc.d_color));
        report.loss_s += t.elapsed().as_secs_f64();

        let t = Instant::now();
        backward_into(
            &self.map.view(),
            &cam,
            &r,
            &ImageGrads {
                color: Some(&sc.d_color),
                depth: Some(&sc.d_depth),
                alpha: None,
                features: with_features.then_some(&sc.d_feat[..]),
            },
            &mut sc.backward,
            &mut sc.grads,
        )?;
        report.backward_s += t.elapsed().as_secs_f64();
        // Densification statistics from the main layer's screen-space gradients.
        add_screen_grads(&mut self.stats, &sc.grads.means2d, &sc.grads.rows, w, h);
        // Contributions at the finest level trained only: a Gaussian smaller than a coarser
        // level's pixels can fall between their centres there and seem to make nothing.
        if li == c.finest_level.min(coarsest) {
            let per_million = 1e6 / (w * h) as Real; // contributions in millionths of the view
            add_contributions(
                &mut self.seen,
                &sc.grads.contribution,
                &r.radii,
                &sc.grads.rows,
                per_million,
            );
        }
        self.scratch.rendered = r;
        report.last = terms;

        let t = Instant::now();
        self.refine_pose(ki);
        if let Some(g) = exposure_grad {
            let lr = f64::from(self.config.exposure_lr);
            self.keyframes[ki].exposure.step(&g, lr);
        }
        let grads = &self.scratch.grads;
        let rows = &grads.rows[..];
        self.adam
            .step_rows(self.map.params_mut(), Groups::from(grads), Some(rows))?;
        normalize_quats(&mut self.map.quats, self.config.adam.sparse.then_some(rows))?;
        self.iteration += 1;
        let interval = self.config.densify.interval;
        if interval > 0 && self.iteration % interval == 0 {
            self.refine(report)?;
        }
        report.step_s += t.elapsed().as_secs_f64();
        Ok(())
    }

    /// Moves keyframe `ki`'s pose along this iteration's pose gradient (never the first
    /// keyframe's, which anchors the map).
    fn refine_pose(&mut self, ki: usize) {
        let c = &self.config;
        let lr = [
            f64::from(c.pose_lr_translation),
            f64::from(c.pose_lr_rotation),
        ];
        if ki == 0 || lr == [0.0, 0.0] {
            return;
        }
        let kf = &mut self.keyframes[ki];
        kf.pose = step_pose(&mut kf.pose_adam, &kf.pose, &self.scratch.grads.pose, lr);
    }

    /// Densifies, then prunes; the optimiser's rows follow the map's.
    fn refine(&mut self, report: &mut TrainReport) -> Result<(), String> {
        let extent = self.extent();
        let d = densify(
            &mut self.map,
            &self.stats,
            extent,
            &self.config.densify,
            &mut self.rng,
        );
        self.adam.append(d.sources.len());
        // Rows densification just appended have no views yet: `keep_mask` reads them as unseen.
        let prune = keep_mask(
            &self.map,
            extent,
            None,
            Some(&self.seen),
            &self.config.prune,
        );
        let keep: Vec<bool> = d.keep.iter().zip(&prune).map(|(a, b)| *a && *b).collect();
        let before = self.map.len();
        if self.config.spatial_order {
            let order = spatial_order(&self.map.means, &keep);
            self.map.gather(&order);
            self.adam.gather(&order)?;
        } else {
            self.map.retain(&keep);
            self.adam.retain(&keep)?;
        }
        report.cloned += d.cloned;
        report.split += d.split;
        report.pruned += before - self.map.len() - d.split;
        self.stats.reset(self.map.len());
        self.seen.reset(self.map.len());
        Ok(())
    }
}

// Every option of [`MapperConfig`] by name (see [`crate::options`]).
crate::options!(MapperConfig, "mapper", {
    "levels" => levels,
    "finest_level" => finest_level,
    "uses_per_level" => uses_per_level,
    "feature_level_offset" => feature_level_offset,
    "feature_jitter" => feature_jitter,
    "window" => window,
    "revisit" => revisit,
    "grow_level" => grow_level,
    "sh_degree" => sh_degree,
    "num_features" => num_features,
    "seed" => seed,
    "loss_color" => loss.color,
    "loss_ssim_lambda" => loss.ssim_lambda,
    "loss_depth" => loss.depth,
    "loss_feature" => loss.feature,
    "lr_means" => adam.lr.means,
    "lr_log_scales" => adam.lr.log_scales,
    "lr_quats" => adam.lr.quats,
    "lr_opacity" => adam.lr.opacity_logits,
    "lr_sh" => adam.lr.sh,
    "lr_features" => adam.lr.features,
    "adam_sparse" => adam.sparse,
    "adam_sparse_features" => adam.sparse_features,
    "adam_sparse_sh" => adam.sparse_sh,
    "spatial_order" => spatial_order,
    "grow_stride" => grow.stride,
    "grow_alpha_threshold" => grow.alpha_threshold,
    "grow_depth_tolerance" => grow.depth_tolerance,
    "grow_occluded_tolerance" => grow.occluded_tolerance,
    "grow_opacity" => grow.opacity,
    "grow_scale" => grow.scale,
    "grow_merge_tolerance" => grow.merge_tolerance,
    "grow_merge_depth_tolerance" => grow.merge_depth_tolerance,
    "grow_flatness" => grow.flatness,
    "depth_min" => grow.depth_min,
    "depth_max" => grow.depth_max,
    "prune_min_opacity" => prune.min_opacity,
    "prune_max_world_scale" => prune.max_world_scale,
    "prune_min_contribution" => prune.min_contribution,
    "prune_contribution_views" => prune.contribution_views,
    "densify_interval" => densify.interval,
    "densify_grad_threshold" => densify.grad_threshold,
    "densify_split_scale" => densify.split_scale,
    "max_gaussians" => densify.max_gaussians,
    "pose_lr_translation" => pose_lr_translation,
    "pose_lr_rotation" => pose_lr_rotation,
    "exposure_lr" => exposure_lr,
    "simd" => simd,
});
