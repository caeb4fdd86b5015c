//! The PerspNet network: ResNet-18 encoder, 2D and 3D (UV) decoders and the
//! correspondence head.
//!
//! Variable names mirror the official PyTorch `state_dict` (`cnn.resnet18_8s.layer1.0.conv1.weight`,
//! `cnn.conv16s.0.weight`, `assignment.4.bias`, ...). The per-point `Conv1d(c_in, c_out, 1)`
//! layers are stored as `c_out x c_in` linear weights (PyTorch: `c_out x c_in x 1`).

use candle_core::{DType, Device, Module, ModuleT, Result, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};

use crate::config::PerspNetConfig;
use crate::layers::{
    Act, BatchNorm2d, Conv2d, ConvBn, PointLinear, PointSampler, add_relu, add_rows_relu,
    dropout2d, gather_pixels, max_pool_3x3_s2_p1, mean_points, point_linear,
    positional_encoding_points, relu, softmax_last, upsample2x_bilinear,
};

/// Scale between the UV-map values and canonical mesh units in the official
/// code: the network regresses `9 x` the canonical vertex positions.
pub const UV_SCALE: f64 = 9.0;

#[derive(Debug, Clone)]
struct BasicBlock {
    conv1: ConvBn,
    conv2: ConvBn,
    downsample: Option<ConvBn>,
}

impl BasicBlock {
    fn new(
        vb: VarBuilder,
        c_in: usize,
        c_out: usize,
        stride: usize,
        cfg: &PerspNetConfig,
    ) -> Result<Self> {
        let (s, e, m) = (cfg.init_std, cfg.bn_eps, cfg.bn_momentum);
        let conv1 = ConvBn::named(
            vb.pp("conv1"),
            vb.pp("bn1"),
            c_in,
            c_out,
            3,
            stride,
            Act::Relu,
            s,
            e,
            m,
        )?;
        let conv2 = ConvBn::named(
            vb.pp("conv2"),
            vb.pp("bn2"),
            c_out,
            c_out,
            3,
            1,
            Act::None,
            s,
            e,
            m,
        )?;
        let downsample = if stride != 1 || c_in != c_out {
            let d = vb.pp("downsample");
            Some(ConvBn::named(
                d.pp("0"),
                d.pp("1"),
                c_in,
                c_out,
                1,
                stride,
                Act::None,
                s,
                e,
                m,
            )?)
        } else {
            None
        };
        Ok(Self {
            conv1,
            conv2,
            downsample,
        })
    }

    fn forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let y = self
            .conv2
            .forward_t(&self.conv1.forward_t(x, train)?, train)?;
        let id = match &self.downsample {
            Some(d) => d.forward_t(x, train)?,
            None => x.clone(),
        };
        add_relu(&y, &id)
    }
}

/// The ResNet-18 trunk shared by PerspNet and the direct baseline: the stem (7x7
/// conv, BN, ReLU), the max-pool and the four stages of two basic blocks, under the
/// official names (`cnn.resnet18_8s.conv1`, `.bn1`, `.layer1.0.conv1`, ...).
#[derive(Debug, Clone)]
pub(crate) struct ResNetTrunk {
    conv1: Conv2d,
    bn1: BatchNorm2d,
    layers: Vec<Vec<BasicBlock>>,
}

impl ResNetTrunk {
    /// The trunk's variables under `rn` (`cnn.resnet18_8s`).
    pub(crate) fn new(rn: VarBuilder, cfg: &PerspNetConfig) -> Result<Self> {
        let (s, e, m) = (cfg.init_std, cfg.bn_eps, cfg.bn_momentum);
        let w0 = cfg.encoder_widths[0];
        let conv1 = Conv2d::new(rn.pp("conv1"), 3, w0, 7, 2, 3, false, s)?;
        let bn1 = BatchNorm2d::new(rn.pp("bn1"), w0, s, e, m)?;
        let mut layers = Vec::new();
        let mut c_in = w0;
        for (i, &w) in cfg.encoder_widths.iter().enumerate() {
            let stride = if i == 0 { 1 } else { 2 };
            let lv = rn.pp(format!("layer{}", i + 1));
            let b0 = BasicBlock::new(lv.pp("0"), c_in, w, stride, cfg)?;
            let b1 = BasicBlock::new(lv.pp("1"), w, w, 1, cfg)?;
            layers.push(vec![b0, b1]);
            c_in = w;
        }
        Ok(Self { conv1, bn1, layers })
    }

