//! Training the reference PerspNet on a rendered dataset: examples from the `samples`
//! and `targets` tables, batches as candle tensors, the training loop, checkpoints.
//!
//! An example is what the official loader builds per sample, read from storage
//! instead of re-rendered: the crop (ImageNet-normalised), the first M stored face
//! pixels, the ground-truth coordinates under them (`4.5 x` canonical, the official
//! scale), their barycentric correspondences (3 vertex ids and weights per pixel), the
//! crop's face mask and the canonical mesh. The targets must have been rendered at the
//! network's input size with at least M points (`render --size S --points M`); a
//! mismatch is an error that says which `render` options to use.
//!
//! A checkpoint folder holds `perspnet.json` (the network config and how it was
//! trained), `model.safetensors` (the weights, batch-norm statistics included) and
//! `loss.csv` (one row per step). Files are written atomically.

use crate::layers::{IMAGENET_MEAN, IMAGENET_STD};
use crate::loss::PerspNetLoss;
use crate::model::named_trainable_vars;
use crate::safetensors_file::SafetensorsFile;
use crate::{
    Adam, Architecture, CorrTarget, DirectNet, LossTargets, LossWeights, PerspNet, PerspNetConfig,
};
use arkit_data::conventions::Pose;
use arkit_data::dataset::Dataset;
use arkit_data::error::{Error, Result};
use arkit_data::eval_dataset::SplitLookup;
use arkit_data::render::CropTransform;
use arkit_data::rng::Rng;
use arkit_data::samples_table::SampleRecord;
use arkit_data::targets_table::{self, TargetsRecord};
use arkit_data::topology::FaceTopology;
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Scale of the official coordinate targets: `nocs = 4.5 x` canonical position.
pub const NOCS_SCALE: f32 = 4.5;

fn candle_err(what: &str, e: candle_core::Error) -> Error {
    Error::invalid(what, e.to_string())
}

/// One training example (see the module docs), flat row-major buffers. Every face pixel
/// of the crop is kept with its targets, so that training can draw fresh pixels each
/// time it sees the example (as the official loader does) and shift the crop.
#[derive(Clone, Debug)]
pub struct Example {
    /// The sample.
    pub sample: SampleRecord,
    /// Crop transform of the targets.
    pub crop: CropTransform,
    /// `3 x S x S`, ImageNet-normalised.
    pub image: Vec<f32>,
    /// `S x S` face mask (0 or 1).
    pub mask: Vec<f32>,
    /// Every face pixel of the crop (`y * S + x`), in mask order.
    pub pixels: Vec<u32>,
    /// `P x 3` ground-truth coordinates under each face pixel, `4.5 x` canonical.
    pub nocs: Vec<f32>,
    /// `P x 3` vertex ids of each face pixel's triangle.
    pub ids: Vec<u32>,
    /// `P x 3` barycentric weights.
    pub weights: Vec<f32>,
    /// The `M` points `render` stored (indices into `pixels`): the view without
    /// augmentation.
    pub points: Vec<u32>,
}

impl Example {
    /// Bytes this example holds in memory (its buffers; `train` keeps every example).
    pub fn memory_bytes(&self) -> usize {
        4 * (self.image.len()
            + self.mask.len()
            + self.pixels.len()
            + self.nocs.len()
            + self.ids.len()
            + self.weights.len()
            + self.points.len())
            + self.sample.verts.len() * 4
    }
}

/// What the network sees of one example in one step.
#[derive(Clone, Debug, PartialEq)]
pub struct View {
    /// `3 x S x S`, ImageNet-normalised.
    pub image: Vec<f32>,
    /// `S x S` face mask.
    pub mask: Vec<f32>,
    /// `M` chosen crop pixels (`y * S + x`).
    pub choose: Vec<u32>,
    /// `M x 3` coordinates, `4.5 x` canonical.
    pub nocs: Vec<f32>,
    /// `M x 3` vertex ids.
    pub ids: Vec<u32>,
    /// `M x 3` barycentric weights.
    pub weights: Vec<f32>,
    /// How far the crop was shifted, pixels `(dx, dy)` (the direct model's
    /// translation target moves with it).
    pub shift: (i64, i64),
}

/// Training-time augmentation, drawn per example and step from the run's seed.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Augmentation {
    /// Colour jitter strength `c`: brightness and contrast factors in `[1-c, 1+c]`,
    /// each channel's gain in `[1-c/2, 1+c/2]` (0: off).
    pub colour: f32,
    /// Crop jitter: the crop is shifted by up to this many pixels on each axis
    /// (the image, the mask and the face pixels move together; pixels shifted out
    /// are dropped, uncovered ones are the mean colour).
    pub shift_px: u32,
    /// Draw fresh face pixels each step instead of the `M` stored ones.
    pub resample_points: bool,
}

impl Augmentation {
    /// No augmentation: the stored view.
    pub const NONE: Augmentation = Augmentation {
        colour: 0.0,
        shift_px: 0,
        resample_points: false,
    };
    /// The default for training: colour 0.2, shift 2 px, fresh points.
    pub const DEFAULT: Augmentation = Augmentation {
        colour: 0.2,
        shift_px: 2,
        resample_points: true,
    };
}

impl Default for Augmentation {
    fn default() -> Self {
        Augmentation::DEFAULT
    }
}

impl Example {
    /// The view `render` stored: the crop as is and the stored points.
    pub fn stored_view(&self) -> View {
        self.view_of(self.image.clone(), self.mask.clone(), &self.points, (0, 0))
    }

    /// An augmented view, drawn from `rng`.
    pub fn augmented_view(&self, m: usize, aug: &Augmentation, rng: &mut Rng) -> View {
        let s = self.crop.size as usize;
        let k = aug.shift_px as i64;
        let (dx, dy) = if k > 0 {
            (
                rng.below(2 * k as u64 + 1) as i64 - k,
                rng.below(2 * k as u64 + 1) as i64 - k,
            )
        } else {
            (0, 0)
        };
        let image = jitter_colour(
            &shift_planes(&self.image, s, 3, dx, dy),
            s * s,
            aug.colour,
            rng,
        );
        let mask = shift_planes(&self.mask, s, 1, dx, dy);
        let inside = |p: u32| {
            let (x, y) = ((p as usize % s) as i64 + dx, (p as usize / s) as i64 + dy);
            x >= 0 && y >= 0 && x < s as i64 && y < s as i64
        };
        let kept: Vec<u32> = (0..self.pixels.len() as u32)
            .filter(|&i| inside(self.pixels[i as usize]))
            .collect();
        if kept.is_empty() {
            return self.stored_view();
        }
        let points: Vec<u32> = if aug.resample_points {
            arkit_data::render::sample_points(kept.len(), m, rng.next_u64())
                .into_iter()
                .map(|i| kept[i as usize])
                .collect()
        } else {
            let stored: Vec<u32> = self
                .points
                .iter()
                .copied()
                .filter(|&i| inside(self.pixels[i as usize]))
                .collect();
            if stored.is_empty() {
                return self.stored_view();
            }
            (0..m).map(|i| stored[i % stored.len()]).collect()
        };
        self.view_of(image, mask, &points, (dx, dy))
    }

    fn view_of(
        &self,
        image: Vec<f32>,
        mask: Vec<f32>,
        points: &[u32],
        (dx, dy): (i64, i64),
    ) -> View {
        let s = self.crop.size as i64;
        let mut v = View {
            image,
            mask,
            choose: Vec::with_capacity(points.len()),
            nocs: Vec::with_capacity(3 * points.len()),
            ids: Vec::with_capacity(3 * points.len()),
            weights: Vec::with_capacity(3 * points.len()),
            shift: (dx, dy),
        };
        for &i in points {
            let i = i as usize;
            let p = self.pixels[i] as i64;
            v.choose.push(((p / s + dy) * s + p % s + dx) as u32);
            v.nocs.extend_from_slice(&self.nocs[3 * i..3 * i + 3]);
            v.ids.extend_from_slice(&self.ids[3 * i..3 * i + 3]);
            v.weights.extend_from_slice(&self.weights[3 * i..3 * i + 3]);
        }
        v
    }
}

/// Shifts `planes` planes of `s x s` by `(dx, dy)` pixels; uncovered pixels are 0 (the
/// mean colour after normalisation, background in a mask).
fn shift_planes(data: &[f32], s: usize, planes: usize, dx: i64, dy: i64) -> Vec<f32> {
    if dx == 0 && dy == 0 {
        return data.to_vec();
    }
    let mut out = vec![0f32; data.len()];
    for c in 0..planes {
        for y in 0..s as i64 {
            let sy = y - dy;
            if sy < 0 || sy >= s as i64 {
                continue;
            }
            for x in 0..s as i64 {
                let sx = x - dx;
                if sx >= 0 && sx < s as i64 {
                    out[c * s * s + (y as usize) * s + x as usize] =
                        data[c * s * s + (sy as usize) * s + sx as usize];
                }
            }
        }
    }
    out
}

/// Brightness, contrast and per-channel gain on a normalised `3 x n` image, in pixel
/// values (`[0, 1]`, clamped), renormalised.
fn jitter_colour(image: &[f32], n: usize, c: f32, rng: &mut Rng) -> Vec<f32> {
    if c <= 0.0 {
        return image.to_vec();
    }
    let c = c as f64;
    let brightness = rng.uniform(1.0 - c, 1.0 + c) as f32;
    let contrast = rng.uniform(1.0 - c, 1.0 + c) as f32;
    let gain: [f32; 3] = std::array::from_fn(|_| rng.uniform(1.0 - c / 2.0, 1.0 + c / 2.0) as f32);
    let mut out = image.to_vec();
    for k in 0..3 {
        let plane = &mut out[k * n..(k + 1) * n];
        let raw = |v: f32| v * IMAGENET_STD[k] + IMAGENET_MEAN[k];
        let mean = plane.iter().map(|&v| raw(v)).sum::<f32>() / n as f32;
        for v in plane.iter_mut() {
            let x = ((raw(*v) - mean) * contrast + mean) * brightness * gain[k];
            *v = (x.clamp(0.0, 1.0) - IMAGENET_MEAN[k]) / IMAGENET_STD[k];
        }
    }
    out
}

/// The crop of a sample's image, as the network's input: `3 x S x S` floats,
/// ImageNet-normalised.
pub fn network_input(image: &image::RgbImage, crop: &CropTransform) -> Vec<f32> {
    arkit_data::loader::normalise(crop.crop_image(image).as_raw())
}

