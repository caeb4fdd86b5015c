//! ONNX export of a trained PerspNet: two graphs and a manifest in a folder.
//!
//! PerspNet reads the pixels its own mask selects, chosen by our seeded sampler
//! (`arkit_data::render::sample_points`), a step no ONNX operator reproduces.
//! The network is therefore cut there into two graphs (opset 17, float32, the batch
//! dimension a symbolic `batch`):
//!
//! - `dense.onnx`: the normalised crop `image` (`batch x 3 x S x S`) to `seg_logits`
//!   (`batch x 2 x S x S`), `uv_map` (`batch x 3 x S x S`, tanh, 9 x canonical metres),
//!   `image_features` and `uv_features` (`batch x F x S x S`): the encoder and both
//!   decoders, batch norm in inference mode folded into the convolutions, bilinear 2x
//!   up-sampling with `align_corners=True` (`Resize`, `coordinate_transformation_mode`
//!   `align_corners`), LeakyReLU 0.1 in the decoders.
//! - `points.onnx`: the dense features and `choose` (`batch x M` int64 pixel indices
//!   `y * S + x`) to `assignment` (`batch x M x V`, softmax over the vertices),
//!   `points` (`M X`, `batch x M x 3`) and `vertices` (X, `batch x V x 3`), the last
//!   two in the UV map's units (9 x canonical metres): the pixel gather, the 2D
//!   position encoding of the chosen pixels (from `choose`, inside the graph), the two
//!   global-feature MLPs with their mean over points, the UV reads at the vertex UVs
//!   (`grid_sample` with `align_corners=False` and zero padding, as constant gather
//!   indices and weights), and the assignment MLP (its first layer split into the
//!   local and the global part, which equals one product with the concatenation).
//!
//! Between the two, a caller chooses the points as `predict` does (`onnx.json`'s
//! `point_selection`, and `arkit_tool.onnx` in Python).

mod graph;
mod proto;

use crate::config::{Architecture, PerspNetConfig};
use crate::layers::{PointSampler, positional_encoding_at};
use crate::training::checkpoint::TrainedModel;
use arkit_core::{Error, Result};
use arkit_data::mesh::FaceTopology;
use graph::Graph;
use proto::{Attr, Dim, FLOAT, INT64};
use serde::Serialize;
use sha2::Digest;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The ONNX operator set the graphs use.
pub const ONNX_OPSET: i64 = 17;
/// The ONNX IR version of opset 17.
const IR_VERSION: i64 = 8;
/// The symbolic name of the batch dimension.
const BATCH: &str = "batch";

/// The files [`export_onnx`] writes in its folder.
pub const ONNX_FILES: [&str; 3] = ["dense.onnx", "points.onnx", "onnx.json"];

/// The rule by which the pixels fed to `points.onnx` are chosen (as `predict` does).
pub const POINT_SELECTION: &str = "mask = seg_logits[1] >= seg_logits[0] per pixel; \
candidates = the flat indices y * S + x of the mask's pixels in increasing order (every \
pixel of the crop when the mask is empty); picks = arkit_data::render::sample_points(\
len(candidates), M, seed): M distinct picks in increasing order when there are more than M \
candidates (a partial Fisher-Yates shuffle of 0..n-1 driven by xoshiro256++ seeded through \
SplitMix64, then sorted), else 0, 1, ..., n-1, 0, 1, ... (wrap-around); choose = \
candidates[picks]. In Python, arkit_tool._native.choose_points(mask, M, seed) does all of \
this; docs/onnx.md writes the sampler out. `predict --dataset` seeds sample i of shard k \
with seed ^ ((k << 32) | i); `predict --image` seeds face f of photo p with \
seed ^ (p << 32) ^ f.";

/// One input or output of an exported graph, as the manifest lists it.
#[derive(Debug, Clone, Serialize)]
pub struct OnnxValue {
    /// Its name in the graph.
    pub name: String,
    /// Its element type (`float32` or `int64`).
    pub dtype: String,
    /// Its shape, `"batch"` for the dynamic batch dimension.
    pub shape: Vec<serde_json::Value>,
    /// What it holds and in which units.
    pub doc: String,
}