    /// The stem's output (stride 2, after its BN and ReLU) and the four stages'
    /// outputs (strides 4, 8, 16, 32).
    pub(crate) fn forward(&self, x: &Tensor, train: bool) -> Result<(Tensor, [Tensor; 4])> {
        let x2s = self
            .bn1
            .forward_act(&self.conv1.forward(x)?, train, Act::Relu)?;
        let mut y = max_pool_3x3_s2_p1(&x2s)?;
        let mut outs = Vec::with_capacity(4);
        for layer in &self.layers {
            for block in layer {
                y = block.forward_t(&y, train)?;
            }
            outs.push(y.clone());
        }
        let outs: [Tensor; 4] = outs.try_into().expect("4 stages");
        Ok((x2s, outs))
    }
}

/// The encoder's outputs (all `B x C x h x w`).
#[derive(Debug, Clone)]
pub struct EncoderFeatures {
    /// Stride 2: the stem (conv, BN, ReLU) before the max-pool, as the official
    /// `models/resnet.py` returns it, `encoder_widths[0]` channels.
    pub x2s: Tensor,
    /// Stride 4: `layer1`, `encoder_widths[0]` channels.
    pub x4s: Tensor,
    /// Stride 8: `layer2`, `encoder_widths[1]` channels.
    pub x8s: Tensor,
    /// Stride 16: `layer3`, `encoder_widths[2]` channels.
    pub x16s: Tensor,
    /// Stride 32: `layer4`, `encoder_widths[3]` channels.
    pub x32s: Tensor,
    /// Stride 32: 3x3 conv + BN + ReLU of `x32s`, `fc_channels` channels.
    pub fc: Tensor,
}

/// Dense (per-pixel) outputs of the encoder and both decoders.
#[derive(Debug, Clone)]
pub struct DenseOutput {
    /// Encoder features and skips.
    pub encoder: EncoderFeatures,
    /// 2D decoder stage outputs (after conv + BN + LeakyReLU, before
    /// up-sampling) at strides 16, 8, 4, 2 with `decoder_widths` channels.
    pub decoder_2d: Vec<Tensor>,
    /// 3D (UV) decoder stage outputs at strides 16, 8, 4, 2.
    pub decoder_uv: Vec<Tensor>,
    /// Full-resolution image features `B x feature_channels x H x W`.
    pub image_features: Tensor,
    /// Segmentation logits `B x 2 x H x W` (class 1 = face).
    pub seg_logits: Tensor,
    /// Full-resolution UV features `B x feature_channels x H x W`.
    pub uv_features: Tensor,
    /// UV position map `B x 3 x H x W` in `[-1, 1]` (tanh), in units of
    /// [`UV_SCALE`] x canonical mesh coordinates.
    pub uv_map: Tensor,
}

/// Outputs of [`PerspNet::forward`].
#[derive(Debug, Clone)]
pub struct PerspNetOutput {
    /// Encoder, decoders and dense maps.
    pub dense: DenseOutput,
    /// Assignment logits `B x M x V` (softmax over the last axis gives M).
    pub assign_logits: Tensor,
    /// Vertices X read bilinearly from the UV map at the vertex UVs, `B x V x 3`
    /// (UV-map units, i.e. `9 x` canonical; the shape loss compares to `9 x model`).
    pub vertices: Tensor,
}

impl PerspNetOutput {
    /// The soft assignment M = softmax(logits) over vertices, `B x M x V`.
    pub fn assignment(&self) -> Result<Tensor> {
        softmax_last(&self.assign_logits)
    }

    /// `M X`: the 3D point corresponding to each sampled pixel, `B x M x 3`,
    /// in UV-map units (divide by [`UV_SCALE`] for canonical coordinates).
    pub fn correspondences(&self) -> Result<Tensor> {
        self.assignment()?.matmul(&self.vertices)
    }
}

/// PerspNet (official `DeformNetUV2` with its `Resnet18_8s` backbone).
#[derive(Debug, Clone)]
pub struct PerspNet {
    cfg: PerspNetConfig,
    trunk: ResNetTrunk,
    fc: ConvBn,
    dec_2d: Vec<ConvBn>,
    final_2d: ConvBn,
    seg: Conv2d,
    dec_uv: Vec<ConvBn>,
    final_uv: ConvBn,
    uv: Conv2d,
    instance_color: PointLinear,
    instance_global: [PointLinear; 2],
    category_global: [PointLinear; 2],
    assignment: [PointLinear; 3],
    sampler: PointSampler,
    dropout_rng: std::sync::Arc<std::sync::Mutex<arkit_core::Rng>>,
}