/// Builds an example from a sample and its targets row for a network of `cfg`.
pub fn example(
    sample: &SampleRecord,
    targets: &TargetsRecord,
    cfg: &PerspNetConfig,
    dataset: &Dataset,
) -> Result<Example> {
    if targets.crop.size as usize != cfg.input_size {
        return Err(Error::invalid(
            "targets",
            format!(
                "rendered at {}x{} but the network takes {}x{}: run `arkit-tool render --size {} --points {}` (with --output to keep both)",
                targets.crop.size,
                targets.crop.size,
                cfg.input_size,
                cfg.input_size,
                cfg.input_size,
                cfg.points
            ),
        ));
    }
    if targets.points.len() < cfg.points {
        return Err(Error::invalid(
            "targets",
            format!(
                "{} stored points per sample, the network samples {}: run `arkit-tool render --points {}`",
                targets.points.len(),
                cfg.points,
                cfg.points
            ),
        ));
    }
    let mask = targets.mask()?;
    let pixels = targets_table::mask_pixel_indices(&mask);
    let weights = targets.weights();
    let verts = &sample.verts;
    if pixels.len() != targets.corr_vertices.len() {
        return Err(Error::invalid(
            "targets",
            format!(
                "{}: {} mask pixels but {} correspondence rows",
                sample.key,
                pixels.len(),
                targets.corr_vertices.len()
            ),
        ));
    }
    let n = pixels.len();
    let (mut nocs, mut ids, mut ws) = (
        Vec::with_capacity(3 * n),
        Vec::with_capacity(3 * n),
        Vec::with_capacity(3 * n),
    );
    for (p, tri) in targets.corr_vertices.iter().enumerate() {
        let mut c = [0f32; 3];
        for k in 0..3 {
            let v = tri[k] as usize;
            if 3 * v + 2 >= verts.len() {
                return Err(Error::invalid(
                    "targets",
                    format!("{}: vertex id {v} out of range", sample.key),
                ));
            }
            for (a, ca) in c.iter_mut().enumerate() {
                *ca += weights[p][k] * verts[3 * v + a];
            }
            ids.push(tri[k] as u32);
            ws.push(weights[p][k]);
        }
        nocs.extend(c.map(|x| x * NOCS_SCALE));
    }
    let points = targets.points[..cfg.points].to_vec();
    if let Some(&p) = points.iter().find(|&&p| p as usize >= n) {
        return Err(Error::invalid(
            "targets",
            format!("{}: point refers to mask pixel {p} of {n}", sample.key),
        ));
    }
    let image = dataset.image(sample)?;
    Ok(Example {
        sample: sample.clone(),
        crop: targets.crop,
        image: network_input(&image, &targets.crop),
        mask: mask.iter().map(|&m| m as u8 as f32).collect(),
        pixels,
        nocs,
        ids,
        weights: ws,
        points,
    })
}

/// Reads the examples of one split (`None`: all) of a rendered dataset, all of them
/// into memory ([`ShardedExamples`] reads one shard at a time).
pub fn read_examples(
    dataset: &Path,
    targets_dir: &Path,
    cfg: &PerspNetConfig,
    split: Option<&str>,
) -> Result<Vec<Example>> {
    let source = ShardedExamples::open(dataset, targets_dir, cfg, split)?;
    let mut out = Vec::with_capacity(source.total());
    for k in 0..source.shards() {
        out.extend(source.load(k)?.into_owned());
    }
    Ok(out)
}

/// Where [`train`] takes its examples from, one shard at a time: it loads a shard, runs
/// the batches of its examples, and drops it before loading the next.
pub trait ExampleShards: Sync {
    /// Number of shards.
    fn shards(&self) -> usize;
    /// Examples in shard `k`, known without loading it.
    fn shard_len(&self, k: usize) -> usize;
    /// The examples of shard `k`.
    fn load(&self, k: usize) -> Result<std::borrow::Cow<'_, [Example]>>;
    /// Examples in all shards.
    fn total(&self) -> usize {
        (0..self.shards()).map(|k| self.shard_len(k)).sum()
    }
}

/// Examples already in memory: one shard.
impl ExampleShards for [Example] {
    fn shards(&self) -> usize {
        1
    }
    fn shard_len(&self, _k: usize) -> usize {
        self.len()
    }
    fn load(&self, _k: usize) -> Result<std::borrow::Cow<'_, [Example]>> {
        Ok(std::borrow::Cow::Borrowed(self))
    }
}

impl ExampleShards for Vec<Example> {
    fn shards(&self) -> usize {
        self.as_slice().shards()
    }
    fn shard_len(&self, k: usize) -> usize {
        self.as_slice().shard_len(k)
    }
    fn load(&self, k: usize) -> Result<std::borrow::Cow<'_, [Example]>> {
        self.as_slice().load(k)
    }
}

/// The examples of one split of a rendered dataset, read shard by shard from the
/// `samples` and `targets` tables and the images when [`train`] reaches the shard
/// (`train --stream`), so memory holds one shard's examples instead of the whole
/// split's. Shards without an example of the split are left out.
pub struct ShardedExamples {
    dataset: PathBuf,
    targets_dir: PathBuf,
    cfg: PerspNetConfig,
    split: Option<String>,
    data: Dataset,
    splits: SplitLookup,
    /// `(shard index, samples file, examples in the split)`.
    shards: Vec<(usize, String, usize)>,
    /// Samples left out because their image could not be read, with the reason.
    unreadable: Vec<(arkit_data::release::SampleKey, String)>,
}

impl ShardedExamples {
    /// Opens a rendered dataset: checks every shard has its targets, checks that every
    /// example's image can be found and has its recorded size (from the image's header:
    /// a sample whose image cannot be read is left out and listed in
    /// [`ShardedExamples::unreadable`], never replaced), and counts the examples of
    /// `split` in each shard.
    pub fn open(
        dataset: &Path,
        targets_dir: &Path,
        cfg: &PerspNetConfig,
        split: Option<&str>,
    ) -> Result<Self> {
        let data = Dataset::open(dataset)?;
        let splits = SplitLookup::read(dataset)?;
        let mut shards = Vec::new();
        let mut unreadable = Vec::new();
        for shard in data.shards() {
            let tpath = targets_table::shard_path(targets_dir, shard.index);
            if !tpath.exists() {
                return Err(Error::format(
                    &tpath,
                    "no targets for this shard: run `arkit-tool render` first",
                ));
            }
            let skipped = targets_table::read_skipped_keys(targets_dir, shard.index)?;
            let kept: Vec<SampleRecord> = data
                .read_samples(shard)?
                .into_iter()
                .filter(|r| splits.keeps(r, split) && !skipped.contains(&r.key))
                .collect();
            let checks: Vec<Option<(arkit_data::release::SampleKey, String)>> = {
                use rayon::prelude::*;
                kept.par_iter()
                    .map(|r| {
                        data.check_image(r)
                            .err()
                            .map(|e| (r.key.clone(), e.to_string()))
                    })
                    .collect()
            };
            let bad = checks.iter().flatten().count();
            unreadable.extend(checks.into_iter().flatten());
            let n = kept.len() - bad;
            if n > 0 {
                shards.push((shard.index, shard.samples_file.clone(), n));
            }
        }
        Ok(Self {
            dataset: dataset.to_path_buf(),
            targets_dir: targets_dir.to_path_buf(),
            cfg: cfg.clone(),
            split: split.map(str::to_string),
            data,
            splits,
            shards,
            unreadable,
        })
    }
}

impl ShardedExamples {
    /// The samples left out because their image could not be read (key, reason naming
    /// the file), in shard order.
    pub fn unreadable(&self) -> &[(arkit_data::release::SampleKey, String)] {
        &self.unreadable
    }
}

impl ExampleShards for ShardedExamples {
    fn shards(&self) -> usize {
        self.shards.len()
    }

    fn shard_len(&self, k: usize) -> usize {
        self.shards[k].2
    }

    fn load(&self, k: usize) -> Result<std::borrow::Cow<'_, [Example]>> {
        let (index, samples_file, n) = &self.shards[k];
        let tpath = targets_table::shard_path(&self.targets_dir, *index);
        let targets = targets_table::read_targets_by_key(&tpath)?;
        // Samples `render` reported it could not render have no row: leave them out.
        let skipped = targets_table::read_skipped_keys(&self.targets_dir, *index)?;
        let mut out = Vec::with_capacity(*n);
        let unreadable: std::collections::HashSet<&arkit_data::release::SampleKey> =
            self.unreadable.iter().map(|(k, _)| k).collect();
        let shard = self
            .data
            .shards()
            .iter()
            .find(|s| s.index == *index)
            .ok_or_else(|| {
                Error::format(self.dataset.join(samples_file), "shard left the manifest")
            })?;
        for r in self.data.read_samples(shard)? {
            if !self.splits.keeps(&r, self.split.as_deref())
                || skipped.contains(&r.key)
                || unreadable.contains(&r.key)
            {
                continue;
            }
            let t = targets
                .get(&r.key)
                .ok_or_else(|| Error::format(&tpath, format!("no targets row for {}", r.key)))?;
            out.push(example(&r, t, &self.cfg, &self.data)?);
        }
        if out.len() != *n {
            return Err(Error::format(
                self.dataset.join(samples_file),
                format!("{} examples now, {n} when the run started", out.len()),
            ));
        }
        Ok(std::borrow::Cow::Owned(out))
    }
}

/// A batch as tensors.
pub struct Batch {
    /// `B x 3 x S x S`.
    pub image: Tensor,
    /// `B x M` u32.
    pub choose: Tensor,
    /// `B x M x 3`.
    pub nocs: Tensor,
    /// `B x V x 3` canonical meshes.
    pub model: Tensor,
    /// `B x S x S`.
    pub mask: Tensor,
    /// Barycentric targets.
    pub corr: CorrTarget,
    /// The direct model's `B x 12` targets ([`crate::direct::direct_target`]),
    /// for that architecture only.
    pub direct: Option<Tensor>,
}