/// One exported graph in the manifest.
#[derive(Debug, Clone, Serialize)]
pub struct OnnxGraphInfo {
    /// The file in the folder.
    pub file: String,
    /// Its size in bytes.
    pub bytes: u64,
    /// SHA-256 of the file, hex.
    pub sha256: String,
    /// Number of nodes.
    pub nodes: usize,
    /// Number of stored constant values (weights, tables).
    pub constant_values: usize,
    /// Inputs, in order.
    pub inputs: Vec<OnnxValue>,
    /// Outputs, in order.
    pub outputs: Vec<OnnxValue>,
}

/// What [`export_onnx`] wrote: the content of `onnx.json`.
#[derive(Debug, Clone, Serialize)]
pub struct OnnxManifest {
    /// The version of arkit-tool that wrote the export.
    pub arkit_tool_version: String,
    /// The ONNX operator set (17).
    pub opset: i64,
    /// The ONNX IR version (8).
    pub ir_version: i64,
    /// The network's configuration.
    pub config: PerspNetConfig,
    /// The topology the model was trained with (its vertex UVs are in `points.onnx`).
    pub topology: String,
    /// Side S of the square input crop, pixels.
    pub input_size: usize,
    /// Number M of chosen pixels per crop.
    pub points: usize,
    /// Number V of mesh vertices.
    pub vertices: usize,
    /// ImageNet channel means (RGB) subtracted from the crop's values in `[0, 1]`.
    pub normalisation_mean: [f32; 3],
    /// ImageNet channel standard deviations (RGB) the crop is divided by after.
    pub normalisation_std: [f32; 3],
    /// The UV map's units per canonical metre (9): divide `points` and `vertices` by it.
    pub uv_scale: f64,
    /// How the crop is normalised, in words.
    pub normalisation: String,
    /// How `choose` is picked from the dense graph's mask, in words.
    pub point_selection: String,
    /// The dense graph (`dense.onnx`).
    pub dense: OnnxGraphInfo,
    /// The point graph (`points.onnx`).
    pub points_graph: OnnxGraphInfo,
}

/// What [`export_onnx`] returns.
#[derive(Debug, Clone)]
pub struct OnnxExport {
    /// The manifest written as `onnx.json`.
    pub manifest: OnnxManifest,
    /// The files written, in the order written (`dense.onnx`, `points.onnx`, `onnx.json`).
    pub files: Vec<PathBuf>,
}

