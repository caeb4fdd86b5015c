//! Training examples and what the network sees of them.
//!
//! An example is what the official loader builds per sample, read from storage
//! instead of re-rendered: the crop, the face pixels of the crop, the ground-truth
//! coordinates under them (`4.5 x` canonical, the official scale), their barycentric
//! correspondences (3 vertex ids and weights per pixel), the crop's face mask and the
//! canonical mesh. The targets must have been rendered at the network's input size
//! with at least M points (`render --size S --points M`); a mismatch is an error that
//! says which `render` options to use.

use crate::candle_error::candle_err;
use crate::config::{Architecture, PerspNetConfig};
use crate::loss::CorrTarget;
use arkit_core::Rng;
use arkit_core::conventions::Pose;
use arkit_core::{Error, Result};
use arkit_data::crop::CropTransform;
use arkit_data::loader::{ColourJitter, ColourJitterRanges};
use arkit_data::loader::{LoaderItem, normalise};
use arkit_data::store::Dataset;
use arkit_data::store::SampleRecord;
use arkit_data::store::SplitLookup;
use arkit_data::store::{self, TargetsRecord};
use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Scale of the official coordinate targets: `nocs = 4.5 x` canonical position.
pub const NOCS_SCALE: f32 = 4.5;

/// One training example (see the module docs), flat row-major buffers. Every face pixel
/// of the crop is kept with its targets, so that training can draw fresh pixels each
/// time it sees the example (as the official loader does) and shift the crop.
#[derive(Clone, Debug)]
pub struct Example {
    /// The sample.
    pub sample: SampleRecord,
    /// Its image file (absolute), or the dataset folder for an embedded image.
    pub image_path: PathBuf,
    /// Crop transform of the targets.
    pub crop: CropTransform,
    /// The crop's pixels, `S x S` interleaved RGB bytes (the network sees them through
    /// [`Example::item`]: colour-jittered, normalised, shifted).
    pub rgb: Vec<u8>,
    /// `S x S` face mask (0 or 1).
    pub mask: Vec<u8>,
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
        self.rgb.len()
            + self.mask.len()
            + 4 * (self.pixels.len()
                + self.nocs.len()
                + self.ids.len()
                + self.weights.len()
                + self.points.len())
            + self.sample.verts.len() * 4
    }
}

/// Training-time augmentation, drawn per example and step from the run's seed.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Augmentation {
    /// Colour jitter strength `c`: torchvision's `ColorJitter(c, c, 2c/3, c/30)` on
    /// the crop's bytes, the Python loader's jitter
    /// ([`arkit_data::loader::ColourJitterRanges::of_strength`]; 0.3 is the
    /// official loader's, 0 turns it off).
    #[serde(rename = "colour_jitter", default)]
    pub colour: f32,
    /// Crop jitter: the crop is shifted by up to this many pixels on each axis
    /// (the image, the mask and the face pixels move together; pixels shifted out
    /// are dropped, uncovered ones are the mean colour).
    pub shift_px: u32,
    /// Draw fresh face pixels each step instead of the `M` stored ones.
    pub resample_points: bool,
    /// The strength of the colour jitter `train` used before it used the loader's
    /// (brightness, contrast and per-channel gains on the normalised crop), as older
    /// checkpoints record it (their `colour`). Read, never written, never applied: a
    /// checkpoint that has one cannot be resumed.
    #[serde(
        rename = "colour",
        default,
        deserialize_with = "legacy_colour",
        skip_serializing_if = "Option::is_none"
    )]
    pub legacy_colour: Option<f32>,
}

/// An older checkpoint's `colour`: `None` when 0 (no jitter then, whichever rule).
fn legacy_colour<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> std::result::Result<Option<f32>, D::Error> {
    Ok(Option::<f32>::deserialize(d)?.filter(|&c| c != 0.0))
}

impl Augmentation {
    /// No augmentation: the stored view.
    pub const NONE: Augmentation = Augmentation {
        colour: 0.0,
        shift_px: 0,
        resample_points: false,
        legacy_colour: None,
    };
    /// The default for training: the official colour jitter (0.3), shift 2 px, fresh
    /// points.
    pub const DEFAULT: Augmentation = Augmentation {
        colour: 0.3,
        shift_px: 2,
        resample_points: true,
        legacy_colour: None,
    };
}