/// Stacks examples' views into a batch (`views[i]` is a view of `examples[i]`).
pub fn batch(
    examples: &[&Example],
    views: &[View],
    cfg: &PerspNetConfig,
    device: &Device,
) -> Result<Batch> {
    let b = examples.len();
    let (s, m, v) = (cfg.input_size, cfg.points, cfg.vertices);
    let cat_f = |f: &dyn Fn(&View) -> &[f32]| -> Vec<f32> {
        views.iter().flat_map(|e| f(e).iter().copied()).collect()
    };
    let cat_u = |f: &dyn Fn(&View) -> &[u32]| -> Vec<u32> {
        views.iter().flat_map(|e| f(e).iter().copied()).collect()
    };
    let t = |data: Vec<f32>, shape: &[usize]| {
        Tensor::from_vec(data, shape, device).map_err(|e| candle_err("batch", e))
    };
    let model: Vec<f32> = examples
        .iter()
        .flat_map(|e| e.sample.verts.iter().copied())
        .collect();
    if model.len() != b * v * 3 {
        return Err(Error::invalid(
            "batch",
            format!(
                "meshes have {} values, the network expects {v} vertices",
                model.len() / b.max(1)
            ),
        ));
    }
    if views.len() != b || views.iter().any(|w| w.choose.len() != m) {
        return Err(Error::invalid(
            "batch",
            format!("each of the {b} views needs {m} points"),
        ));
    }
    let direct = match cfg.architecture {
        Architecture::PerspNet => None,
        Architecture::Direct => {
            let mut d = Vec::with_capacity(12 * b);
            for (e, w) in examples.iter().zip(views) {
                let pose = Pose::from_release_rt(&e.sample.rt)?;
                let k =
                    arkit_data::predict::intrinsics(e.sample.image_width, e.sample.image_height);
                d.extend(crate::direct::direct_target(&pose, &e.crop, &k, w.shift));
            }
            Some(t(d, &[b, 12])?)
        }
    };
    Ok(Batch {
        direct,
        image: t(cat_f(&|e| &e.image), &[b, 3, s, s])?,
        choose: Tensor::from_vec(cat_u(&|e| &e.choose), (b, m), device)
            .map_err(|e| candle_err("batch", e))?,
        nocs: t(cat_f(&|e| &e.nocs), &[b, m, 3])?,
        model: t(model, &[b, v, 3])?,
        mask: t(cat_f(&|e| &e.mask), &[b, s, s])?,
        corr: CorrTarget::Sparse {
            ids: Tensor::from_vec(cat_u(&|e| &e.ids), (b, m, 3), device)
                .map_err(|e| candle_err("batch", e))?,
            weights: t(cat_f(&|e| &e.weights), &[b, m, 3])?,
        },
    })
}

/// The learning rate of `step` of `total`: `base` for the first `hold` share of the
/// run, then falling linearly to zero at the end (the paper's schedule, scaled to the
/// run's length).
pub fn learning_rate_at(step: usize, total: usize, base: f64, hold: f64) -> f64 {
    let hold_steps = (hold.clamp(0.0, 1.0) * total as f64).round() as usize;
    if step < hold_steps || total <= hold_steps {
        base
    } else {
        base * (total - step) as f64 / (total - hold_steps) as f64
    }
}

/// The `V x 2` vertex UV table the network reads its UV map at.
pub fn vertex_uv(topology: &FaceTopology, device: &Device) -> Result<Tensor> {
    let v = topology.vertex_count;
    let flat: Vec<f32> = topology.uv[..v].iter().flat_map(|t| [t[0], t[1]]).collect();
    Tensor::from_vec(flat, (v, 2), device).map_err(|e| candle_err("vertex UVs", e))
}

/// The network of a config: PerspNet or the direct baseline (its `architecture`).
#[derive(Debug, Clone)]
pub enum Network {
    /// PerspNet (correspondences, then PnP).
    PerspNet(Box<PerspNet>),
    /// The paper's "Direct 6DoF Regress" baseline.
    Direct(Box<DirectNet>),
}

impl Network {
    /// Builds the network of `cfg` with fresh variables in `vb` (`vertex_uv`: see
    /// [`PerspNet::new`]; the direct baseline does not use it).
    pub fn new(
        cfg: &PerspNetConfig,
        vertex_uv: &Tensor,
        vb: VarBuilder,
    ) -> candle_core::Result<Self> {
        Ok(match cfg.architecture {
            Architecture::PerspNet => {
                Network::PerspNet(Box::new(PerspNet::new(cfg, vertex_uv, vb)?))
            }
            Architecture::Direct => Network::Direct(Box::new(DirectNet::new(cfg, vb)?)),
        })
    }

    /// The PerspNet, or an error naming what needs one.
    pub fn perspnet(&self, what: &str) -> Result<&PerspNet> {
        match self {
            Network::PerspNet(n) => Ok(n),
            Network::Direct(_) => Err(Error::invalid(
                what,
                "needs a PerspNet; this model is the direct baseline (no correspondences, mask or mesh)",
            )),
        }
    }
}

/// How a checkpoint was made (`perspnet.json`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Checkpoint {
    /// The network.
    pub config: PerspNetConfig,
    /// Topology source (the vertex UVs come from it).
    pub topology: String,
    /// Epochs run.
    pub epochs: usize,
    /// Batch size.
    pub batch: usize,
    /// Learning rate.
    pub learning_rate: f64,
    /// Share of the steps at the full learning rate before the linear decay (older
    /// checkpoints: 1, a constant rate).
    #[serde(default = "constant_rate")]
    pub lr_hold: f64,
    /// Training-time augmentation (older checkpoints: none).
    #[serde(default = "no_augmentation")]
    pub augmentation: Augmentation,
    /// Whether the loss started at the lowered weights.
    #[serde(default)]
    pub lowered_start: bool,
    /// The step budget, when the run had one (`train --steps`).
    #[serde(default)]
    pub max_steps: Option<usize>,
    /// Seed.
    pub seed: u64,
    /// The loss weights when this checkpoint was written (the official schedule lowers
    /// them as `L_corr` falls; a resumed run goes on from these). Older checkpoints:
    /// none, the run's starting weights.
    #[serde(default)]
    pub loss_weights: Option<LossWeights>,
    /// Epochs finished when this checkpoint was written (`epochs` once training is
    /// done; a checkpoint is written after every epoch).
    #[serde(default)]
    pub epochs_done: usize,
    /// Training examples.
    pub examples: usize,
    /// Shards the examples were taken from, one at a time (1: all in memory; `train
    /// --stream`: the dataset's shards with examples of the split). The sample order
    /// depends on it, so a resumed run must match.
    #[serde(default = "one_shard")]
    pub example_shards: usize,
    /// Steps run.
    pub steps: usize,
    /// Total loss of the first and last step (NaN, written `null`, without steps).
    #[serde(deserialize_with = "nan_if_null")]
    pub first_loss: f32,
    /// Total loss of the last step.
    #[serde(deserialize_with = "nan_if_null")]
    pub last_loss: f32,
    /// The weights file this model was imported from (`import-weights`), if it was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub imported_from: Option<String>,
}

/// A loss written as `null` (JSON has no NaN) reads back as NaN.
fn nan_if_null<'de, D: serde::Deserializer<'de>>(d: D) -> std::result::Result<f32, D::Error> {
    Ok(Option::<f32>::deserialize(d)?.unwrap_or(f32::NAN))
}

fn one_shard() -> usize {
    1
}

fn constant_rate() -> f64 {
    1.0
}

fn no_augmentation() -> Augmentation {
    Augmentation::NONE
}

/// Training options.
#[derive(Clone, Debug)]
pub struct TrainOptions {
    /// Network.
    pub config: PerspNetConfig,
    /// Passes over the examples.
    pub epochs: usize,
    /// A step budget instead: stop after this many steps (the last epoch may end part
    /// way; the schedule is scaled to the budget). `epochs` must cover it.
    pub max_steps: Option<usize>,
    /// Examples per step.
    pub batch: usize,
    /// AdamW learning rate (the official Adam uses 1e-4 at batch 32 on GPUs; small
    /// CPU runs learn faster with more).
    pub learning_rate: f64,
    /// Share of the steps at the full rate; the rate then falls linearly to zero
    /// ([`learning_rate_at`]).
    pub lr_hold: f64,
    /// Augmentation drawn per example and step.
    pub augmentation: Augmentation,
    /// Start the loss at the weights the official schedule lowers to once `L_corr`
    /// falls below 0.1 (KL and segmentation 0.01) instead of waiting for a batch to get
    /// there: short CPU runs otherwise spend most steps with the KL term dominating.
    pub lowered_start: bool,
    /// Seed of the weights and the shuffling.
    pub seed: u64,
    /// Checkpoint folder.
    pub output: PathBuf,
    /// Continue from the checkpoint in `output` (written after each epoch) when there is
    /// one made with the same settings: its weights, Adam's moments (`adam.safetensors`),
    /// the loss weights, its loss log, the same sample order, augmentation and
    /// learning-rate schedule from the next epoch on, so the resumed run is step for
    /// step the uninterrupted one. (A checkpoint written before the optimiser state
    /// was stored has no `adam.safetensors`: its moments restart from zero.)
    pub resume: bool,
}

impl TrainOptions {
    /// Checks the options a caller (the CLI, or code using the library) can get wrong:
    /// at least one epoch and one sample per batch, a positive finite learning rate, a
    /// hold fraction in [0, 1], a colour jitter in [0, 1], no `--lowered-start` with the
    /// paper's loss (its weights are fixed).
    pub fn validate(&self) -> Result<()> {
        let bad = |what: &str, why: String| Err(Error::invalid(what, why));
        if self.epochs == 0 {
            return bad("--epochs", "must be at least 1".into());
        }
        if self.batch == 0 {
            return bad("--batch", "must be at least 1".into());
        }
        if self.max_steps == Some(0) {
            return bad("--steps", "must be at least 1".into());
        }
        if !(self.learning_rate.is_finite() && self.learning_rate > 0.0) {
            return bad(
                "--lr",
                format!("{} is not a positive learning rate", self.learning_rate),
            );
        }
        if !(0.0..=1.0).contains(&self.lr_hold) {
            return bad(
                "--lr-hold",
                format!("{} is not a fraction in [0, 1]", self.lr_hold),
            );
        }
        if self.lowered_start && self.config.loss == crate::LossVariant::Paper {
            return bad(
                "--lowered-start",
                "lowers the official schedule's weights; --loss paper holds the paper's fixed weights".into(),
            );
        }
        if !(0.0..=1.0).contains(&self.augmentation.colour) {
            return bad(
                "--colour-jitter",
                format!("{} is not in [0, 1]", self.augmentation.colour),
            );
        }
        Ok(())
    }
}

/// One step's losses (weighted, as summed into the total).
#[derive(Clone, Copy, Debug, Serialize)]
pub struct StepLoss {
    /// Step number (0-based).
    pub step: usize,
    /// Epoch.
    pub epoch: usize,
    /// Total.
    pub total: f32,
    /// Correspondence smooth L1.
    pub corr: f32,
    /// Shape L1.
    pub shape: f32,
    /// KL to the barycentric targets.
    pub kl: f32,
    /// Entropy.
    pub entropy: f32,
    /// Segmentation.
    pub seg: f32,
}