impl PerspNet {
    /// Builds the network with fresh variables in `vb` (initialised like the
    /// official `init_weights('normal', 0.02)` when `vb` is backed by a
    /// [`VarMap`]). `vertex_uv` is the `V x 2` table of vertex UV coordinates in
    /// `[0, 1]` (`u` along the width), at which the UV maps are read.
    pub fn new(cfg: &PerspNetConfig, vertex_uv: &Tensor, vb: VarBuilder) -> Result<Self> {
        cfg.validate().map_err(candle_core::Error::msg)?;
        let (nv, two) = vertex_uv.dims2()?;
        if nv != cfg.vertices || two != 2 {
            candle_core::bail!(
                "vertex_uv must be {} x 2, got {:?}",
                cfg.vertices,
                vertex_uv.dims()
            );
        }
        let (s, e, m) = (cfg.init_std, cfg.bn_eps, cfg.bn_momentum);
        let [w0, w1, w2, w3] = cfg.encoder_widths;
        let [d0, d1, d2, d3] = cfg.decoder_widths;
        let f = cfg.feature_channels;
        let leaky = Act::Leaky(0.1);

        let cnn = vb.pp("cnn");
        let rn = cnn.pp("resnet18_8s");
        let trunk = ResNetTrunk::new(rn.clone(), cfg)?;
        let fc = ConvBn::new(rn.pp("fc"), w3, cfg.fc_channels, 3, 1, Act::Relu, s, e, m)?;

        let cb = |name: &str, ci: usize, co: usize| {
            ConvBn::new(cnn.pp(name), ci, co, 3, 1, leaky, s, e, m)
        };
        let dec_2d = vec![
            cb("conv16s", cfg.fc_channels + w2, d0)?,
            cb("conv8s", d0 + w1, d1)?,
            cb("conv4s", d1 + w0, d2)?,
            cb("conv2s", d2 + w0, d3)?,
        ];
        let final_2d = cb("final", d3 + 3, f)?;
        let seg = Conv2d::new(cnn.pp("seg"), f, 2, 1, 1, 0, true, s)?;
        let dec_uv = vec![
            cb("conv16s_uv", cfg.fc_channels, d0)?,
            cb("conv8s_uv", d0, d1)?,
            cb("conv4s_uv", d1, d2)?,
            cb("conv2s_uv", d2, d3)?,
        ];
        let final_uv = cb("final_uv", d3, f)?;
        let uv = Conv2d::new(cnn.pp("uv"), f, 3, 1, 1, 0, true, s)?;

        let instance_color = PointLinear::new(vb.pp("instance_color.0"), f, cfg.color_channels, s)?;
        let lc = cfg.local_channels();
        let (gh, gc) = (cfg.global_hidden, cfg.global_channels);
        let instance_global = [
            PointLinear::new(vb.pp("instance_global.0"), lc, gh, s)?,
            PointLinear::new(vb.pp("instance_global.2"), gh, gc, s)?,
        ];
        let category_global = [
            PointLinear::new(vb.pp("category_global.0"), f, gh, s)?,
            PointLinear::new(vb.pp("category_global.2"), gh, gc, s)?,
        ];
        let [a0, a1] = cfg.assign_hidden;
        let assignment = [
            PointLinear::new(vb.pp("assignment.0"), cfg.assign_in_channels(), a0, s)?,
            PointLinear::new(vb.pp("assignment.2"), a0, a1, s)?,
            PointLinear::new(vb.pp("assignment.4"), a1, cfg.vertices, s)?,
        ];
        let sampler = {
            let uv = vertex_uv.to_dtype(DType::F32)?.to_vec2::<f32>()?;
            PointSampler::from_uv(&uv, cfg.input_size, cfg.input_size, vb.device())?
        };
        Ok(Self {
            dropout_rng: std::sync::Arc::new(std::sync::Mutex::new(arkit_core::Rng::new(0))),
            cfg: cfg.clone(),
            trunk,
            fc,
            dec_2d,
            final_2d,
            seg,
            dec_uv,
            final_uv,
            uv,
            instance_color,
            instance_global,
            category_global,
            assignment,
            sampler,
        })
    }

    /// The configuration this network was built with.
    pub fn config(&self) -> &PerspNetConfig {
        &self.cfg
    }