/// Writes a trained PerspNet as ONNX into the folder `dir` (created if missing):
/// `dense.onnx`, `points.onnx` and the manifest `onnx.json` (see the module docs and
/// docs/onnx.md), each written atomically (an error leaves no partial file).
/// `topology` must be the one the model was loaded with (its vertex UVs are where
/// `points.onnx` reads the UV maps). The direct baseline is refused.
pub fn export_onnx(
    model: &TrainedModel,
    topology: &FaceTopology,
    dir: &Path,
) -> Result<OnnxExport> {
    let cfg = &model.checkpoint.config;
    if cfg.architecture == Architecture::Direct {
        return Err(Error::invalid(
            "--model",
            "export-onnx exports PerspNet; this model is the direct baseline (architecture \"direct\")",
        ));
    }
    model.net.perspnet("exporting to ONNX")?;
    if model.checkpoint.topology != topology.source {
        return Err(Error::invalid(
            "--resources",
            format!(
                "the model was trained with the topology '{}', not '{}'",
                model.checkpoint.topology, topology.source
            ),
        ));
    }
    let weights = Weights::of(model)?;
    let producer_version = env!("CARGO_PKG_VERSION");

    let (dense, mut dense_info) = dense_graph(cfg, &weights)?;
    let (points, mut points_info) = points_graph(cfg, &weights, topology)?;
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    arkit_core::atomic_file::remove_stale_temporaries(dir, false)?;
    let mut files = Vec::new();
    for (g, info, doc) in [
        (
            dense,
            &mut dense_info,
            "PerspNet's encoder and decoders: normalised crop -> segmentation logits, UV map, image and UV features",
        ),
        (
            points,
            &mut points_info,
            "PerspNet's correspondence head: dense features and chosen pixels -> assignment, points, vertices",
        ),
    ] {
        let meta = vec![
            ("arkit_tool.config".to_string(), json(cfg)),
            ("arkit_tool.topology".to_string(), topology.source.clone()),
        ];
        let bytes = proto::model(
            IR_VERSION,
            ONNX_OPSET,
            ("arkit-tool", producer_version),
            doc,
            &g,
            &meta,
        )
        .into_bytes();
        let path = dir.join(&info.file);
        arkit_core::atomic_file::write_bytes(&path, &bytes)?;
        info.bytes = bytes.len() as u64;
        info.sha256 = hex(&sha2::Sha256::digest(&bytes));
        files.push(path);
    }
    let manifest = OnnxManifest {
        arkit_tool_version: producer_version.to_string(),
        opset: ONNX_OPSET,
        ir_version: IR_VERSION,
        config: cfg.clone(),
        topology: topology.source.clone(),
        input_size: cfg.input_size,
        points: cfg.points,
        vertices: cfg.vertices,
        normalisation_mean: arkit_data::loader::IMAGENET_MEAN,
        normalisation_std: arkit_data::loader::IMAGENET_STD,
        uv_scale: crate::model::UV_SCALE,
        normalisation: "image[c] = (rgb[c] / 255 - mean[c]) / std[c], channels R, G, B, \
            laid out channels x rows x columns, of the S x S crop"
            .into(),
        point_selection: POINT_SELECTION.into(),
        dense: dense_info,
        points_graph: points_info,
    };
    let path = dir.join("onnx.json");
    let text = serde_json::to_string_pretty(&manifest).expect("the manifest serialises");
    arkit_core::atomic_file::write_bytes(&path, format!("{text}\n").as_bytes())?;
    files.push(path);
    Ok(OnnxExport { manifest, files })
}