/// Optimiser steps of a run: `epochs` passes over `examples` in batches of `batch`
/// (the last batch of an epoch may be short).
pub fn total_steps(examples: usize, epochs: usize, batch: usize) -> usize {
    epochs * examples.div_ceil(batch.max(1))
}

/// Optimiser steps of one pass over `source`: its shards' examples in batches of
/// `batch`, a shard's last batch possibly short (for one shard, [`total_steps`] of one
/// epoch).
pub fn steps_per_epoch<S: ExampleShards + ?Sized>(source: &S, batch: usize) -> usize {
    (0..source.shards())
        .map(|k| source.shard_len(k).div_ceil(batch.max(1)))
        .sum()
}

/// Fisher-Yates with our own generator: the same order for a seed everywhere.
fn shuffle(order: &mut [usize], rng: &mut Rng) {
    for i in (1..order.len()).rev() {
        order.swap(i, rng.below(i as u64 + 1) as usize);
    }
}

/// Trains a fresh network on `examples` (in memory, or [`ShardedExamples`] loaded one
/// shard at a time: each epoch visits the shards in a shuffled order and each shard's
/// examples in a shuffled order); writes the checkpoint folder. `on_step` sees every
/// step's losses (for progress).
pub fn train<S: ExampleShards + ?Sized>(
    examples: &S,
    topology: &FaceTopology,
    options: &TrainOptions,
    on_step: &dyn Fn(&StepLoss),
) -> Result<(Checkpoint, Vec<StepLoss>)> {
    let cfg = &options.config;
    options.validate()?;
    if examples.total() == 0 {
        return Err(Error::invalid("train", "no training examples"));
    }
    let device = Device::Cpu;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &device);
    let net = Network::new(cfg, &vertex_uv(topology, &device)?, vb)
        .map_err(|e| candle_err("network", e))?;
    reseed(&varmap, options.seed, cfg.init_std).map_err(|e| candle_err("initial weights", e))?;
    let epoch_steps = options.epochs * steps_per_epoch(examples, options.batch);
    let total_steps = match options.max_steps {
        Some(n) if n > epoch_steps => {
            return Err(Error::invalid(
                "train",
                format!("{n} steps need more than {} epochs", options.epochs),
            ));
        }
        Some(n) => n,
        None => epoch_steps,
    };
    let mut checkpoint = Checkpoint {
        config: cfg.clone(),
        topology: topology.source.clone(),
        epochs: options.epochs,
        batch: options.batch,
        learning_rate: options.learning_rate,
        lr_hold: options.lr_hold,
        augmentation: options.augmentation,
        lowered_start: options.lowered_start,
        max_steps: options.max_steps,
        seed: options.seed,
        loss_weights: None,
        epochs_done: 0,
        examples: examples.total(),
        example_shards: examples.shards(),
        steps: 0,
        first_loss: f32::NAN,
        last_loss: f32::NAN,
        imported_from: None,
    };
    let mut log = Vec::new();
    let mut start_epoch = 0;
    let mut opt = Adam::new(named_trainable_vars(&varmap), options.learning_rate)
        .map_err(|e| candle_err("optimizer", e))?;
    let mut loss = PerspNetLoss::for_config(cfg);
    if options.lowered_start {
        // The weights the official schedule reaches once L_corr < 0.1.
        loss.weights.update_schedule(0.05);
    }
    if options.resume && options.output.join("perspnet.json").exists() {
        let resumed = resume_from(&options.output, &checkpoint, &varmap, &mut opt)?;
        start_epoch = resumed.checkpoint.epochs_done;
        log = resumed.log;
        if let Some(w) = resumed.checkpoint.loss_weights {
            loss.weights = w;
        }
        checkpoint.epochs_done = start_epoch;
        checkpoint.steps = log.len();
        checkpoint.first_loss = log.first().map_or(f32::NAN, |s| s.total);
        checkpoint.last_loss = log.last().map_or(f32::NAN, |s| s.total);
    }
    let mut rng = Rng::new(options.seed);
    let mut shard_order: Vec<usize> = (0..examples.shards()).collect();
    let mut orders: Vec<Vec<usize>> = (0..examples.shards())
        .map(|k| (0..examples.shard_len(k)).collect())
        .collect();
    for epoch in 0..options.epochs {
        // The shards' order, then each shard's samples, from our generator (replayed for
        // the epochs a resumed run skips). With one shard this draws exactly what a
        // single shuffle of all examples does.
        shuffle(&mut shard_order, &mut rng);
        for &k in &shard_order {
            shuffle(&mut orders[k], &mut rng);
        }
        if epoch < start_epoch {
            continue;
        }
        if log.len() >= total_steps {
            // A step budget spent before the last epoch: nothing more to write.
            break;
        }
        // The next shard is read on its own thread while this one trains.
        std::thread::scope(|scope| -> Result<()> {
            let mut next = None;
            for (pos, &k) in shard_order.iter().enumerate() {
                if log.len() >= total_steps {
                    break;
                }
                let shard = match next.take() {
                    Some(h) => std::thread::ScopedJoinHandle::join(h).expect("shard reader")?,
                    None => examples.load(k)?,
                };
                // Read ahead only when the budget reaches past this shard (no read of
                // a shard the run will not train on).
                let this_shard_steps = orders[k].len().div_ceil(options.batch.max(1));
                if let Some(&after) = shard_order.get(pos + 1)
                    && log.len() + this_shard_steps < total_steps
                {
                    next = Some(scope.spawn(move || examples.load(after)));
                }
                for chunk in orders[k].chunks(options.batch.max(1)) {
                    if log.len() >= total_steps {
                        break;
                    }
                    let refs: Vec<&Example> = chunk.iter().map(|&i| &shard[i]).collect();
                    // Each step's augmentation has its own stream: the same views for a seed
                    // whatever else changes.
                    let mut aug_rng = Rng::for_stream(options.seed, 1 << 40 | log.len() as u64);
                    let views: Vec<View> = refs
                        .iter()
                        .map(|e| e.augmented_view(cfg.points, &options.augmentation, &mut aug_rng))
                        .collect();
                    let b = batch(&refs, &views, cfg, &device)?;
                    if let Network::PerspNet(net) = &net {
                        net.seed_dropout(
                            Rng::for_stream(options.seed, 2 << 40 | log.len() as u64).next_u64(),
                        );
                    }
                    opt.learning_rate = learning_rate_at(
                        log.len(),
                        total_steps,
                        options.learning_rate,
                        options.lr_hold,
                    );
                    let step = (|| -> candle_core::Result<StepLoss> {
                        let net = match &net {
                            Network::PerspNet(net) => net,
                            Network::Direct(direct) => {
                                let out = direct.forward(&b.image, true)?;
                                let target = b.direct.as_ref().expect("direct targets");
                                let (total, rot, trans) = crate::direct::direct_loss(&out, target)?;
                                opt.backward_step(&total)?;
                                let v = |t: &Tensor| t.to_scalar::<f32>();
                                return Ok(StepLoss {
                                    step: log.len(),
                                    epoch,
                                    total: v(&total)?,
                                    corr: v(&rot)?,
                                    shape: v(&trans)?,
                                    kl: 0.0,
                                    entropy: 0.0,
                                    seg: 0.0,
                                });
                            }
                        };
                        let out = net.forward(&b.image, &b.choose, true)?;
                        let terms = loss.compute(
                            &out,
                            &LossTargets {
                                nocs: &b.nocs,
                                model: &b.model,
                                seg_mask: &b.mask,
                                corr: &b.corr,
                                uv_map: None,
                            },
                        )?;
                        opt.backward_step(&terms.total)?;
                        let v = terms.values()?;
                        Ok(StepLoss {
                            step: log.len(),
                            epoch,
                            total: v[0],
                            corr: v[1],
                            shape: v[2],
                            kl: v[3],
                            entropy: v[4],
                            seg: v[5],
                        })
                    })()
                    .map_err(|e| candle_err("training step", e))?;
                    if !step.total.is_finite() {
                        return Err(Error::invalid(
                            "train",
                            format!(
                                "the loss is {} at step {}: lower --lr",
                                step.total, step.step
                            ),
                        ));
                    }
                    on_step(&step);
                    log.push(step);
                }
            }
            Ok(())
        })?;
        checkpoint.epochs_done = epoch + 1;
        checkpoint.steps = log.len();
        checkpoint.first_loss = log.first().map_or(f32::NAN, |s| s.total);
        checkpoint.last_loss = log.last().map_or(f32::NAN, |s| s.total);
        checkpoint.loss_weights = Some(loss.weights);
        write_checkpoint(&options.output, &checkpoint, &varmap, &opt, &log)?;
    }
    Ok((checkpoint, log))
}

/// What a resumed run picks up besides the weights.
struct Resumed {
    checkpoint: Checkpoint,
    log: Vec<StepLoss>,
}

/// Loads the checkpoint in `dir` into `varmap` and `opt` for a resumed run with the
/// settings of `wanted`; returns it with its loss log.
fn resume_from(
    dir: &Path,
    wanted: &Checkpoint,
    varmap: &VarMap,
    opt: &mut Adam,
) -> Result<Resumed> {
    verify_checkpoint(dir)?;
    let p = dir.join("perspnet.json");
    let text = std::fs::read_to_string(&p).map_err(|e| Error::io(&p, e))?;
    let old: Checkpoint =
        serde_json::from_str(&text).map_err(|e| Error::format(&p, e.to_string()))?;
    let same = |a: &Checkpoint| {
        let mut a = a.clone();
        a.epochs_done = 0;
        a.steps = 0;
        a.first_loss = f32::NAN;
        a.last_loss = f32::NAN;
        a.loss_weights = None;
        serde_json::to_value(&a).ok()
    };
    if same(&old) != same(wanted) {
        return Err(Error::format(
            &p,
            "made with other settings (config, data, epochs, batch, rate, augmentation or seed): resume only with the same options, or choose another --output",
        ));
    }
    let w = dir.join("model.safetensors");
    load_weights(varmap, &mut open_weights(&w)?, &w)?;
    let adam = dir.join(ADAM_FILE);
    if adam.exists() {
        opt.load(&adam)
            .map_err(|e| Error::format(&adam, e.to_string()))?;
        if opt.steps() != old.steps {
            return Err(Error::format(
                &adam,
                format!(
                    "{} optimiser steps but the checkpoint ran {}",
                    opt.steps(),
                    old.steps
                ),
            ));
        }
    }
    let csv = dir.join("loss.csv");
    let text = std::fs::read_to_string(&csv).map_err(|e| Error::io(&csv, e))?;
    let mut log = Vec::new();
    for (n, line) in text.lines().enumerate().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        let num = |i: usize| -> Result<f32> {
            f.get(i)
                .and_then(|v| v.parse().ok())
                .ok_or_else(|| Error::format(&csv, format!("line {}: bad field {i}", n + 1)))
        };
        log.push(StepLoss {
            step: num(0)? as usize,
            epoch: num(1)? as usize,
            total: num(2)?,
            corr: num(3)?,
            shape: num(4)?,
            kl: num(5)?,
            entropy: num(6)?,
            seg: num(7)?,
        });
    }
    if log.len() != old.steps {
        return Err(Error::format(
            &csv,
            format!(
                "{} rows but the checkpoint ran {} steps",
                log.len(),
                old.steps
            ),
        ));
    }
    Ok(Resumed {
        checkpoint: old,
        log,
    })
}