    /// Runs the encoder on a normalised `B x 3 x H x W` image.
    pub fn encode(&self, x: &Tensor, train: bool) -> Result<EncoderFeatures> {
        let (x2s, [x4s, x8s, x16s, x32s]) = self.trunk.forward(x, train)?;
        let fc = self.fc.forward_t(&x32s, train)?;
        Ok(EncoderFeatures {
            x2s,
            x4s,
            x8s,
            x16s,
            x32s,
            fc,
        })
    }

    /// Restarts the dropout generator from `seed` (training calls it every step, so a
    /// run, and a resumed run, follow from its seed).
    pub(crate) fn seed_dropout(&self, seed: u64) {
        *self.dropout_rng.lock().expect("dropout generator") = arkit_core::Rng::new(seed);
    }

    /// Runs the encoder and both decoders (the official `Resnet18_8s.forward`).
    pub fn forward_dense(&self, img: &Tensor, train: bool) -> Result<DenseOutput> {
        let enc = self.encode(img, train)?;
        let p = self.cfg.dropout;
        let mut rng = self.dropout_rng.lock().expect("dropout generator");
        let x16 = upsample2x_bilinear(&enc.fc)?;

        // 2D decoder with skips; dropout after the stride-4 and stride-2 up-samplings.
        let skips = [&enc.x16s, &enc.x8s, &enc.x4s, &enc.x2s];
        let mut fm = x16.clone();
        let mut decoder_2d = Vec::with_capacity(4);
        for (i, (stage, skip)) in self.dec_2d.iter().zip(skips).enumerate() {
            let y = stage.forward_t(&Tensor::cat(&[&fm, skip], 1)?, train)?;
            decoder_2d.push(y.clone());
            fm = upsample2x_bilinear(&y)?;
            if i == 1 || i == 2 {
                fm = dropout2d(&fm, p, train.then_some(&mut *rng))?;
            }
        }
        let image_features = self
            .final_2d
            .forward_t(&Tensor::cat(&[&fm, img], 1)?, train)?;
        let seg_logits = self.seg.forward(&image_features)?;

        // 3D (UV) decoder without skips.
        let mut fm = x16;
        let mut decoder_uv = Vec::with_capacity(4);
        for (i, stage) in self.dec_uv.iter().enumerate() {
            let y = stage.forward_t(&fm, train)?;
            decoder_uv.push(y.clone());
            fm = upsample2x_bilinear(&y)?;
            if i == 1 || i == 2 {
                fm = dropout2d(&fm, p, train.then_some(&mut *rng))?;
            }
        }
        let uv_features = self.final_uv.forward_t(&fm, train)?;
        let uv_map = self.uv.forward(&uv_features)?.tanh()?;
        Ok(DenseOutput {
            encoder: enc,
            decoder_2d,
            decoder_uv,
            image_features,
            seg_logits,
            uv_features,
            uv_map,
        })
    }

    /// Full forward pass: [`PerspNet::forward_dense`], then [`PerspNet::forward_head`].
    ///
    /// * `img`: normalised `B x 3 x H x W` crop (see [`crate::layers::imagenet_normalize`]).
    /// * `choose`: `B x M` (u32 or i64) flat pixel indices `y * W + x` of the sampled pixels.
    /// * `train`: batch-norm batch statistics and channel dropout when true.
    pub fn forward(&self, img: &Tensor, choose: &Tensor, train: bool) -> Result<PerspNetOutput> {
        let dense = self.forward_dense(img, train)?;
        let (assign_logits, vertices) = self.forward_head(&dense, choose)?;
        Ok(PerspNetOutput {
            dense,
            assign_logits,
            vertices,
        })
    }

    /// The correspondence head on dense outputs already computed (inference runs the
    /// dense network once, reads the mask off it, chooses the pixels, then calls this):
    /// the assignment logits `B x M x V` and the vertices read from the UV map
    /// `B x V x 3` (UV-map units), for the `B x M` pixels `choose` of `dense`'s images.
    pub fn forward_head(&self, dense: &DenseOutput, choose: &Tensor) -> Result<(Tensor, Tensor)> {
        self.head(
            &dense.image_features,
            &dense.uv_features,
            &dense.uv_map,
            choose,
        )
    }