fn json<T: Serialize>(v: &T) -> String {
    serde_json::to_string(v).expect("serialises")
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

/// The model's variables by name, as float32 values with their shapes.
struct Weights(HashMap<String, (Vec<usize>, Vec<f32>)>);

impl Weights {
    fn of(model: &TrainedModel) -> Result<Self> {
        let data = model.varmap.data().lock().expect("varmap lock");
        let mut map = HashMap::new();
        for (k, v) in data.iter() {
            let t = v.as_tensor();
            let values = t
                .flatten_all()
                .and_then(|t| t.to_dtype(candle_core::DType::F32))
                .and_then(|t| t.to_vec1::<f32>())
                .map_err(|e| crate::candle_error::candle_err(k, e))?;
            map.insert(k.clone(), (t.dims().to_vec(), values));
        }
        Ok(Self(map))
    }

    fn get(&self, name: &str) -> Result<&(Vec<usize>, Vec<f32>)> {
        self.0
            .get(name)
            .ok_or_else(|| Error::invalid("model", format!("no variable '{name}' in the weights")))
    }

    fn has(&self, name: &str) -> bool {
        self.0.contains_key(name)
    }
}

fn ints(v: &[i64]) -> Attr {
    Attr::Ints(v.to_vec())
}

fn batch_dims(rest: &[usize]) -> Vec<Dim> {
    std::iter::once(Dim::Named(BATCH.into()))
        .chain(rest.iter().map(|&n| Dim::Fixed(n)))
        .collect()
}

fn describe(name: &str, dtype: &str, rest: &[usize], doc: &str) -> OnnxValue {
    OnnxValue {
        name: name.into(),
        dtype: dtype.into(),
        shape: std::iter::once(serde_json::Value::from(BATCH))
            .chain(rest.iter().map(|&n| serde_json::Value::from(n)))
            .collect(),
        doc: doc.into(),
    }
}

/// Post-convolution activation.
#[derive(Clone, Copy)]
enum Act {
    None,
    Relu,
    Leaky,
}

fn activate(g: &mut Graph, x: String, act: Act) -> String {
    match act {
        Act::None => x,
        Act::Relu => g.op("Relu", &[&x], &[]),
        Act::Leaky => g.op("LeakyRelu", &[&x], &[("alpha", Attr::Float(0.1))]),
    }
}

/// A convolution with `pad = k / 2` and an optional bias.
fn conv(
    g: &mut Graph,
    x: &str,
    w: &[usize],
    wv: &[f32],
    bias: Option<&[f32]>,
    stride: usize,
) -> String {
    let (k, pad) = (w[2] as i64, (w[2] / 2) as i64);
    let wn = g.constant_f32("weight", w, wv);
    let mut inputs = vec![x.to_string(), wn];
    if let Some(b) = bias {
        inputs.push(g.constant_f32("bias", &[w[0]], b));
    }
    let inputs: Vec<&str> = inputs.iter().map(String::as_str).collect();
    let s = stride as i64;
    g.op(
        "Conv",
        &inputs,
        &[
            ("kernel_shape", ints(&[k, k])),
            ("strides", ints(&[s, s])),
            ("pads", ints(&[pad, pad, pad, pad])),
            ("dilations", ints(&[1, 1])),
            ("group", Attr::Int(1)),
        ],
    )
}

/// Conv (no bias) + batch norm in inference mode + activation, the batch norm folded
/// into the convolution: `w' = w gamma / sqrt(var + eps)`, `b' = beta - mean gamma /
/// sqrt(var + eps)` per output channel (computed in f64).
#[allow(clippy::too_many_arguments)]
fn conv_bn(
    g: &mut Graph,
    wts: &Weights,
    x: &str,
    conv_name: &str,
    bn_name: &str,
    stride: usize,
    act: Act,
    eps: f64,
) -> Result<String> {
    let (wd, wv) = wts.get(&format!("{conv_name}.weight"))?;
    let gamma = &wts.get(&format!("{bn_name}.weight"))?.1;
    let beta = &wts.get(&format!("{bn_name}.bias"))?.1;
    let mean = &wts.get(&format!("{bn_name}.running_mean"))?.1;
    let var = &wts.get(&format!("{bn_name}.running_var"))?.1;
    let co = wd[0];
    let per = wv.len() / co;
    let mut w = Vec::with_capacity(wv.len());
    let mut b = Vec::with_capacity(co);
    for o in 0..co {
        let scale = gamma[o] as f64 / (var[o] as f64 + eps).sqrt();
        w.extend(
            wv[o * per..(o + 1) * per]
                .iter()
                .map(|&v| (v as f64 * scale) as f32),
        );
        b.push((beta[o] as f64 - mean[o] as f64 * scale) as f32);
    }
    let y = conv(g, x, wd, &w, Some(&b), stride);
    Ok(activate(g, y, act))
}

/// Bilinear 2x up-sampling with `align_corners=True` (`layers::upsample2x_bilinear`).
fn upsample(g: &mut Graph, x: &str, scales: &str) -> String {
    g.op(
        "Resize",
        &[x, "", scales],
        &[
            ("mode", Attr::String("linear".into())),
            (
                "coordinate_transformation_mode",
                Attr::String("align_corners".into()),
            ),
        ],
    )
}

/// The `dense.onnx` graph. Long (over 150 lines) on purpose: it walks
/// `PerspNet::forward_dense` layer by layer in the same order, so that the two read side
/// by side.
fn dense_graph(cfg: &PerspNetConfig, w: &Weights) -> Result<(proto::Message, OnnxGraphInfo)> {
    let (s, f, eps) = (cfg.input_size, cfg.feature_channels, cfg.bn_eps);
    let mut g = Graph::new();
    let img_doc = "the S x S crop, ImageNet-normalised (onnx.json: normalisation)";
    let img = g.input("image", FLOAT, &batch_dims(&[3, s, s]), img_doc);
    let rn = "cnn.resnet18_8s";
    let stem = format!("{rn}.conv1");
    let x2s = conv_bn(
        &mut g,
        w,
        &img,
        &stem,
        &format!("{rn}.bn1"),
        2,
        Act::Relu,
        eps,
    )?;
    let mut y = g.op(
        "MaxPool",
        &[&x2s],
        &[
            ("kernel_shape", ints(&[3, 3])),
            ("strides", ints(&[2, 2])),
            ("pads", ints(&[1, 1, 1, 1])),
        ],
    );
    let mut stages = Vec::new();
    for i in 0..4 {
        for j in 0..2 {
            let p = format!("{rn}.layer{}.{j}", i + 1);
            let stride = if i > 0 && j == 0 { 2 } else { 1 };
            let a = conv_bn(
                &mut g,
                w,
                &y,
                &format!("{p}.conv1"),
                &format!("{p}.bn1"),
                stride,
                Act::Relu,
                eps,
            )?;
            let b = conv_bn(
                &mut g,
                w,
                &a,
                &format!("{p}.conv2"),
                &format!("{p}.bn2"),
                1,
                Act::None,
                eps,
            )?;
            let id = if w.has(&format!("{p}.downsample.0.weight")) {
                let (c, n) = (format!("{p}.downsample.0"), format!("{p}.downsample.1"));
                conv_bn(&mut g, w, &y, &c, &n, stride, Act::None, eps)?
            } else {
                y.clone()
            };
            let sum = g.op("Add", &[&b, &id], &[]);
            y = g.op("Relu", &[&sum], &[]);
        }
        stages.push(y.clone());
    }
    let fc = conv_bn(
        &mut g,
        w,
        &y,
        &format!("{rn}.fc.0"),
        &format!("{rn}.fc.1"),
        1,
        Act::Relu,
        eps,
    )?;
    let scales = g.constant_f32("scales_2x", &[4], &[1.0, 1.0, 2.0, 2.0]);
    let x16 = upsample(&mut g, &fc, &scales);

    // 2D decoder with skips (dropout is the identity in inference).
    let skips = [&stages[2], &stages[1], &stages[0], &x2s];
    let mut fm = x16.clone();
    for (name, skip) in ["conv16s", "conv8s", "conv4s", "conv2s"]
        .into_iter()
        .zip(skips)
    {
        let cat = g.op("Concat", &[&fm, skip], &[("axis", Attr::Int(1))]);
        let n = format!("cnn.{name}");
        let y = conv_bn(
            &mut g,
            w,
            &cat,
            &format!("{n}.0"),
            &format!("{n}.1"),
            1,
            Act::Leaky,
            eps,
        )?;
        fm = upsample(&mut g, &y, &scales);
    }
    let cat = g.op("Concat", &[&fm, &img], &[("axis", Attr::Int(1))]);
    let image_features = conv_bn(
        &mut g,
        w,
        &cat,
        "cnn.final.0",
        "cnn.final.1",
        1,
        Act::Leaky,
        eps,
    )?;
    let (sd, sv) = w.get("cnn.seg.weight")?;
    let seg = conv(
        &mut g,
        &image_features,
        sd,
        sv,
        Some(&w.get("cnn.seg.bias")?.1),
        1,
    );

    // 3D (UV) decoder without skips.
    let mut fm = x16;
    for name in ["conv16s_uv", "conv8s_uv", "conv4s_uv", "conv2s_uv"] {
        let n = format!("cnn.{name}");
        let y = conv_bn(
            &mut g,
            w,
            &fm,
            &format!("{n}.0"),
            &format!("{n}.1"),
            1,
            Act::Leaky,
            eps,
        )?;
        fm = upsample(&mut g, &y, &scales);
    }
    let uv_features = conv_bn(
        &mut g,
        w,
        &fm,
        "cnn.final_uv.0",
        "cnn.final_uv.1",
        1,
        Act::Leaky,
        eps,
    )?;
    let (ud, uvw) = w.get("cnn.uv.weight")?;
    let uv_pre = conv(
        &mut g,
        &uv_features,
        ud,
        uvw,
        Some(&w.get("cnn.uv.bias")?.1),
        1,
    );
    let uv_map = g.op("Tanh", &[&uv_pre], &[]);

    let outputs = [
        (
            seg,
            "seg_logits",
            2,
            "segmentation logits, class 1 = face (the mask is logit 1 >= logit 0)",
        ),
        (
            uv_map,
            "uv_map",
            3,
            "UV position map, tanh, in 9 x canonical metres",
        ),
        (
            image_features,
            "image_features",
            f,
            "full-resolution image features (input of points.onnx)",
        ),
        (
            uv_features,
            "uv_features",
            f,
            "full-resolution UV features (input of points.onnx)",
        ),
    ];
    let mut out_info = Vec::new();
    for (v, name, c, doc) in outputs {
        g.output(&v, name, FLOAT, &batch_dims(&[c, s, s]), doc);
        out_info.push(describe(name, "float32", &[c, s, s], doc));
    }
    let info = OnnxGraphInfo {
        file: "dense.onnx".into(),
        bytes: 0,
        sha256: String::new(),
        nodes: g.node_count,
        constant_values: g.constant_values,
        inputs: vec![describe("image", "float32", &[3, s, s], img_doc)],
        outputs: out_info,
    };
    Ok((
        g.finish("perspnet_dense", "PerspNet encoder and decoders"),
        info,
    ))
}

/// A per-point linear layer `x Wᵀ + b` (`weight` `c_out x c_in`, stored transposed).
fn linear(g: &mut Graph, w: &Weights, x: &str, name: &str, relu: bool) -> Result<String> {
    let (wd, wv) = w.get(&format!("{name}.weight"))?;
    let b = &w.get(&format!("{name}.bias"))?.1;
    let y = matmul_t(g, x, wd[0], wd[1], wv, 0, wd[1]);
    let bn = g.constant_f32("bias", &[wd[0]], b);
    let y = g.op("Add", &[&y, &bn], &[]);
    Ok(if relu { g.op("Relu", &[&y], &[]) } else { y })
}

/// `x Wᵀ` for the columns `[c0, c0 + n)` of a row-major `rows x cols` weight.
fn matmul_t(
    g: &mut Graph,
    x: &str,
    rows: usize,
    cols: usize,
    wv: &[f32],
    c0: usize,
    n: usize,
) -> String {
    let mut t = vec![0f32; n * rows];
    for r in 0..rows {
        for c in 0..n {
            t[c * rows + r] = wv[r * cols + c0 + c];
        }
    }
    let wn = g.constant_f32("weight_t", &[n, rows], &t);
    g.op("MatMul", &[x, &wn], &[])
}

/// The two-layer MLP with ReLUs and the mean over points (`model::mlp_global`).
fn mlp_global(g: &mut Graph, w: &Weights, x: &str, name: &str) -> Result<String> {
    let h = linear(g, w, x, &format!("{name}.0"), true)?;
    let h = linear(g, w, &h, &format!("{name}.2"), true)?;
    Ok(g.op(
        "ReduceMean",
        &[&h],
        &[("axes", ints(&[1])), ("keepdims", Attr::Int(1))],
    ))
}

/// Bilinear reads of a `batch x c x S x S` map at the vertex UVs (`PointSampler`:
/// four constant neighbour indices and weights per vertex): `batch x V x c`.
fn sample_at_vertices(
    g: &mut Graph,
    map: &str,
    c: usize,
    s: usize,
    taps: (&str, &str),
    v: usize,
) -> String {
    let shape = g.constant_i64("shape", &[3], &[0, c as i64, (s * s) as i64]);
    let flat = g.op("Reshape", &[map, &shape], &[]);
    let picked = g.op("Gather", &[&flat, taps.0], &[("axis", Attr::Int(2))]);
    let shape4 = g.constant_i64("shape", &[4], &[0, c as i64, 4, v as i64]);
    let corners = g.op("Reshape", &[&picked, &shape4], &[]);
    let weighted = g.op("Mul", &[&corners, taps.1], &[]);
    let axes = g.constant_i64("axes", &[1], &[2]);
    let sum = g.op(
        "ReduceSum",
        &[&weighted, &axes],
        &[("keepdims", Attr::Int(0))],
    );
    g.op("Transpose", &[&sum], &[("perm", ints(&[0, 2, 1]))])
}

fn points_graph(
    cfg: &PerspNetConfig,
    w: &Weights,
    topology: &FaceTopology,
) -> Result<(proto::Message, OnnxGraphInfo)> {
    let (s, f, m, v) = (
        cfg.input_size,
        cfg.feature_channels,
        cfg.points,
        cfg.vertices,
    );
    let mut g = Graph::new();
    let docs = [
        ("image_features", f, "dense.onnx's image_features"),
        ("uv_features", f, "dense.onnx's uv_features"),
        ("uv_map", 3, "dense.onnx's uv_map"),
    ];
    let mut inputs = Vec::new();
    let mut in_info = Vec::new();
    for (name, c, doc) in docs {
        inputs.push(g.input(name, FLOAT, &batch_dims(&[c, s, s]), doc));
        in_info.push(describe(name, "float32", &[c, s, s], doc));
    }
    let choose_doc =
        "the M chosen crop pixels, flat indices y * S + x (onnx.json: point_selection)";
    let choose = g.input("choose", INT64, &batch_dims(&[m]), choose_doc);
    in_info.push(describe("choose", "int64", &[m], choose_doc));
    let (image_features, uv_features, uv_map) = (&inputs[0], &inputs[1], &inputs[2]);

    // Local features: the chosen pixels' image features (1x1 conv + ReLU) ++ the
    // position encoding of (x, y) = (choose mod S, choose div S).
    let shape = g.constant_i64("shape", &[3], &[0, f as i64, (s * s) as i64]);
    let flat = g.op("Reshape", &[image_features, &shape], &[]);
    let pixels_major = g.op("Transpose", &[&flat], &[("perm", ints(&[0, 2, 1]))]);
    let axes = g.constant_i64("axes", &[1], &[2]);
    let idx = g.op("Unsqueeze", &[&choose, &axes], &[]);
    let emb = g.op(
        "GatherND",
        &[&pixels_major, &idx],
        &[("batch_dims", Attr::Int(1))],
    );
    let color = linear(&mut g, w, &emb, "instance_color.0", true)?;
    let local = if cfg.position_encoding {
        // The encoding's first half depends on x only, its second half on y only: two
        // S-row tables (`positional_encoding_at`'s values), read at x and at y.
        let (d, half) = (cfg.pos_channels, cfg.pos_channels / 2);
        let mut tx = Vec::with_capacity(s * half);
        let mut ty = Vec::with_capacity(s * half);
        for p in 0..s {
            tx.extend_from_slice(&positional_encoding_at(d, p as f64, 0.0)[..half]);
            ty.extend_from_slice(&positional_encoding_at(d, 0.0, p as f64)[half..]);
        }
        let tx = g.constant_f32("position_x", &[s, half], &tx);
        let ty = g.constant_f32("position_y", &[s, half], &ty);
        let side = g.constant_i64("side", &[], &[s as i64]);
        let x = g.op("Mod", &[&choose, &side], &[]);
        let y = g.op("Div", &[&choose, &side], &[]);
        let px = g.op("Gather", &[&tx, &x], &[("axis", Attr::Int(0))]);
        let py = g.op("Gather", &[&ty, &y], &[("axis", Attr::Int(0))]);
        g.op("Concat", &[&color, &px, &py], &[("axis", Attr::Int(2))])
    } else {
        color
    };
    let g2 = mlp_global(&mut g, w, &local, "instance_global")?;

    // The vertex UVs' bilinear taps (exactly `PointSampler`'s).
    let uv = crate::network::vertex_uv(topology, &candle_core::Device::Cpu)?;
    let sampler = PointSampler::new(&uv, s, s)
        .map_err(|e| crate::candle_error::candle_err("vertex UVs", e))?;
    let (tap_idx, tap_w) = sampler.taps();
    let tap_idx: Vec<i64> = tap_idx.iter().map(|&i| i as i64).collect();
    let tap_idx = g.constant_i64("vertex_taps", &[4 * v], &tap_idx);
    let tap_w = g.constant_f32("vertex_tap_weights", &[4, v], tap_w);
    let uv_local = sample_at_vertices(&mut g, uv_features, f, s, (&tap_idx, &tap_w), v);
    let g3 = mlp_global(&mut g, w, &uv_local, "category_global")?;

    // Assignment MLP on [local, g2, g3], the first layer split in its local and global
    // columns (one row per batch for the global part, added to every point).
    let (ad, av) = w.get("assignment.0.weight")?;
    let (a0, cin) = (ad[0], ad[1]);
    let lc = cfg.local_channels();
    let h_local = matmul_t(&mut g, &local, a0, cin, av, 0, lc);
    let global = g.op("Concat", &[&g2, &g3], &[("axis", Attr::Int(2))]);
    let h_global = matmul_t(&mut g, &global, a0, cin, av, lc, cin - lc);
    let b0 = g.constant_f32("bias", &[a0], &w.get("assignment.0.bias")?.1);
    let h_global = g.op("Add", &[&h_global, &b0], &[]);
    let h = g.op("Add", &[&h_local, &h_global], &[]);
    let h = g.op("Relu", &[&h], &[]);
    let h = linear(&mut g, w, &h, "assignment.2", true)?;
    let logits = linear(&mut g, w, &h, "assignment.4", false)?;
    let assignment = g.op("Softmax", &[&logits], &[("axis", Attr::Int(-1))]);
    let vertices = sample_at_vertices(&mut g, uv_map, 3, s, (&tap_idx, &tap_w), v);
    let points = g.op("MatMul", &[&assignment, &vertices], &[]);

    let outputs = [
        (
            assignment,
            "assignment",
            vec![m, v],
            "the soft assignment M of each chosen pixel to the vertices (softmax; rows sum to 1)",
        ),
        (
            points,
            "points",
            vec![m, 3],
            "M X: the 3D point each chosen pixel shows, in 9 x canonical metres",
        ),
        (
            vertices,
            "vertices",
            vec![v, 3],
            "X: the vertices read from the UV map, in 9 x canonical metres",
        ),
    ];
    let mut out_info = Vec::new();
    for (val, name, rest, doc) in outputs {
        g.output(&val, name, FLOAT, &batch_dims(&rest), doc);
        out_info.push(describe(name, "float32", &rest, doc));
    }
    let info = OnnxGraphInfo {
        file: "points.onnx".into(),
        bytes: 0,
        sha256: String::new(),
        nodes: g.node_count,
        constant_values: g.constant_values,
        inputs: in_info,
        outputs: out_info,
    };
    Ok((
        g.finish("perspnet_points", "PerspNet correspondence head"),
        info,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shipped model exports to the three files; each graph is a `ModelProto` that
    /// starts with `ir_version = 8` (key 0x08, value 0x08) and the manifest matches.
    #[test]
    fn the_shipped_model_exports_and_the_manifest_describes_it() {
        let topology = arkit_data::mesh::builtin().topology.clone();
        let model = crate::training::checkpoint::shipped_model(&topology).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("onnx");
        let e = export_onnx(&model, &topology, &out).unwrap();
        let names: Vec<String> = e
            .files
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ONNX_FILES);
        for g in [&e.manifest.dense, &e.manifest.points_graph] {
            let bytes = std::fs::read(out.join(&g.file)).unwrap();
            assert_eq!(&bytes[..2], [0x08, 0x08]);
            assert_eq!(bytes.len() as u64, g.bytes);
            assert_eq!(hex(&sha2::Sha256::digest(&bytes)), g.sha256);
        }
        let m = &e.manifest;
        assert_eq!(
            (m.input_size, m.points, m.vertices, m.opset),
            (64, 256, 1220, 17)
        );
        let text = std::fs::read_to_string(out.join("onnx.json")).unwrap();
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(
            v["dense"]["inputs"][0]["shape"],
            serde_json::json!(["batch", 3, 64, 64])
        );
        assert_eq!(v["points_graph"]["inputs"][3]["dtype"], "int64");
        // No temporary is left behind.
        assert_eq!(std::fs::read_dir(&out).unwrap().count(), 3);
    }
}