/// Redraws every randomly initialised variable from our seeded generator (candle's
/// CPU generator cannot be seeded), so the initial weights, and the whole run, follow
/// from the seed: N(0, `init_std`) for convolution and linear weights, N(1, `init_std`)
/// for batch-norm weights (the official `init_weights`). Which of the two a variable
/// is comes from the mean candle's draw gave it (rounded to 0 or 1); the draw's own
/// spread is not used, as it varies from run to run. Constant variables (biases,
/// batch-norm statistics) are left as they are.
pub fn reseed(varmap: &VarMap, seed: u64, init_std: f64) -> candle_core::Result<()> {
    let data = varmap.data().lock().expect("varmap lock");
    let mut named: Vec<(&String, &candle_core::Var)> = data
        .iter()
        .filter(|(k, _)| !k.contains("running_"))
        .collect();
    named.sort_by(|a, b| a.0.cmp(b.0));
    for (i, (_, var)) in named.into_iter().enumerate() {
        let values = var.as_tensor().flatten_all()?.to_vec1::<f32>()?;
        let n = values.len() as f64;
        let mean = values.iter().map(|&v| v as f64).sum::<f64>() / n;
        let var_ = values
            .iter()
            .map(|&v| (v as f64 - mean).powi(2))
            .sum::<f64>()
            / n;
        if var_ <= 0.0 {
            continue;
        }
        let mut rng = Rng::for_stream(seed, i as u64);
        let (mean, sd) = (mean.round(), init_std);
        let fresh: Vec<f32> = (0..values.len())
            .map(|_| (mean + sd * rng.normal()) as f32)
            .collect();
        var.set(&Tensor::from_vec(fresh, var.shape(), var.device())?)?;
    }
    Ok(())
}

/// Writes `path` through `save` under a temporary name in the same folder, then renames.
fn save_renamed(path: &Path, save: &dyn Fn(&Path) -> candle_core::Result<()>) -> Result<()> {
    let name = path
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    let tmp = path.with_file_name(format!(".{name}.tmp-{}", std::process::id()));
    if let Err(e) = save(&tmp) {
        let _ = std::fs::remove_file(&tmp);
        return Err(Error::format(path, e.to_string()));
    }
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}

/// The optimiser's state in a checkpoint folder ([`Adam::save`]).
pub const ADAM_FILE: &str = "adam.safetensors";

fn write_checkpoint(
    dir: &Path,
    c: &Checkpoint,
    varmap: &VarMap,
    opt: &Adam,
    log: &[StepLoss],
) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    // Weights and optimiser state first, each under a temporary name then renamed;
    // perspnet.json last, so a folder whose json says N steps has both files of step N.
    save_renamed(&dir.join("model.safetensors"), &|p| varmap.save(p))?;
    save_renamed(&dir.join(ADAM_FILE), &|p| opt.save(p))?;
    // The direct model's two terms take the first two loss columns.
    let mut csv = String::from(match c.config.architecture {
        Architecture::PerspNet => "step,epoch,total,corr,shape,kl,entropy,seg\n",
        Architecture::Direct => "step,epoch,total,rotation,translation,unused,unused,unused\n",
    });
    for s in log {
        csv += &format!(
            "{},{},{},{},{},{},{},{}\n",
            s.step, s.epoch, s.total, s.corr, s.shape, s.kl, s.entropy, s.seg
        );
    }
    arkit_data::atomic_file::write_bytes(&dir.join("loss.csv"), csv.as_bytes())?;
    let json = serde_json::to_string_pretty(c).expect("checkpoint json");
    arkit_data::atomic_file::write_bytes(&dir.join("perspnet.json"), json.as_bytes())?;
    // Last, the record of what was written: a folder whose files do not all match it
    // (a run stopped between two renames) is refused by --resume.
    write_checkpoint_record(dir)
}

/// The record a checkpoint folder's files are checked against on `train --resume`:
/// written last, after every other file, it holds the size and SHA-256 of each.
pub const CHECKPOINT_RECORD: &str = "checkpoint.json";

/// The files of a checkpoint folder that [`CHECKPOINT_RECORD`] covers.
const CHECKPOINT_FILES: [&str; 4] = ["model.safetensors", ADAM_FILE, "loss.csv", "perspnet.json"];

/// One file of a checkpoint, as its record holds it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
struct RecordedFile {
    name: String,
    bytes: u64,
    sha256: String,
}

#[derive(Debug, Serialize, Deserialize)]
struct CheckpointRecord {
    files: Vec<RecordedFile>,
}

/// The size and SHA-256 (lowercase hex) of `path`, read in pieces.
fn file_digest(path: &Path) -> Result<(u64, String)> {
    use sha2::Digest;
    use std::io::Read;
    let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut h = sha2::Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    let mut n = 0u64;
    loop {
        let k = f.read(&mut buf).map_err(|e| Error::io(path, e))?;
        if k == 0 {
            break;
        }
        h.update(&buf[..k]);
        n += k as u64;
    }
    let hex = h.finalize().iter().map(|b| format!("{b:02x}")).collect();
    Ok((n, hex))
}

fn write_checkpoint_record(dir: &Path) -> Result<()> {
    let mut files = Vec::new();
    for name in CHECKPOINT_FILES {
        let (bytes, sha256) = file_digest(&dir.join(name))?;
        files.push(RecordedFile {
            name: name.to_string(),
            bytes,
            sha256,
        });
    }
    let json = serde_json::to_string_pretty(&CheckpointRecord { files }).expect("record json");
    arkit_data::atomic_file::write_bytes(&dir.join(CHECKPOINT_RECORD), json.as_bytes())
}

/// Checks that every file of the checkpoint in `dir` is the one its record
/// ([`CHECKPOINT_RECORD`]) describes; the error names the first that differs and how.
/// Nothing in the folder is changed.
pub fn verify_checkpoint(dir: &Path) -> Result<()> {
    let torn = "the checkpoint is torn (a run was stopped while writing it) and is left as it is: train into another --output, or run again without --resume to start over";
    let rec = dir.join(CHECKPOINT_RECORD);
    let meta = std::fs::metadata(&rec).map_err(|e| {
        Error::format(
            &rec,
            format!("cannot be read ({e}): without this record of the checkpoint's files, it cannot be told whole; {torn}"),
        )
    })?;
    if meta.len() > 1 << 16 {
        return Err(Error::format(
            &rec,
            format!("{} bytes: not a checkpoint record", meta.len()),
        ));
    }
    let text = std::fs::read_to_string(&rec).map_err(|e| Error::io(&rec, e))?;
    let record: CheckpointRecord = serde_json::from_str(&text)
        .map_err(|e| Error::format(&rec, format!("not a checkpoint record: {e}")))?;
    for name in CHECKPOINT_FILES {
        let Some(want) = record.files.iter().find(|f| f.name == name) else {
            return Err(Error::format(&rec, format!("does not list {name}")));
        };
        let p = dir.join(name);
        let (bytes, sha256) = match std::fs::metadata(&p) {
            Ok(_) => file_digest(&p)?,
            Err(e) => {
                return Err(Error::format(
                    &p,
                    format!("missing ({e}), but {CHECKPOINT_RECORD} records it; {torn}"),
                ));
            }
        };
        if bytes != want.bytes {
            return Err(Error::format(
                &p,
                format!(
                    "{bytes} bytes, but {CHECKPOINT_RECORD} records {} for it: {torn}",
                    want.bytes
                ),
            ));
        }
        if sha256 != want.sha256 {
            return Err(Error::format(
                &p,
                format!(
                    "its SHA-256 is {sha256}, but {CHECKPOINT_RECORD} records {} (same size, other content): {torn}",
                    want.sha256
                ),
            ));
        }
    }
    Ok(())
}

/// Reads a PyTorch `state_dict` (a `torch.save` zip, or the safetensors file
/// [`export_weights`] writes) of the official network with `config`'s shapes into a new
/// model folder `output` (`perspnet.json` and `model.safetensors`, which `predict
/// --model` reads). Every tensor must match by name and shape; otherwise nothing is
/// written and the error lists the missing, extra and misshapen ones.
pub fn import_weights(
    file: &Path,
    config: &PerspNetConfig,
    topology: &FaceTopology,
    output: &Path,
) -> Result<Checkpoint> {
    use crate::weights::{WeightError, WeightFile};
    if config.architecture == Architecture::Direct {
        return Err(Error::invalid(
            "--config",
            "the direct baseline is not the official network: its weights have no PyTorch counterpart to import",
        ));
    }
    let weights = WeightFile::open(file).map_err(|e| Error::format(file, e.to_string()))?;
    let device = Device::Cpu;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &device);
    PerspNet::new(config, &vertex_uv(topology, &device)?, vb)
        .map_err(|e| candle_err("network", e))?;
    let steps = weights.load_into(&varmap).map_err(|e| match e {
        WeightError::Mismatch(m) => Error::format(
            file,
            format!("does not match the network of this --config: {m}"),
        ),
        WeightError::Read(m) => Error::format(file, m),
    })?;
    let checkpoint = Checkpoint {
        config: config.clone(),
        topology: topology.source.clone(),
        epochs: 0,
        batch: 0,
        learning_rate: 0.0,
        lr_hold: 1.0,
        augmentation: Augmentation::NONE,
        lowered_start: false,
        max_steps: None,
        seed: 0,
        loss_weights: None,
        epochs_done: 0,
        examples: 0,
        example_shards: 1,
        steps: steps.max(0) as usize,
        first_loss: f32::NAN,
        last_loss: f32::NAN,
        imported_from: Some(file.display().to_string()),
    };
    std::fs::create_dir_all(output).map_err(|e| Error::io(output, e))?;
    save_renamed(&output.join("model.safetensors"), &|p| varmap.save(p))?;
    let json = serde_json::to_string_pretty(&checkpoint).expect("checkpoint json");
    arkit_data::atomic_file::write_bytes(&output.join("perspnet.json"), json.as_bytes())?;
    Ok(checkpoint)
}