impl Default for Augmentation {
    fn default() -> Self {
        Augmentation::DEFAULT
    }
}

impl Example {
    /// The view `render` stored: the crop as is and the stored points.
    pub(crate) fn stored_item(&self) -> LoaderItem {
        self.item_of(
            normalise(&self.rgb),
            self.mask.clone(),
            &self.points,
            (0, 0),
        )
    }

    /// What the network sees of this example in one step, drawn from `rng`: the crop
    /// shifted by `(dx, dy)` pixels (drawn first, up to `aug.shift_px`), its bytes
    /// colour-jittered ([`arkit_data::loader::ColourJitter`], the loader's, at
    /// strength `aug.colour`) and normalised, and `m` face pixels (fresh ones, or the
    /// stored points cycled) with their targets. The item is the loader's type: what
    /// the Python package serves for a sample, with the shifted crop as its `crop` and
    /// `tform_inv` and no UV map.
    pub fn item(&self, m: usize, aug: &Augmentation, rng: &mut Rng) -> LoaderItem {
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
        let mut rgb = self.rgb.clone();
        if aug.colour > 0.0 {
            ColourJitter::draw_in(rng, &ColourJitterRanges::of_strength(aug.colour))
                .apply(&mut rgb);
        }
        let img = shift_planes(&normalise(&rgb), s, 3, dx, dy);
        let mask = shift_planes(&self.mask, s, 1, dx, dy);
        let inside = |p: u32| {
            let (x, y) = ((p as usize % s) as i64 + dx, (p as usize / s) as i64 + dy);
            x >= 0 && y >= 0 && x < s as i64 && y < s as i64
        };
        let kept: Vec<u32> = (0..self.pixels.len() as u32)
            .filter(|&i| inside(self.pixels[i as usize]))
            .collect();
        if kept.is_empty() {
            return self.stored_item();
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
                return self.stored_item();
            }
            (0..m).map(|i| stored[i % stored.len()]).collect()
        };
        self.item_of(img, mask, &points, (dx, dy))
    }

    /// The item of the (shifted) normalised crop `img`, its mask and the face pixels
    /// `points` (indices into [`Example::pixels`]) moved by the shift `(dx, dy)`.
    fn item_of(
        &self,
        img: Vec<f32>,
        mask: Vec<u8>,
        points: &[u32],
        (dx, dy): (i64, i64),
    ) -> LoaderItem {
        let s = self.crop.size as i64;
        // The content moved by (dx, dy) pixels: the crop window moved by minus that.
        let crop = if (dx, dy) == (0, 0) {
            self.crop
        } else {
            CropTransform {
                x0: self.crop.x0 - dx as f64 * self.crop.side / s as f64,
                y0: self.crop.y0 - dy as f64 * self.crop.side_y / s as f64,
                ..self.crop
            }
        };
        let mut item = LoaderItem {
            key: self.sample.key.clone(),
            image_path: self.image_path.clone(),
            img,
            choose: Vec::with_capacity(points.len()),
            model: self.sample.verts.clone(),
            uvmap: Vec::new(),
            nocs: Vec::with_capacity(3 * points.len()),
            mask,
            corr_vertices: Vec::with_capacity(points.len()),
            corr_weights: Vec::with_capacity(points.len()),
            tform_inv: arkit_data::loader::tform_inv(&crop),
            rt: self.sample.rt,
            crop,
            official_box: None,
            choose_box: Vec::new(),
            box_clipped: false,
        };
        for &i in points {
            let i = i as usize;
            let p = self.pixels[i] as i64;
            item.choose.push((p / s + dy) * s + p % s + dx);
            item.nocs.extend_from_slice(&self.nocs[3 * i..3 * i + 3]);
            let (ids, w) = (&self.ids[3 * i..3 * i + 3], &self.weights[3 * i..3 * i + 3]);
            item.corr_vertices.push([ids[0], ids[1], ids[2]]);
            item.corr_weights.push([w[0], w[1], w[2]]);
        }
        item
    }
}

