//! The network's predictions: one crop's mask, chosen pixels, correspondences and
//! mesh; the pose from them by our PnP (or the direct baseline's regressed pose); a
//! whole split predicted into prediction rows; `predict --dump`'s npz.
//!
//! The network's input is the crop of the official evaluation box, normalised
//! ([`crate::network_input`]); no colour jitter.

use crate::candle_error::candle_err;
use crate::config::PerspNetConfig;
use crate::direct::DirectNet;
use crate::network::Network;
use crate::training::checkpoint::TrainedModel;
use crate::training::data::network_input;
use arkit_core::conventions::Pose;
use arkit_core::{Error, Result};
use arkit_data::crop::CropTransform;
use arkit_data::mesh::FaceTopology;
use arkit_data::store::Dataset;
use arkit_data::store::SplitLookup;
use arkit_data::store::{self, TargetsRecord};
use candle_core::{Device, Tensor};
use serde::Serialize;
use std::collections::HashMap;
use std::path::Path;

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
    let crop = CropInput { input, seed, truth };
    let mut out = predict_crops(model, std::slice::from_ref(&crop), keep_raw)?;
    Ok(out.pop().expect("one crop in, one prediction out"))
}

/// One crop for [`predict_crops`]: the normalised `3 x S x S` input, the seed of its
/// chosen pixels, and the mask to choose them from instead of the predicted one.
#[derive(Clone, Copy, Debug)]
pub struct CropInput<'a> {
    /// The normalised crop, `3 x S x S`.
    pub input: &'a [f32],
    /// The seed of the chosen pixels.
    pub seed: u64,
    /// The mask to choose the pixels from (`S x S`), or `None` for the predicted one.
    pub truth: Option<&'a [bool]>,
}

/// The most crops [`predict_crops`] puts through the network at once (a bigger batch
/// gains little and holds its activations in memory: about 25 MB a crop at 192 px).
pub const MAX_CROP_BATCH: usize = 8;