/// Writes a model folder's weights as the official network's `state_dict` in a
/// safetensors file (official names and shapes, with every batch norm's
/// `num_batches_tracked`, set to the model's training steps), which PyTorch loads with
/// `load_state_dict(safetensors.torch.load_file(path), strict=True)`. Returns the
/// number of entries written.
pub fn export_weights(model_dir: &Path, output: &Path) -> Result<usize> {
    let p = model_dir.join("perspnet.json");
    let text = std::fs::read_to_string(&p).map_err(|e| Error::io(&p, e))?;
    let checkpoint: Checkpoint =
        serde_json::from_str(&text).map_err(|e| Error::format(&p, e.to_string()))?;
    let cfg = &checkpoint.config;
    if cfg.architecture == Architecture::Direct {
        return Err(Error::format(
            &p,
            "a direct-baseline model: the official network has no such head, so there is no state_dict to export",
        ));
    }
    let device = Device::Cpu;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &device);
    // The vertex UV table is not a weight: any table of the right size builds the network.
    let uv = crate::model::synthetic_vertex_uv(cfg.vertices, &device)
        .map_err(|e| candle_err("network", e))?;
    PerspNet::new(cfg, &uv, vb).map_err(|e| candle_err("network", e))?;
    let w = model_dir.join("model.safetensors");
    load_weights(&varmap, &mut open_weights(&w)?, &w)?;
    let entries = crate::weights::export_state_dict(&varmap, checkpoint.steps as i64)
        .map_err(|e| candle_err("export", e))?;
    let n = entries.len();
    let map: HashMap<String, Tensor> = entries.into_iter().collect();
    if let Some(dir) = output.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    save_renamed(output, &|p| candle_core::safetensors::save(&map, p))?;
    Ok(n)
}

/// Writes `predict --dump`'s npz: for each sample `KEY` (`subject/action/image`),
/// `KEY/image` (`3 x S x S` f32, the normalised crop), `KEY/choose` (`M` int64 pixel
/// indices `y * S + x`), `KEY/seg_logits` (`2 x S x S`), `KEY/uv_map` (`3 x S x S`),
/// `KEY/assignment` (`M x V`, rows summing to 1), `KEY/points` (`M X`, `M x 3`) and
/// `KEY/vertices` (X, `V x 3`), the last three in the UV map's units (9 x canonical);
/// and once, `vertex_uv` (`V x 2`, where X is read from the UV map: `grid_sample` at
/// `2 uv - 1`, `align_corners=False`).
pub fn write_dump(
    path: &Path,
    cfg: &PerspNetConfig,
    topology: &FaceTopology,
    dump: &[(arkit_data::release::SampleKey, RawOutputs)],
) -> Result<()> {
    use arkit_data::npy::{NpyArray, NpzCompression, write_npz};
    let (s, m, v) = (cfg.input_size, cfg.points, cfg.vertices);
    let uv: Vec<f32> = topology.uv[..v].iter().flat_map(|t| [t[0], t[1]]).collect();
    let mut arrays: Vec<(String, NpyArray)> =
        vec![("vertex_uv".into(), NpyArray::from_f32(vec![v, 2], uv)?)];
    for (key, r) in dump {
        let k = key.to_string();
        arrays.push((
            format!("{k}/image"),
            NpyArray::from_f32(vec![3, s, s], r.image.clone())?,
        ));
        arrays.push((
            format!("{k}/choose"),
            NpyArray::from_i64(vec![m], r.choose.iter().map(|&c| c as i64).collect())?,
        ));
        arrays.push((
            format!("{k}/seg_logits"),
            NpyArray::from_f32(vec![2, s, s], r.seg_logits.clone())?,
        ));
        arrays.push((
            format!("{k}/uv_map"),
            NpyArray::from_f32(vec![3, s, s], r.uv_map.clone())?,
        ));
        arrays.push((
            format!("{k}/assignment"),
            NpyArray::from_f32(vec![m, v], r.assignment.clone())?,
        ));
        arrays.push((
            format!("{k}/points"),
            NpyArray::from_f32(vec![m, 3], r.points.clone())?,
        ));
        arrays.push((
            format!("{k}/vertices"),
            NpyArray::from_f32(vec![v, 3], r.vertices.clone())?,
        ));
    }
    let members: Vec<(&str, &NpyArray)> = arrays.iter().map(|(k, a)| (k.as_str(), a)).collect();
    let mut buf = std::io::Cursor::new(Vec::new());
    write_npz(&mut buf, &members, NpzCompression::Deflated)?;
    arkit_data::atomic_file::write_bytes(path, buf.get_ref())
}

/// A trained network loaded from a checkpoint folder.
pub struct TrainedModel {
    /// How it was made.
    pub checkpoint: Checkpoint,
    /// The network.
    pub net: Network,
    /// Its variables.
    pub varmap: VarMap,
}

/// Loads a checkpoint folder written by [`train`].
pub fn load(dir: &Path, topology: &FaceTopology) -> Result<TrainedModel> {
    let p = dir.join("perspnet.json");
    let text = std::fs::read_to_string(&p).map_err(|e| Error::io(&p, e))?;
    let checkpoint: Checkpoint =
        serde_json::from_str(&text).map_err(|e| Error::format(&p, e.to_string()))?;
    if checkpoint.topology != topology.source {
        return Err(Error::invalid(
            "--resources",
            format!(
                "the model was trained with the topology '{}', not '{}'",
                checkpoint.topology, topology.source
            ),
        ));
    }
    let w = dir.join("model.safetensors");
    let mut st = open_weights(&w)?;
    model_from_parts(checkpoint, &mut st, &w, topology)
}

/// Where the shipped model's folder is in the repository: a `tiny` PerspNet trained by
/// `train` on synthetic data (docs/train.md, "The shipped model", has the commands and
/// seed that made it), its weights stored as float16 (`half-model`).
pub const SHIPPED_MODEL_DIR: &str = "models/tiny-synthetic";

/// The shipped model's `perspnet.json` and weights, compiled into the binary so that
/// `demo` needs no path to find them.
const SHIPPED_JSON: &str = include_str!("../../../../models/tiny-synthetic/perspnet.json");
const SHIPPED_WEIGHTS: &[u8] =
    include_bytes!("../../../../models/tiny-synthetic/model.safetensors");

/// How the shipped model was made (its `perspnet.json`).
pub fn shipped_checkpoint() -> Result<Checkpoint> {
    let p = Path::new(SHIPPED_MODEL_DIR).join("perspnet.json");
    serde_json::from_str(SHIPPED_JSON).map_err(|e| Error::format(&p, e.to_string()))
}

/// The shipped model ([`SHIPPED_MODEL_DIR`]), from the copy compiled into the binary;
/// it was trained on the built-in face's topology, and another `topology` is refused
/// as [`load`] refuses it.
pub fn shipped_model(topology: &FaceTopology) -> Result<TrainedModel> {
    let dir = Path::new(SHIPPED_MODEL_DIR);
    let checkpoint = shipped_checkpoint()?;
    if checkpoint.topology != topology.source {
        return Err(Error::invalid(
            "--resources",
            format!(
                "the shipped model was trained with the topology '{}', not '{}'",
                checkpoint.topology, topology.source
            ),
        ));
    }
    let w = dir.join("model.safetensors");
    let mut st =
        crate::safetensors_file::from_bytes(SHIPPED_WEIGHTS).map_err(|e| Error::format(&w, e))?;
    model_from_parts(checkpoint, &mut st, &w, topology)
}

/// The network of `checkpoint` with the weights of the safetensors file `st` (read
/// from `file`, named in errors), float32 or float16 ([`load_weights`]).
fn model_from_parts<R: std::io::Read + std::io::Seek>(
    checkpoint: Checkpoint,
    st: &mut SafetensorsFile<R>,
    file: &Path,
    topology: &FaceTopology,
) -> Result<TrainedModel> {
    let device = Device::Cpu;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &device);
    let net = Network::new(&checkpoint.config, &vertex_uv(topology, &device)?, vb)
        .map_err(|e| candle_err("network", e))?;
    load_weights(&varmap, st, file)?;
    Ok(TrainedModel {
        checkpoint,
        net,
        varmap,
    })
}

/// Opens the safetensors file `path` ([`crate::safetensors_file`]): its header is read
/// and checked against the file's length; no tensor data is read yet.
pub fn open_weights(path: &Path) -> Result<SafetensorsFile<std::io::BufReader<std::fs::File>>> {
    if let Err(e) = std::fs::metadata(path) {
        return Err(Error::io(path, e));
    }
    crate::safetensors_file::open(path).map_err(|e| Error::format(path, e))
}

/// Sets every variable of `varmap` from the safetensors file `st` (read from `file`,
/// which errors name), matched by name and shape and converted to float32: a model
/// folder may hold float32 weights (`train`) or float16 ones ([`write_half_model`]).
/// Every name, shape and type in the header is checked before any tensor is read; a
/// missing, misshapen, extra or non-float tensor is an error that names it. The
/// tensors are then read one at a time.
pub fn load_weights<R: std::io::Read + std::io::Seek>(
    varmap: &VarMap,
    st: &mut SafetensorsFile<R>,
    file: &Path,
) -> Result<()> {
    let data = varmap.data().lock().expect("varmap lock");
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let header: HashMap<&str, &crate::safetensors_file::Entry> =
        st.entries().iter().map(|e| (e.name.as_str(), e)).collect();
    for name in &names {
        let var = &data[*name];
        let e = header
            .get(name.as_str())
            .ok_or_else(|| Error::format(file, format!("no tensor {name}")))?;
        if e.shape != var.dims() {
            return Err(Error::format(
                file,
                format!("{name} is {:?}, the network has {:?}", e.shape, var.dims()),
            ));
        }
        if !matches!(e.dtype, DType::F16 | DType::BF16 | DType::F32 | DType::F64) {
            return Err(Error::format(
                file,
                format!("{name} is {:?}, not floating point", e.dtype),
            ));
        }
    }
    let mut extra: Vec<&str> = header
        .keys()
        .filter(|k| !data.contains_key(**k))
        .copied()
        .collect();
    if !extra.is_empty() {
        extra.sort();
        return Err(Error::format(
            file,
            format!("tensors the network does not have: {extra:?}"),
        ));
    }
    for name in names {
        let var = &data[name];
        let t = st
            .read(name)
            .and_then(|t| t.to_dtype(DType::F32).map_err(|e| e.to_string()))
            .map_err(|e| Error::format(file, format!("{name}: {e}")))?;
        var.set(&t)
            .map_err(|e| Error::format(file, format!("{name}: {e}")))?;
    }
    Ok(())
}