    /// [`PerspNet::forward_head`] on the three dense outputs it reads.
    pub(crate) fn head(
        &self,
        image_features: &Tensor,
        uv_features: &Tensor,
        uv_map: &Tensor,
        choose: &Tensor,
    ) -> Result<(Tensor, Tensor)> {
        let (b, m) = choose.dims2()?;
        let w = image_features.dim(3)?;

        // Local 2D features: sampled image features (1x1 conv + ReLU) ++ position encoding.
        let emb = gather_pixels(image_features, choose)?; // B x M x F
        let color = relu(&self.instance_color.forward(&emb)?)?;
        let local = if self.cfg.position_encoding {
            let pos = positional_encoding_points(choose, self.cfg.pos_channels, w, emb.device())?
                .to_dtype(color.dtype())?;
            Tensor::cat(&[&color, &pos], 2)? // B x M x 128
        } else {
            color
        };
        let g2 = mlp_global(&self.instance_global, &local)?; // B x 1 x 1024

        // 3D global feature from the UV features read at the vertex UVs.
        let uv_local = self.sampler.sample(uv_features)?.transpose(1, 2)?; // B x V x F
        let g3 = mlp_global(&self.category_global, &uv_local.contiguous()?)?; // B x 1 x 1024

        // Assignment MLP on [local, g2, g3]; the first layer is applied to the three
        // parts separately (identical result, avoids materialising B x M x 2176).
        // The global part and the bias are one row per batch, added to every point.
        let a0 = &self.assignment[0];
        let wt = a0.weight();
        let lc = self.cfg.local_channels();
        let gc = self.cfg.global_channels;
        let h_local = point_linear(&local, &wt.narrow(1, 0, lc)?, None)?; // B x M x A0
        let global = Tensor::cat(&[&g2, &g3], 2)?; // B x 1 x 2 gc
        let h_global = point_linear(&global, &wt.narrow(1, lc, 2 * gc)?, Some(a0.bias()))?;
        let h = add_rows_relu(&h_local, &h_global)?;
        let h = relu(&self.assignment[1].forward(&h)?)?;
        let assign_logits = self.assignment[2].forward(&h)?; // B x M x V
        debug_assert_eq!(assign_logits.dims(), &[b, m, self.cfg.vertices]);

        let vertices = self.sampler.sample(uv_map)?.transpose(1, 2)?.contiguous()?; // B x V x 3
        Ok((assign_logits, vertices))
    }
}

fn mlp_global(layers: &[PointLinear; 2], x: &Tensor) -> Result<Tensor> {
    let h = relu(&layers[0].forward(x)?)?;
    let h = relu(&layers[1].forward(&h)?)?;
    mean_points(&h)
}

/// Trainable variables of a [`VarMap`]: everything except batch-norm running statistics.
pub fn trainable_vars(varmap: &VarMap) -> Vec<Var> {
    named_trainable_vars(varmap)
        .into_iter()
        .map(|(_, v)| v)
        .collect()
}

/// [`trainable_vars`] with their names (the checkpoint keys), sorted by name.
pub fn named_trainable_vars(varmap: &VarMap) -> Vec<(String, Var)> {
    let data = varmap.data().lock().expect("varmap lock");
    let mut named: Vec<(String, Var)> = data
        .iter()
        .filter(|(k, _)| !k.contains("running_"))
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    named.sort_by(|a, b| a.0.cmp(&b.0));
    named
}

/// Number of trainable scalars whose variable name starts with `prefix` (`""` for all).
pub fn parameter_count(varmap: &VarMap, prefix: &str) -> usize {
    let data = varmap.data().lock().expect("varmap lock");
    data.iter()
        .filter(|(k, _)| !k.contains("running_") && k.starts_with(prefix))
        .map(|(_, v)| v.elem_count())
        .sum()
}

/// A synthetic `V x 2` vertex-UV table on a jittered grid inside `[0.05, 0.95]^2`,
/// for tests and benchmarks when the real ARKit UV table is not at hand.
pub fn synthetic_vertex_uv(vertices: usize, device: &Device) -> Result<Tensor> {
    let side = (vertices as f64).sqrt().ceil() as usize;
    let mut v = Vec::with_capacity(vertices * 2);
    for i in 0..vertices {
        let (r, c) = (i / side, i % side);
        let jit = ((i * 7919) % 97) as f64 / 97.0 * 0.3 / side as f64;
        v.push((0.05 + 0.9 * (c as f64 + 0.5) / side as f64 + jit) as f32);
        v.push((0.05 + 0.9 * (r as f64 + 0.5) / side as f64 - jit) as f32);
    }
    Tensor::from_vec(v, (vertices, 2), device)
}