/// [`predict_crop_raw`] for several crops, batched: the dense network runs once on
/// up to [`MAX_CROP_BATCH`] crops, the mask of each is read off it, its pixels chosen
/// (from its own seed), and the correspondence head runs once on the batch. Each
/// crop's prediction is the one [`predict_crop`] gives it alone, bit for bit (every
/// kernel computes each batch element on its own).
pub fn predict_crops(
    model: &TrainedModel,
    crops: &[CropInput<'_>],
    keep_raw: bool,
) -> Result<Vec<(NetworkPrediction, Option<RawOutputs>)>> {
    let s = model.checkpoint.config.input_size;
    for c in crops {
        if c.input.len() != 3 * s * s {
            return Err(Error::invalid(
                "network input",
                format!("{} values; a {s}x{s} crop has {}", c.input.len(), 3 * s * s),
            ));
        }
        if let Some(t) = c.truth.filter(|t| t.len() != s * s) {
            return Err(Error::invalid(
                "--mask truth",
                format!("a mask of {} pixels; the crop has {}", t.len(), s * s),
            ));
        }
    }
    let mut out = Vec::with_capacity(crops.len());
    for batch in crops.chunks(MAX_CROP_BATCH) {
        out.extend(predict_batch(model, batch, keep_raw)?);
    }
    Ok(out)
}

/// One batch of [`predict_crops`] (inputs checked).
fn predict_batch(
    model: &TrainedModel,
    crops: &[CropInput<'_>],
    keep_raw: bool,
) -> Result<Vec<(NetworkPrediction, Option<RawOutputs>)>> {
    let cfg = &model.checkpoint.config;
    let (s, m, b) = (cfg.input_size, cfg.points, crops.len());
    let device = Device::Cpu;
    let net = model.net.perspnet("predicting correspondences")?;
    let run = || -> candle_core::Result<Vec<(NetworkPrediction, Option<RawOutputs>)>> {
        let flat: Vec<f32> = crops.iter().flat_map(|c| c.input.iter().copied()).collect();
        let img = Tensor::from_vec(flat, (b, 3, s, s), &device)?;
        let dense = net.forward_dense(&img, false)?;
        // The face mask: class 1's logit at least class 0's, pixel by pixel.
        let logits = dense.seg_logits.flatten_all()?.to_vec1::<f32>()?; // B x 2 x S x S
        let (mut masks, mut chosen) = (Vec::with_capacity(b), Vec::with_capacity(b * m));
        for (k, c) in crops.iter().enumerate() {
            let l = &logits[k * 2 * s * s..(k + 1) * 2 * s * s];
            let (bg, face) = l.split_at(s * s);
            let mask: Vec<bool> = face.iter().zip(bg).map(|(f, g)| f >= g).collect();
            chosen.extend(choose_pixels(c.truth.unwrap_or(&mask), m, c.seed));
            masks.push(mask);
        }
        // The head face by face (each its own products, as alone), the rest batched.
        let (mut logits_k, mut vertices_k) = (Vec::with_capacity(b), Vec::with_capacity(b));
        for k in 0..b {
            let one = |t: &Tensor| t.narrow(0, k, 1);
            let choose = Tensor::from_slice(&chosen[k * m..(k + 1) * m], (1, m), &device)?;
            let (l, v) = net.head(
                &one(&dense.image_features)?,
                &one(&dense.uv_features)?,
                &one(&dense.uv_map)?,
                &choose,
            )?;
            logits_k.push(l);
            vertices_k.push(v);
        }
        let assign_logits = Tensor::cat(&logits_k, 0)?;
        let vertices = Tensor::cat(&vertices_k, 0)?;
        let assignment = crate::layers::softmax_last(&assign_logits)?;
        let points = assignment.matmul(&vertices)?; // B x M x 3, UV-map units
        let corr = points
            .affine(1.0 / crate::model::UV_SCALE, 0.0)?
            .to_vec3::<f32>()?;
        let verts = vertices.affine(1.0 / crate::model::UV_SCALE, 0.0)?;
        let mut out = Vec::with_capacity(b);
        for (k, (c, mask)) in crops.iter().zip(masks).enumerate() {
            let one = |t: &Tensor| t.narrow(0, k, 1)?.flatten_all()?.to_vec1::<f32>();
            let raw = if keep_raw {
                Some(RawOutputs {
                    image: c.input.to_vec(),
                    choose: chosen[k * m..(k + 1) * m].to_vec(),
                    seg_logits: one(&dense.seg_logits)?,
                    uv_map: one(&dense.uv_map)?,
                    assignment: one(&assignment)?,
                    points: one(&points)?,
                    vertices: one(&vertices)?,
                })
            } else {
                None
            };
            out.push((
                NetworkPrediction {
                    mask,
                    pixels: chosen[k * m..(k + 1) * m].to_vec(),
                    points: corr[k].iter().map(|p| [p[0], p[1], p[2]]).collect(),
                    verts: one(&verts)?,
                },
                raw,
            ));
        }
        Ok(out)
    };
    run().map_err(|e| candle_err("network forward", e))
}

/// `m` pixels chosen from the set ones of `mask` (every pixel when none is set) by
/// [`arkit_data::render::sample_points`] from `seed`.
fn choose_pixels(mask: &[bool], m: usize, seed: u64) -> Vec<u32> {
    let mut candidates: Vec<u32> = (0..mask.len() as u32)
        .filter(|&i| mask[i as usize])
        .collect();
    if candidates.is_empty() {
        candidates = (0..mask.len() as u32).collect();
    }
    let picks = arkit_data::render::sample_points(candidates.len(), m, seed);
    picks.iter().map(|&k| candidates[k as usize]).collect()
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
    let k = arkit_data::pose::intrinsics(width, height);
    Ok(crate::direct::pose_from_output(&out, crop, &k))
}

/// The pose of a sample predicted from the network's correspondences (crop pixels
/// mapped to the image by the crop's sampling rule, our PnP), or `None` when PnP fails.
pub fn pose_of(
    prediction: &NetworkPrediction,
    crop: &CropTransform,
    width: u32,
    height: u32,
    ransac: &arkit_data::pose::RansacParams,
) -> Option<Pose> {
    use arkit_data::pose::crop_pixel_to_image;
    let mut seen = std::collections::HashSet::new();
    let (mut object, mut image) = (Vec::new(), Vec::new());
    for (px, p) in prediction.pixels.iter().zip(&prediction.points) {
        if seen.insert(*px) {
            object.push(nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64));
            image.push(crop_pixel_to_image(crop, *px));
        }
    }
    let k = arkit_data::pose::intrinsics(width, height);
    arkit_data::pose::pose_from_correspondences(&object, &image, &k, ransac)
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
    pub unreadable: Vec<(arkit_core::SampleKey, String)>,
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
    crop_rule: arkit_data::crop::RuleSet,
    true_masks: Option<&Path>,
    seed: u64,
    ransac: &arkit_data::pose::RansacParams,
    progress: &dyn Fn(usize),
) -> Result<(Vec<arkit_core::PredictionRecord>, ModelPredictSummary)> {
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
    crop_rule: arkit_data::crop::RuleSet,
    true_masks: Option<&Path>,
    seed: u64,
    ransac: &arkit_data::pose::RansacParams,
    progress: &dyn Fn(usize),
    mut dump: Option<&mut Vec<(arkit_core::SampleKey, RawOutputs)>>,
) -> Result<(Vec<arkit_core::PredictionRecord>, ModelPredictSummary)> {
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
    // Opened with the dataset and checked to be of its generation: served to the end.
    let rendered = match true_masks {
        Some(dir) => Some(store::RenderedTargets::open(dir, &data)?),
        None => None,
    };
    data.confirm_unchanged()?;
    let size = model.checkpoint.config.input_size as u32;
    let mut out = Vec::new();
    let mut summary = ModelPredictSummary::default();
    for shard in data.shards() {
        let truth: HashMap<arkit_core::SampleKey, TargetsRecord> = match &rendered {
            Some(t) => t.by_key(shard.index)?,
            None => HashMap::new(),
        };
        let skipped = match &rendered {
            Some(t) => t.skipped(shard.index)?,
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
            let Some(mut crop) = crop_rule.crop_around_landmarks(&r.landmarks_2d, size) else {
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
                out.push(arkit_core::PredictionRecord {
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
            out.push(arkit_core::PredictionRecord {
                key: r.key.clone(),
                rt: pose.map(|p| p.to_release_rt()),
                verts: Some(p.verts),
                mask_rle: Some(arkit_core::rle_encode(&p.mask)),
            });
            progress(1);
        }
    }
    Ok((out, summary))
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
    dump: &[(arkit_core::SampleKey, RawOutputs)],
) -> Result<()> {
    use arkit_core::{NpyArray, NpzCompression, write_npz};
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
    arkit_core::atomic_file::write_bytes(path, buf.get_ref())
}