/// Copies the model folder `model_dir` (`perspnet.json`, `model.safetensors` and
/// `loss.csv` when there is one) to `output` with its weights stored as float16: half
/// the bytes, read back as float32 by [`load`] (each weight then differs from the
/// original by at most its float16 rounding, a relative 2^-11). Returns the bytes of
/// the weights file written.
pub fn write_half_model(model_dir: &Path, output: &Path) -> Result<u64> {
    let p = model_dir.join("perspnet.json");
    let json = std::fs::read_to_string(&p).map_err(|e| Error::io(&p, e))?;
    let checkpoint =
        serde_json::from_str::<Checkpoint>(&json).map_err(|e| Error::format(&p, e.to_string()))?;
    // The weights are read into the network of the checkpoint's config, so that their
    // names and shapes are checked before any data is read.
    let device = Device::Cpu;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &device);
    let uv = crate::model::synthetic_vertex_uv(checkpoint.config.vertices, &device)
        .map_err(|e| candle_err("network", e))?;
    Network::new(&checkpoint.config, &uv, vb).map_err(|e| candle_err("network", e))?;
    let w = model_dir.join("model.safetensors");
    load_weights(&varmap, &mut open_weights(&w)?, &w)?;
    let half = varmap
        .data()
        .lock()
        .expect("varmap lock")
        .iter()
        .map(|(k, v)| Ok((k.clone(), v.as_tensor().to_dtype(DType::F16)?)))
        .collect::<candle_core::Result<HashMap<String, Tensor>>>()
        .map_err(|e| Error::format(&w, e.to_string()))?;
    std::fs::create_dir_all(output).map_err(|e| Error::io(output, e))?;
    let out = output.join("model.safetensors");
    save_renamed(&out, &|p| candle_core::safetensors::save(&half, p))?;
    let csv = model_dir.join("loss.csv");
    if csv.exists() {
        let text = std::fs::read(&csv).map_err(|e| Error::io(&csv, e))?;
        arkit_data::atomic_file::write_bytes(&output.join("loss.csv"), &text)?;
    }
    arkit_data::atomic_file::write_bytes(&output.join("perspnet.json"), json.as_bytes())?;
    std::fs::metadata(&out)
        .map(|m| m.len())
        .map_err(|e| Error::io(&out, e))
}

/// What the network predicts for one crop.
#[derive(Clone, Debug)]
pub struct NetworkPrediction {
    /// Predicted face mask over the crop.
    pub mask: Vec<bool>,
    /// The chosen crop pixels.
    pub pixels: Vec<u32>,
    /// The canonical point each chosen pixel shows (`M X / 9`), metres.
    pub points: Vec<[f32; 3]>,
    /// Predicted canonical vertices (`X / 9`), metres.
    pub verts: Vec<f32>,
}

/// Runs the network on one crop (`3 x S x S` normalised): segments the face, samples M
/// pixels from the predicted mask, or from `truth` when given (with wrap-around, from
/// `seed`; every pixel when the mask is empty), and reads the correspondences and the
/// mesh. The returned mask is the predicted one either way.
pub fn predict_crop(
    model: &TrainedModel,
    input: &[f32],
    seed: u64,
    truth: Option<&[bool]>,
) -> Result<NetworkPrediction> {
    predict_crop_raw(model, input, seed, truth, false).map(|(p, _)| p)
}

/// The network's inputs and raw outputs for one crop (`predict --dump`).
#[derive(Clone, Debug)]
pub struct RawOutputs {
    /// The normalised crop as the network sees it, `3 x S x S`.
    pub image: Vec<f32>,
    /// The chosen pixel indices `y * S + x`, `M`.
    pub choose: Vec<u32>,
    /// Segmentation logits `2 x S x S`.
    pub seg_logits: Vec<f32>,
    /// UV position map `3 x S x S` (tanh; 9 x canonical units).
    pub uv_map: Vec<f32>,
    /// The assignment matrix M (softmax over the vertices), `M x V`.
    pub assignment: Vec<f32>,
    /// `M X`, `M x 3`, in the UV map's units (9 x canonical).
    pub points: Vec<f32>,
    /// The vertices X read from the UV map, `V x 3`, in the UV map's units.
    pub vertices: Vec<f32>,
}

/// [`predict_crop`], also returning the raw outputs when `keep_raw`.
pub fn predict_crop_raw(
    model: &TrainedModel,
    input: &[f32],
    seed: u64,
    truth: Option<&[bool]>,
    keep_raw: bool,
) -> Result<(NetworkPrediction, Option<RawOutputs>)> {
    let cfg = &model.checkpoint.config;
    let s = cfg.input_size;
    let device = Device::Cpu;
    let net = model.net.perspnet("predicting correspondences")?;
    let run = || -> candle_core::Result<(NetworkPrediction, Option<RawOutputs>)> {
        let img = Tensor::from_slice(input, (1, 3, s, s), &device)?;
        let dense = net.forward_dense(&img, false)?;
        let logits = dense.seg_logits.squeeze(0)?; // 2 x S x S
        let face = logits
            .get(1)?
            .ge(&logits.get(0)?)?
            .flatten_all()?
            .to_vec1::<u8>()?;
        let mask: Vec<bool> = face.iter().map(|&v| v != 0).collect();
        let sample_from = truth.unwrap_or(&mask);
        let mut candidates: Vec<u32> = (0..sample_from.len() as u32)
            .filter(|&i| sample_from[i as usize])
            .collect();
        if candidates.is_empty() {
            candidates = (0..mask.len() as u32).collect();
        }
        let picks = arkit_data::render::sample_points(candidates.len(), cfg.points, seed);
        let pixels: Vec<u32> = picks.iter().map(|&k| candidates[k as usize]).collect();
        let choose = Tensor::from_slice(&pixels, (1, cfg.points), &device)?;
        let out = net.forward(&img, &choose, false)?;
        let corr = out
            .correspondences()?
            .affine(1.0 / crate::model::UV_SCALE, 0.0)?
            .squeeze(0)?
            .to_vec2::<f32>()?;
        let verts = out.vertices_canonical()?.flatten_all()?.to_vec1::<f32>()?;
        let raw = if keep_raw {
            let flat = |t: &Tensor| t.flatten_all()?.to_vec1::<f32>();
            Some(RawOutputs {
                image: input.to_vec(),
                choose: pixels.clone(),
                seg_logits: flat(&out.dense.seg_logits)?,
                uv_map: flat(&out.dense.uv_map)?,
                assignment: flat(&out.assignment()?)?,
                points: flat(&out.correspondences()?)?,
                vertices: flat(&out.vertices)?,
            })
        } else {
            None
        };
        Ok((
            NetworkPrediction {
                mask,
                pixels,
                points: corr.iter().map(|p| [p[0], p[1], p[2]]).collect(),
                verts,
            },
            raw,
        ))
    };
    run().map_err(|e| candle_err("network forward", e))
}

/// The direct baseline's pose for one crop (`3 x S x S` normalised) cut by `crop` from
/// an image of `width` x `height`, or `None` when its output is not a pose in front of
/// the camera ([`crate::direct::pose_from_output`]).
pub fn direct_pose(
    net: &DirectNet,
    input: &[f32],
    crop: &CropTransform,
    width: u32,
    height: u32,
) -> Result<Option<Pose>> {
    let s = net.config().input_size;
    let out = (|| -> candle_core::Result<Vec<f32>> {
        let img = Tensor::from_slice(input, (1, 3, s, s), &Device::Cpu)?;
        net.forward(&img, false)?.flatten_all()?.to_vec1::<f32>()
    })()
    .map_err(|e| candle_err("network forward", e))?;
    let k = arkit_data::predict::intrinsics(width, height);
    Ok(crate::direct::pose_from_output(&out, crop, &k))
}

/// The pose of a sample predicted from the network's correspondences (crop pixels
/// mapped to the image by the crop's sampling rule, our PnP), or `None` when PnP fails.
pub fn pose_of(
    prediction: &NetworkPrediction,
    crop: &CropTransform,
    width: u32,
    height: u32,
    ransac: &arkit_data::pnp::RansacParams,
) -> Option<Pose> {
    use arkit_data::predict::crop_pixel_to_image;
    let mut seen = std::collections::HashSet::new();
    let (mut object, mut image) = (Vec::new(), Vec::new());
    for (px, p) in prediction.pixels.iter().zip(&prediction.points) {
        if seen.insert(*px) {
            object.push(nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64));
            image.push(crop_pixel_to_image(crop, *px));
        }
    }
    let k = arkit_data::predict::intrinsics(width, height);
    arkit_data::predict::pose_from_correspondences(&object, &image, &k, ransac)
        .ok()
        .map(|(p, _)| p)
}

/// What [`model_predictions`] did.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ModelPredictSummary {
    /// Samples predicted.
    pub samples: usize,
    /// PnP failures (null `R_t` written).
    pub failures: usize,
    /// Samples left out with `--mask truth` because `render` could not render them
    /// (no true mask; listed in the targets' `errors/`).
    pub without_true_mask: usize,
    /// Samples left out because their image could not be read (key, reason naming the
    /// file): no prediction is written for them, so `eval` counts them missing.
    pub unreadable: Vec<(arkit_data::release::SampleKey, String)>,
}

/// Runs a trained network over the samples of `split` (`None`: all): the crop box of
/// `crop_rule` from the sample's landmarks (as the official evaluation does), the
/// network, our PnP; the predictions carry `R_t`, the predicted mesh and the predicted
/// crop mask (the direct baseline's carry its regressed `R_t` only: no PnP, mesh or
/// mask, so `eval` prints `-` for those scores). With `true_masks` (a folder with `render`'s targets at the network's
/// input size), the points are sampled from the true face mask instead of the
/// predicted one, which separates segmentation errors from correspondence errors; the
/// crop is then the targets' own.
#[allow(clippy::too_many_arguments)]
pub fn model_predictions(
    dataset: &Path,
    model: &TrainedModel,
    split: Option<&str>,
    crop_rule: arkit_data::render::CropRule,
    true_masks: Option<&Path>,
    seed: u64,
    ransac: &arkit_data::pnp::RansacParams,
    progress: &dyn Fn(usize),
) -> Result<(
    Vec<arkit_data::predictions_table::PredictionRecord>,
    ModelPredictSummary,
)> {
    model_predictions_dump(
        dataset, model, split, crop_rule, true_masks, seed, ransac, progress, None,
    )
}