/// Shifts `planes` planes of `s x s` by `(dx, dy)` pixels; uncovered pixels are 0 (the
/// mean colour after normalisation, background in a mask).
fn shift_planes<T: Copy + Default>(
    data: &[T],
    s: usize,
    planes: usize,
    dx: i64,
    dy: i64,
) -> Vec<T> {
    if dx == 0 && dy == 0 {
        return data.to_vec();
    }
    let mut out = vec![T::default(); data.len()];
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

/// The crop of a sample's image, as the network's input: `3 x S x S` floats,
/// ImageNet-normalised ([`arkit_data::loader::normalise`]: the loader's, with no
/// colour jitter; the evaluation input).
pub fn network_input(image: &image::RgbImage, crop: &CropTransform) -> Vec<f32> {
    normalise(crop.crop_image(image).as_raw())
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
    let pixels = arkit_data::store::mask_pixel_indices(&mask);
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
        image_path: dataset
            .image_path(sample)
            .unwrap_or_else(|| dataset.dir().to_path_buf()),
        crop: targets.crop,
        rgb: targets.crop.crop_image(&image).into_raw(),
        mask: mask.iter().map(|&m| m as u8).collect(),
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

/// Where [`crate::train`] takes its examples from, one shard at a time: it loads a shard, runs
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
/// `samples` and `targets` tables and the images when [`crate::train`] reaches the shard
/// (`train --stream`), so memory holds one shard's examples instead of the whole
/// split's. Shards without an example of the split are left out.
pub struct ShardedExamples {
    dataset: PathBuf,
    cfg: PerspNetConfig,
    split: Option<String>,
    data: Dataset,
    splits: SplitLookup,
    /// The targets, opened with the dataset.
    targets: store::RenderedTargets,
    /// `(shard index, samples file, examples in the split)`.
    shards: Vec<(usize, String, usize)>,
    /// Samples left out because their image could not be read, with the reason.
    unreadable: Vec<(arkit_core::SampleKey, String)>,
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
        // The targets opened with the dataset, and both of the generation opened: then
        // this run serves that generation to its end, whatever replaces the folder.
        let targets = store::RenderedTargets::open(targets_dir, &data)?;
        data.confirm_unchanged()?;
        let mut shards = Vec::new();
        let mut unreadable = Vec::new();
        for shard in data.shards() {
            if !targets.has(shard.index) {
                // Removed under this reader by a `render --overwrite`?
                targets.confirm_unchanged()?;
                return Err(Error::format(
                    targets.shard_path(shard.index),
                    "no targets for this shard: run `arkit-tool render` first",
                ));
            }
            let skipped = targets.skipped(shard.index)?;
            let kept: Vec<SampleRecord> = data
                .read_samples(shard)?
                .into_iter()
                .filter(|r| splits.keeps(r, split) && !skipped.contains(&r.key))
                .collect();
            let checks: Vec<Option<(arkit_core::SampleKey, String)>> = {
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
            cfg: cfg.clone(),
            split: split.map(str::to_string),
            data,
            splits,
            targets,
            shards,
            unreadable,
        })
    }
}

impl ShardedExamples {
    /// The samples left out because their image could not be read (key, reason naming
    /// the file), in shard order.
    pub fn unreadable(&self) -> &[(arkit_core::SampleKey, String)] {
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
        let tpath = self.targets.shard_path(*index);
        let targets = self.targets.by_key(*index)?;
        // Samples `render` reported it could not render have no row: leave them out.
        let skipped = self.targets.skipped(*index)?;
        let mut out = Vec::with_capacity(*n);
        let unreadable: std::collections::HashSet<&arkit_core::SampleKey> =
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

/// Stacks the items the network sees in one step into a batch (`items[i]` is drawn
/// from `examples[i]`, which gives the image size the direct model's targets need).
pub fn batch(
    examples: &[&Example],
    items: &[LoaderItem],
    cfg: &PerspNetConfig,
    device: &Device,
) -> Result<Batch> {
    let b = examples.len();
    let (s, m, v) = (cfg.input_size, cfg.points, cfg.vertices);
    let t = |data: Vec<f32>, shape: &[usize]| {
        Tensor::from_vec(data, shape, device).map_err(|e| candle_err("batch", e))
    };
    let u = |data: Vec<u32>, shape: &[usize]| {
        Tensor::from_vec(data, shape, device).map_err(|e| candle_err("batch", e))
    };
    let model: Vec<f32> = items.iter().flat_map(|i| i.model.iter().copied()).collect();
    if model.len() != b * v * 3 {
        return Err(Error::invalid(
            "batch",
            format!(
                "meshes have {} values, the network expects {v} vertices",
                model.len() / b.max(1)
            ),
        ));
    }
    if items.len() != b || items.iter().any(|i| i.choose.len() != m) {
        return Err(Error::invalid(
            "batch",
            format!("each of the {b} items needs {m} points"),
        ));
    }
    let direct = match cfg.architecture {
        Architecture::PerspNet => None,
        Architecture::Direct => {
            let mut d = Vec::with_capacity(12 * b);
            for (e, i) in examples.iter().zip(items) {
                let pose = Pose::from_release_rt(&i.rt)?;
                let k = arkit_data::pose::intrinsics(e.sample.image_width, e.sample.image_height);
                // The item's crop is the shifted one.
                d.extend(crate::direct::direct_target(&pose, &i.crop, &k, (0, 0)));
            }
            Some(t(d, &[b, 12])?)
        }
    };
    let f32s =
        |f: &dyn Fn(&LoaderItem) -> Vec<f32>| -> Vec<f32> { items.iter().flat_map(f).collect() };
    Ok(Batch {
        direct,
        image: t(f32s(&|i| i.img.clone()), &[b, 3, s, s])?,
        choose: u(
            items
                .iter()
                .flat_map(|i| i.choose.iter().map(|&c| c as u32))
                .collect(),
            &[b, m],
        )?,
        nocs: t(f32s(&|i| i.nocs.clone()), &[b, m, 3])?,
        model: t(model, &[b, v, 3])?,
        mask: t(
            f32s(&|i| i.mask.iter().map(|&v| v as f32).collect()),
            &[b, s, s],
        )?,
        corr: CorrTarget::Sparse {
            ids: u(
                items
                    .iter()
                    .flat_map(|i| i.corr_vertices.iter().flatten().copied())
                    .collect(),
                &[b, m, 3],
            )?,
            weights: t(
                f32s(&|i| i.corr_weights.iter().flatten().copied().collect()),
                &[b, m, 3],
            )?,
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 4x4 crop with face pixels 5, 6, 9 (a small L), coordinates that encode the
    /// pixel, and stored points [0, 2].
    fn toy() -> Example {
        let s = 4usize;
        let pixels = vec![5u32, 6, 9];
        let mut mask = vec![0u8; s * s];
        for &p in &pixels {
            mask[p as usize] = 1;
        }
        let nocs: Vec<f32> = pixels.iter().flat_map(|&p| [p as f32, 0.0, 1.0]).collect();
        let ids: Vec<u32> = pixels.iter().flat_map(|&p| [p, p + 1, p + 2]).collect();
        let weights: Vec<f32> = pixels.iter().flat_map(|_| [0.5, 0.25, 0.25]).collect();
        let sample = SampleRecord {
            key: arkit_core::SampleKey {
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
            image_path: PathBuf::new(),
            crop: CropTransform::around_landmarks(&[0.0, 0.0, 10.0, 10.0], s as u32),
            // Each pixel's channels differ from its neighbours'.
            rgb: (0..3 * s * s).map(|i| (i * 37 % 251) as u8).collect(),
            mask,
            pixels,
            nocs,
            ids,
            weights,
            points: vec![0, 2],
        }
    }

    #[test]
    fn stored_item_is_the_stored_points() {
        let e = toy();
        let v = e.stored_item();
        assert_eq!(v.choose, vec![5, 9]);
        assert_eq!(v.nocs, vec![5.0, 0.0, 1.0, 9.0, 0.0, 1.0]);
        assert_eq!(v.corr_vertices, vec![[5, 6, 7], [9, 10, 11]]);
        assert_eq!(v.corr_weights, vec![[0.5, 0.25, 0.25]; 2]);
        // The network's input of the crop: the loader's normalisation.
        assert_eq!(v.img, normalise(&e.rgb));
        assert_eq!((v.crop, v.mask.clone()), (e.crop, e.mask.clone()));
        // No augmentation at all gives the stored points, cycled to M.
        let mut rng = Rng::new(1);
        let n = e.item(4, &Augmentation::NONE, &mut rng);
        assert_eq!(n.choose, vec![5, 9, 5, 9]);
        assert_eq!(n.img, v.img);
    }

    #[test]
    fn shifted_items_keep_pixels_and_targets_together() {
        let e = toy();
        let aug = Augmentation {
            colour: 0.0,
            shift_px: 1,
            resample_points: true,
            legacy_colour: None,
        };
        let plain = normalise(&e.rgb);
        let mut seen_shift = false;
        for seed in 0..40 {
            let v = e.item(6, &aug, &mut Rng::new(seed));
            assert_eq!(v.choose.len(), 6);
            for (k, &c) in v.choose.iter().enumerate() {
                // Every chosen pixel is a face pixel of the shifted mask, and its
                // coordinates are those of the pixel it came from, moved by the shift.
                assert_eq!(v.mask[c as usize], 1, "seed {seed}");
                let from = v.nocs[3 * k] as u32;
                assert!(e.pixels.contains(&from));
                assert_eq!(v.corr_vertices[k][0], from);
                let (dx, dy) = (c % 4 - (from % 4) as i64, c / 4 - (from / 4) as i64);
                assert!(dx.abs() <= 1 && dy.abs() <= 1);
                seen_shift |= dx != 0 || dy != 0;
                // The image moved with the mask: each channel's value under the chosen
                // pixel is the original value under the source pixel.
                for ch in 0..3 {
                    assert_eq!(v.img[ch * 16 + c as usize], plain[ch * 16 + from as usize]);
                }
                // The item's crop is the shifted window: the chosen pixel maps to the
                // image point the source pixel showed.
                let (a, b) = (
                    v.crop.pixel_to_image((c % 4) as u32, (c / 4) as u32),
                    e.crop.pixel_to_image(from % 4, from / 4),
                );
                assert!((a.0 - b.0).abs() < 1e-9 && (a.1 - b.1).abs() < 1e-9);
            }
            // The shifted mask holds exactly the face pixels that stayed inside.
            let from = v.nocs[0] as i64;
            let (dx, dy) = (v.choose[0] % 4 - from % 4, v.choose[0] / 4 - from / 4);
            let inside = e
                .pixels
                .iter()
                .filter(|&&p| {
                    let (x, y) = ((p % 4) as i64 + dx, (p / 4) as i64 + dy);
                    (0..4).contains(&x) && (0..4).contains(&y)
                })
                .count();
            assert_eq!(v.mask.iter().map(|&m| m as usize).sum::<usize>(), inside);
        }
        assert!(seen_shift, "40 draws never shifted");
        // Same generator state, same item.
        assert_eq!(
            e.item(6, &aug, &mut Rng::new(7)),
            e.item(6, &aug, &mut Rng::new(7))
        );
    }

    #[test]
    fn the_colour_jitter_is_the_loaders() {
        let e = toy();
        let aug = Augmentation {
            colour: 0.3,
            shift_px: 0,
            resample_points: false,
            legacy_colour: None,
        };
        // The item's crop is the loader's jitter of the crop's bytes (the official
        // ranges at 0.3, the same draw from the same generator state), normalised.
        let item = e.item(2, &aug, &mut Rng::new(5));
        let mut rgb = e.rgb.clone();
        arkit_data::loader::jitter_colour(&mut rgb, &mut Rng::new(5));
        assert_ne!(rgb, e.rgb);
        assert_eq!(item.img, normalise(&rgb));
    }

    #[test]
    fn older_checkpoints_colour_is_kept_apart() {
        // An older checkpoint's `colour` was the other jitter's strength: read into
        // `legacy_colour`, never as the loader's jitter, and not written back.
        let old: Augmentation =
            serde_json::from_str(r#"{"colour": 0.2, "shift_px": 2, "resample_points": true}"#)
                .unwrap();
        assert_eq!((old.colour, old.legacy_colour), (0.0, Some(0.2)));
        let none: Augmentation =
            serde_json::from_str(r#"{"colour": 0.0, "shift_px": 0, "resample_points": false}"#)
                .unwrap();
        assert_eq!(none, Augmentation::NONE);
        let now = serde_json::to_string(&Augmentation::DEFAULT).unwrap();
        assert_eq!(
            now,
            r#"{"colour_jitter":0.3,"shift_px":2,"resample_points":true}"#
        );
        assert_eq!(
            serde_json::from_str::<Augmentation>(&now).unwrap(),
            Augmentation::DEFAULT
        );
    }
}