/// [`model_predictions`], also collecting each predicted sample's network inputs and
/// raw outputs into `dump` when given.
#[allow(clippy::too_many_arguments)]
pub fn model_predictions_dump(
    dataset: &Path,
    model: &TrainedModel,
    split: Option<&str>,
    crop_rule: arkit_data::render::CropRule,
    true_masks: Option<&Path>,
    seed: u64,
    ransac: &arkit_data::pnp::RansacParams,
    progress: &dyn Fn(usize),
    mut dump: Option<&mut Vec<(arkit_data::release::SampleKey, RawOutputs)>>,
) -> Result<(
    Vec<arkit_data::predictions_table::PredictionRecord>,
    ModelPredictSummary,
)> {
    if let Network::Direct(_) = &model.net {
        if true_masks.is_some() {
            return Err(Error::invalid(
                "--mask truth",
                "chooses the pixels of a PerspNet's correspondences; the direct baseline has none",
            ));
        }
        if dump.is_some() {
            model.net.perspnet("--dump")?;
        }
    }
    let data = Dataset::open(dataset)?;
    let splits = SplitLookup::read(dataset)?;
    let size = model.checkpoint.config.input_size as u32;
    let mut out = Vec::new();
    let mut summary = ModelPredictSummary::default();
    for shard in data.shards() {
        let truth: HashMap<arkit_data::release::SampleKey, TargetsRecord> = match true_masks {
            Some(dir) => {
                targets_table::read_targets_by_key(&targets_table::shard_path(dir, shard.index))?
            }
            None => HashMap::new(),
        };
        let skipped = match true_masks {
            Some(dir) => targets_table::read_skipped_keys(dir, shard.index)?,
            None => Default::default(),
        };
        for (i, r) in data.read_samples(shard)?.into_iter().enumerate() {
            if !splits.keeps(&r, split) {
                continue;
            }
            if skipped.contains(&r.key) {
                summary.without_true_mask += 1;
                progress(1);
                continue;
            }
            let Some(mut crop) = crop_rule.around_landmarks(&r.landmarks_2d, size) else {
                return Err(Error::invalid(
                    "landmarks",
                    format!("{}: the official crop box is empty", r.key),
                ));
            };
            let true_mask = match true_masks {
                None => None,
                Some(dir) => {
                    let t = truth.get(&r.key).ok_or_else(|| {
                        Error::format(dir, format!("no targets row for {}", r.key))
                    })?;
                    // The true mask is in the targets' crop (ours or the official one).
                    crop = t.crop;
                    if t.crop.size != size {
                        return Err(Error::invalid(
                            "--mask truth",
                            format!(
                                "targets in {} were rendered at {}x{}, the network takes {size}x{size}",
                                dir.display(),
                                t.crop.size,
                                t.crop.size
                            ),
                        ));
                    }
                    Some(t.mask()?)
                }
            };
            let image = match data.image(&r) {
                Ok(image) => image,
                Err(e) => {
                    summary.unreadable.push((r.key.clone(), e.to_string()));
                    progress(1);
                    continue;
                }
            };
            let input = network_input(&image, &crop);
            if let Network::Direct(net) = &model.net {
                let pose = direct_pose(net, &input, &crop, r.image_width, r.image_height)?;
                summary.samples += 1;
                summary.failures += pose.is_none() as usize;
                out.push(arkit_data::predictions_table::PredictionRecord {
                    key: r.key.clone(),
                    rt: pose.map(|p| p.to_release_rt()),
                    verts: None,
                    mask_rle: None,
                });
                progress(1);
                continue;
            }
            let (p, raw) = predict_crop_raw(
                model,
                &input,
                seed ^ ((shard.index as u64) << 32 | i as u64),
                true_mask.as_deref(),
                dump.is_some(),
            )?;
            if let (Some(d), Some(raw)) = (dump.as_deref_mut(), raw) {
                d.push((r.key.clone(), raw));
            }
            let pose = pose_of(&p, &crop, r.image_width, r.image_height, ransac);
            summary.samples += 1;
            summary.failures += pose.is_none() as usize;
            out.push(arkit_data::predictions_table::PredictionRecord {
                key: r.key.clone(),
                rt: pose.map(|p| p.to_release_rt()),
                verts: Some(p.verts),
                mask_rle: Some(targets_table::rle_encode(&p.mask)),
            });
            progress(1);
        }
    }
    Ok((out, summary))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 4x4 crop with face pixels 5, 6, 9 (a small L), coordinates that encode the
    /// pixel, and stored points [0, 2].
    fn toy() -> Example {
        let s = 4usize;
        let pixels = vec![5u32, 6, 9];
        let mut mask = vec![0f32; s * s];
        for &p in &pixels {
            mask[p as usize] = 1.0;
        }
        let nocs: Vec<f32> = pixels.iter().flat_map(|&p| [p as f32, 0.0, 1.0]).collect();
        let ids: Vec<u32> = pixels.iter().flat_map(|&p| [p, p + 1, p + 2]).collect();
        let weights: Vec<f32> = pixels.iter().flat_map(|_| [0.5, 0.25, 0.25]).collect();
        let sample = SampleRecord {
            key: arkit_data::release::SampleKey {
                subject_id: "1".into(),
                facial_action: "01_Neutral".into(),
                img_id: "1".into(),
            },
            split: "train".into(),
            image_path: String::new(),
            image_width: 8,
            image_height: 8,
            jpeg: None,
            verts: Vec::new(),
            rt: [0.0; 16],
            yaw_deg: 0.0,
            pitch_deg: 0.0,
            roll_deg: 0.0,
            translation_m: [0.0; 3],
            landmarks_2d: Vec::new(),
            face_box: [0.0; 4],
        };
        Example {
            sample,
            crop: CropTransform::around_landmarks(&[0.0, 0.0, 10.0, 10.0], s as u32),
            image: (0..3 * s * s).map(|i| (i % 7) as f32 * 0.1 - 0.3).collect(),
            mask,
            pixels,
            nocs,
            ids,
            weights,
            points: vec![0, 2],
        }
    }

    #[test]
    fn stored_view_is_the_stored_points() {
        let e = toy();
        let v = e.stored_view();
        assert_eq!(v.choose, vec![5, 9]);
        assert_eq!(v.nocs, vec![5.0, 0.0, 1.0, 9.0, 0.0, 1.0]);
        assert_eq!(v.ids, vec![5, 6, 7, 9, 10, 11]);
        assert_eq!(v.image, e.image);
        // No augmentation at all gives the stored points, cycled to M.
        let mut rng = Rng::new(1);
        let n = e.augmented_view(4, &Augmentation::NONE, &mut rng);
        assert_eq!(n.choose, vec![5, 9, 5, 9]);
        assert_eq!(n.image, e.image);
    }

    #[test]
    fn shifted_views_keep_pixels_and_targets_together() {
        let e = toy();
        let aug = Augmentation {
            colour: 0.0,
            shift_px: 1,
            resample_points: true,
        };
        let mut seen_shift = false;
        for seed in 0..40 {
            let v = e.augmented_view(6, &aug, &mut Rng::new(seed));
            assert_eq!(v.choose.len(), 6);
            for (k, &c) in v.choose.iter().enumerate() {
                // Every chosen pixel is a face pixel of the shifted mask, and its
                // coordinates are those of the pixel it came from, moved by the shift.
                assert_eq!(v.mask[c as usize], 1.0, "seed {seed}");
                let from = v.nocs[3 * k] as u32;
                assert!(e.pixels.contains(&from));
                assert_eq!(v.ids[3 * k], from);
                let (dx, dy) = (
                    (c % 4) as i64 - (from % 4) as i64,
                    (c / 4) as i64 - (from / 4) as i64,
                );
                assert!(dx.abs() <= 1 && dy.abs() <= 1);
                seen_shift |= dx != 0 || dy != 0;
                // The image moved with the mask: the channel-0 value under the chosen
                // pixel is the original value under the source pixel.
                assert_eq!(v.image[c as usize], e.image[from as usize]);
            }
            // The shifted mask holds exactly the face pixels that stayed inside.
            let from = v.nocs[0] as i64;
            let (dx, dy) = (
                v.choose[0] as i64 % 4 - from % 4,
                v.choose[0] as i64 / 4 - from / 4,
            );
            let inside = e
                .pixels
                .iter()
                .filter(|&&p| {
                    let (x, y) = ((p % 4) as i64 + dx, (p / 4) as i64 + dy);
                    (0..4).contains(&x) && (0..4).contains(&y)
                })
                .count();
            assert_eq!(v.mask.iter().sum::<f32>() as usize, inside);
        }
        assert!(seen_shift, "40 draws never shifted");
        // Same generator state, same view.
        assert_eq!(
            e.augmented_view(6, &aug, &mut Rng::new(7)),
            e.augmented_view(6, &aug, &mut Rng::new(7))
        );
    }

    #[test]
    fn colour_jitter_stays_in_range_and_zero_is_identity() {
        let e = toy();
        let n = 16;
        assert_eq!(jitter_colour(&e.image, n, 0.0, &mut Rng::new(1)), e.image);
        let j = jitter_colour(&e.image, n, 0.5, &mut Rng::new(2));
        assert_ne!(j, e.image);
        for k in 0..3 {
            for &v in &j[k * n..(k + 1) * n] {
                let raw = v * IMAGENET_STD[k] + IMAGENET_MEAN[k];
                assert!((-1e-5..=1.0 + 1e-5).contains(&raw), "{raw}");
            }
        }
    }

    #[test]
    fn learning_rate_holds_then_falls_to_zero() {
        // 10 steps, half held: 1 for steps 0-4, then 5/5, 4/5, ... 1/5.
        let lr: Vec<f64> = (0..10).map(|s| learning_rate_at(s, 10, 1.0, 0.5)).collect();
        assert_eq!(&lr[..6], &[1.0; 6]);
        for (s, v) in lr.iter().enumerate().skip(5) {
            assert!((v - (10 - s) as f64 / 5.0).abs() < 1e-12, "{s}: {v}");
        }
        assert_eq!(learning_rate_at(9, 10, 2.0, 1.0), 2.0);
        assert!((learning_rate_at(9, 10, 2.0, 0.0) - 0.2).abs() < 1e-12);
    }
}
