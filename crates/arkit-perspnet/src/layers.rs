//! Building blocks that candle 0.11 does not provide in a differentiable form:
//! bilinear x2 up-sampling with `align_corners=True`, grid-sample-style
//! bilinear point reads (`align_corners=False`, zero padding), 3x3/2 max
//! pooling with padding, channel-wise dropout, the official 2D sine/cosine
//! position encoding, ImageNet normalisation, and conv / batch-norm layers
//! initialised like the official `init_weights(init_type='normal', 0.02)`.
//!
//! On f32 CPU tensors the layers on the training path are single candle ops
//! with our own kernels and one-pass backwards (`ops`: convolution, batch norm
//! fused with its activation, ReLU, the residual join, log-softmax, entropy,
//! per-point linear layers, the up-sampling, max pooling, the point reads):
//! candle's backward creates and accumulates a gradient tensor per node, so
//! every node removed from a large tensor's path saves passes over it. Each
//! is tested against the candle composition it replaces, which stays the
//! path on other devices (what this saves: docs/performance.md, "Where the
//! PerspNet time goes").

// The activation and the interpolation weights are defined beside the kernels that
// use them; this module is their public path.
pub use crate::ops::{Act, interp_matrix_align_corners};
use crate::ops::{
    Activation, AddRelu, AddRowsRelu, ApplyF32Op, FastConv2d, FusedBn, GatherPixels,
    LogSoftmaxLast, MaxPool3x3S2, MeanPoints, PointLinearOp, ResizeAlignCorners, RowEntropy,
    SamplePoints, Taps, with_f32,
};
use candle_core::{D, DType, Device, Module, ModuleT, Result, Tensor};
use candle_nn::{BatchNorm, Init, Linear, VarBuilder};
use rayon::prelude::*;

// The loader's ImageNet channel means and standard deviations: one definition.
use arkit_data::loader::{IMAGENET_MEAN, IMAGENET_STD};

/// Normalises a `B x 3 x H x W` RGB batch with values in `[0, 1]` by the
/// ImageNet mean and standard deviation.
pub fn imagenet_normalize(img: &Tensor) -> Result<Tensor> {
    let dev = img.device();
    let mean = Tensor::new(&IMAGENET_MEAN, dev)?
        .to_dtype(img.dtype())?
        .reshape((1, 3, 1, 1))?;
    let std = Tensor::new(&IMAGENET_STD, dev)?
        .to_dtype(img.dtype())?
        .reshape((1, 3, 1, 1))?;
    img.broadcast_sub(&mean)?.broadcast_div(&std)
}

/// Bilinear up-sampling of a `B x C x H x W` tensor by 2 with
/// `align_corners=True` (PyTorch `nn.UpsamplingBilinear2d(scale_factor=2)`),
/// written as two matmuls with fixed interpolation matrices so that it is
/// differentiable.
pub fn upsample2x_bilinear(x: &Tensor) -> Result<Tensor> {
    let (_b, _c, h, w) = x.dims4()?;
    upsample_bilinear_align_corners(x, 2 * h, 2 * w)
}

/// Bilinear resize of a `B x C x H x W` tensor to `out_h x out_w` with
/// `align_corners=True`, differentiable. On f32 CPU tensors one op with two
/// taps per output per axis, forward and backward (`ResizeAlignCorners`);
/// elsewhere [`upsample_bilinear_matmul`].
pub fn upsample_bilinear_align_corners(x: &Tensor, out_h: usize, out_w: usize) -> Result<Tensor> {
    if x.dtype() != DType::F32 || !x.device().is_cpu() {
        return upsample_bilinear_matmul(x, out_h, out_w);
    }
    let (_b, _c, h, w) = x.dims4()?;
    x.contiguous()?.apply_f32_op1(ResizeAlignCorners {
        rows: Taps::new(h, out_h),
        cols: Taps::new(w, out_w),
    })
}

/// [`upsample_bilinear_align_corners`] as two matmuls with the fixed
/// interpolation matrices (any device and dtype; candle differentiates it).
pub fn upsample_bilinear_matmul(x: &Tensor, out_h: usize, out_w: usize) -> Result<Tensor> {
    let (_b, _c, h, w) = x.dims4()?;
    let dev = x.device();
    // (W, out_w): x @ A_w^T resizes the last dimension.
    let aw = Tensor::from_vec(interp_matrix_align_corners(w, out_w), (out_w, w), dev)?
        .to_dtype(x.dtype())?
        .t()?
        .contiguous()?;
    let ah = Tensor::from_vec(interp_matrix_align_corners(h, out_h), (out_h, h), dev)?
        .to_dtype(x.dtype())?;
    let y = x.contiguous()?.broadcast_matmul(&aw)?; // B x C x H x out_w
    ah.broadcast_matmul(&y) // B x C x out_h x out_w
}

/// Pre-computed bilinear reads of a `B x C x H x W` map at fixed normalised
/// coordinates, equal to `F.grid_sample(map, grid, mode='bilinear',
/// padding_mode='zeros', align_corners=False)` with `grid = 2 * uv - 1`.
///
/// The reads are an `index_select` of the four neighbours followed by a
/// weighted sum, so gradients flow to the map.
#[derive(Debug, Clone)]
pub struct PointSampler {
    /// Flat neighbour indices `y * W + x`, laid out as 4 blocks of `P` (u32).
    indices: Tensor,
    /// Neighbour weights `4 x P` (zero for out-of-range neighbours).
    weights: Tensor,
    /// The same indices and weights on the host, for the CPU op.
    taps: std::sync::Arc<(Vec<u32>, Vec<f32>)>,
    points: usize,
    height: usize,
    width: usize,
}

impl PointSampler {
    /// Builds a sampler for `uv` (`P x 2`, columns `(u, v)` in `[0, 1]`, `u`
    /// along the width) on an `height x width` map.
    pub fn new(uv: &Tensor, height: usize, width: usize) -> Result<Self> {
        let uv = uv.to_dtype(DType::F32)?.to_vec2::<f32>()?;
        Self::from_uv(&uv, height, width, &Device::Cpu)
    }

    /// Builds a sampler from `(u, v)` pairs on `device` (see [`PointSampler::new`]).
    pub(crate) fn from_uv(
        uv: &[Vec<f32>],
        height: usize,
        width: usize,
        device: &Device,
    ) -> Result<Self> {
        let p = uv.len();
        let mut idx = vec![0u32; 4 * p];
        let mut wts = vec![0f32; 4 * p];
        for (k, row) in uv.iter().enumerate() {
            if row.len() < 2 {
                candle_core::bail!("uv rows must have 2 entries");
            }
            // align_corners=False: pixel = ((g + 1) * size - 1) / 2 = uv * size - 0.5
            let x = row[0] as f64 * width as f64 - 0.5;
            let y = row[1] as f64 * height as f64 - 0.5;
            let x0 = x.floor();
            let y0 = y.floor();
            let fx = x - x0;
            let fy = y - y0;
            let corners = [
                (x0, y0, (1.0 - fx) * (1.0 - fy)),
                (x0 + 1.0, y0, fx * (1.0 - fy)),
                (x0, y0 + 1.0, (1.0 - fx) * fy),
                (x0 + 1.0, y0 + 1.0, fx * fy),
            ];
            for (c, &(cx, cy, w)) in corners.iter().enumerate() {
                let inside =
                    cx >= 0.0 && cy >= 0.0 && cx <= (width - 1) as f64 && cy <= (height - 1) as f64;
                if inside {
                    idx[c * p + k] = (cy as usize * width + cx as usize) as u32;
                    wts[c * p + k] = w as f32;
                }
            }
        }
        Ok(Self {
            indices: Tensor::from_vec(idx.clone(), 4 * p, device)?,
            weights: Tensor::from_vec(wts.clone(), (4, p), device)?,
            taps: std::sync::Arc::new((idx, wts)),
            points: p,
            height,
            width,
        })
    }

    /// The flat neighbour indices (4 blocks of `P`) and their weights (`4 x P`),
    /// for the ONNX export's constant gather.
    pub(crate) fn taps(&self) -> (&[u32], &[f32]) {
        (&self.taps.0, &self.taps.1)
    }

    /// Number of sampled points `P`.
    pub fn points(&self) -> usize {
        self.points
    }

    /// Reads `map` (`B x C x H x W`) at the points: returns `B x C x P`.
    pub fn sample(&self, map: &Tensor) -> Result<Tensor> {
        let (b, c, h, w) = map.dims4()?;
        if (h, w) != (self.height, self.width) {
            candle_core::bail!(
                "PointSampler built for {}x{}, got {h}x{w}",
                self.height,
                self.width
            );
        }
        if map.dtype() == DType::F32 && map.device().is_cpu() {
            return map.contiguous()?.apply_f32_op1(SamplePoints {
                taps: self.taps.clone(),
                points: self.points,
            });
        }
        let flat = map.reshape((b, c, h * w))?;
        let g = flat.index_select(&self.indices, 2)?; // B x C x 4P
        let g = g.reshape((b, c, 4, self.points))?;
        let wts = self
            .weights
            .to_dtype(map.dtype())?
            .reshape((1, 1, 4, self.points))?;
        g.broadcast_mul(&wts)?.sum(2)
    }
}

/// Gathers per-batch pixels: `feat` is `B x C x H x W`, `choose` is `B x M`
/// (u32 flat indices `y * W + x`); returns `B x M x C` (points-major, ready for
/// the per-point linear layers). On f32 CPU tensors one op (no transposed copy of
/// the map; the backward scatters into one zeroed map).
pub fn gather_pixels(feat: &Tensor, choose: &Tensor) -> Result<Tensor> {
    let (b, c, h, w) = feat.dims4()?;
    let (b2, m) = choose.dims2()?;
    if b != b2 {
        candle_core::bail!("gather_pixels: batch {b} vs choose batch {b2}");
    }
    if feat.dtype() == DType::F32 && feat.device().is_cpu() {
        let ids: Vec<u32> = choose.to_dtype(DType::U32)?.flatten_all()?.to_vec1()?;
        if let Some(bad) = ids.iter().find(|i| **i as usize >= h * w) {
            candle_core::bail!("gather_pixels: pixel {bad} outside a {h}x{w} map");
        }
        return feat.contiguous()?.apply_f32_op1(GatherPixels {
            ids: std::sync::Arc::new(ids),
            m,
        });
    }
    // Flatten batch and pixels into one axis: (B*HW) x C.
    let flat = feat
        .reshape((b, c, h * w))?
        .transpose(1, 2)?
        .contiguous()?
        .reshape((b * h * w, c))?;
    let offs = Tensor::arange(0u32, b as u32, choose.device())?
        .affine((h * w) as f64, 0.0)?
        .reshape((b, 1))?;
    let ids = choose
        .to_dtype(DType::U32)?
        .broadcast_add(&offs)?
        .flatten_all()?;
    flat.index_select(&ids, 0)?.reshape((b, m, c))
}

/// The official `positionalencoding2d(d_model, H, W)` evaluated at pixel
/// `(x, y)`: channel `2k` / `2k+1` of the first half are `sin` / `cos` of
/// `x * exp(-2k ln(10000) / (d/2))`, the second half the same with `y`.
pub fn positional_encoding_at(d_model: usize, x: f64, y: f64) -> Vec<f32> {
    let half = d_model / 2;
    let mut pe = vec![0f32; d_model];
    for (k, i) in (0..half).step_by(2).enumerate() {
        let div = (i as f64 * -(10000f64.ln() / half as f64)).exp();
        let _ = k;
        pe[i] = (x * div).sin() as f32;
        pe[i + 1] = (x * div).cos() as f32;
        pe[half + i] = (y * div).sin() as f32;
        pe[half + i + 1] = (y * div).cos() as f32;
    }
    pe
}

/// The full `d_model x H x W` position-encoding map (row-major), as the
/// official code pre-computes it.
pub fn positional_encoding_map(d_model: usize, height: usize, width: usize) -> Vec<f32> {
    let mut out = vec![0f32; d_model * height * width];
    for y in 0..height {
        for x in 0..width {
            let pe = positional_encoding_at(d_model, x as f64, y as f64);
            for (c, v) in pe.into_iter().enumerate() {
                out[(c * height + y) * width + x] = v;
            }
        }
    }
    out
}

/// Position encodings of the chosen pixels: `choose` is `B x M` (u32 flat
/// indices in an image of width `width`); returns `B x M x d_model`.
pub(crate) fn positional_encoding_points(
    choose: &Tensor,
    d_model: usize,
    width: usize,
    device: &Device,
) -> Result<Tensor> {
    let (b, m) = choose.dims2()?;
    let ids = choose
        .to_dtype(DType::U32)?
        .flatten_all()?
        .to_vec1::<u32>()?;
    let mut out = Vec::with_capacity(b * m * d_model);
    for id in ids {
        let (x, y) = (id as usize % width, id as usize / width);
        out.extend(positional_encoding_at(d_model, x as f64, y as f64));
    }
    Tensor::from_vec(out, (b, m, d_model), device)
}

/// Max pooling with kernel 3, stride 2, padding 1 (the ResNet stem), PyTorch's
/// `MaxPool2d(3, 2, 1)`: padding never wins, and the gradient goes to the first
/// maximum of each window in row-major order. On f32 CPU tensors one op
/// (forward one pass, backward the same scan scattering each output's gradient);
/// elsewhere [`max_pool_3x3_s2_p1_views`].
pub fn max_pool_3x3_s2_p1(x: &Tensor) -> Result<Tensor> {
    if x.dtype() != DType::F32 || !x.device().is_cpu() {
        return max_pool_3x3_s2_p1_views(x);
    }
    x.contiguous()?.apply_f32_op1(MaxPool3x3S2)
}

/// [`max_pool_3x3_s2_p1`] written with strided views and `maximum` (candle
/// differentiates it; any device). Padding is with zeros, which equals
/// PyTorch's `-inf` padding only because the stem's input is non-negative
/// (it follows a ReLU).
pub fn max_pool_3x3_s2_p1_views(x: &Tensor) -> Result<Tensor> {
    let (_b, _c, h, w) = x.dims4()?;
    let oh = (h + 2 - 3) / 2 + 1;
    let ow = (w + 2 - 3) / 2 + 1;
    // pad so that there are 2*o + 1 (+1 to make it even) rows/cols available
    let xp = x.pad_with_zeros(2, 1, 2 * oh + 2 - (h + 1))?;
    let xp = xp.pad_with_zeros(3, 1, 2 * ow + 2 - (w + 1))?;
    let rows = |t: &Tensor, off: usize| -> Result<Tensor> {
        let (b, c, _, ww) = t.dims4()?;
        t.narrow(2, off, 2 * oh)?
            .reshape((b, c, oh, 2, ww))?
            .narrow(3, 0, 1)?
            .squeeze(3)
    };
    let r = rows(&xp, 0)?
        .maximum(&rows(&xp, 1)?)?
        .maximum(&rows(&xp, 2)?)?;
    let cols = |t: &Tensor, off: usize| -> Result<Tensor> {
        let (b, c, hh, _) = t.dims4()?;
        t.narrow(3, off, 2 * ow)?
            .reshape((b, c, hh, ow, 2))?
            .narrow(4, 0, 1)?
            .squeeze(4)
    };
    cols(&r, 0)?.maximum(&cols(&r, 1)?)?.maximum(&cols(&r, 2)?)
}

/// Channel-wise dropout (PyTorch `nn.Dropout2d`): zeroes whole channels of a
/// `B x C x H x W` tensor with probability `p` and rescales the rest by
/// `1 / (1 - p)`, the channels drawn from `rng` (ours, seeded: candle's CPU generator
/// cannot be). Identity without a generator (evaluation) or when `p == 0`.
pub fn dropout2d(x: &Tensor, p: f64, rng: Option<&mut arkit_core::Rng>) -> Result<Tensor> {
    let Some(rng) = rng else {
        return Ok(x.clone());
    };
    if p <= 0.0 {
        return Ok(x.clone());
    }
    let (b, c, _, _) = x.dims4()?;
    let scale = (1.0 / (1.0 - p)) as f32;
    let keep: Vec<f32> = (0..b * c)
        .map(|_| if rng.next_f64() >= p { scale } else { 0.0 })
        .collect();
    let keep = Tensor::from_vec(keep, (b, c, 1, 1), x.device())?.to_dtype(x.dtype())?;
    x.broadcast_mul(&keep)
}

/// LeakyReLU with negative slope `slope` (one fused op, see `activate`).
pub fn leaky_relu(x: &Tensor, slope: f64) -> Result<Tensor> {
    activate(x, Act::Leaky(slope))
}

/// ReLU as one fused op (see `activate`).
pub fn relu(x: &Tensor) -> Result<Tensor> {
    activate(x, Act::Relu)
}

/// An activation as one op whose backward is one pass, `grad * act'(y)` read
/// from the output `y` (ReLU and LeakyReLU keep the sign), instead of candle's
/// five tensors for `relu`'s backward (compare, convert, multiply, ...).
/// f32 CPU tensors; other devices fall back to candle's ops.
pub(crate) fn activate(x: &Tensor, act: Act) -> Result<Tensor> {
    if x.dtype() != DType::F32 || !x.device().is_cpu() {
        return match act {
            Act::None => Ok(x.clone()),
            Act::Relu => x.relu(),
            Act::Leaky(s) => x.relu()?.affine(1.0 - s, 0.0)? + x.affine(s, 0.0)?,
        };
    }
    x.apply_f32_op1(Activation(act))
}

/// `relu(a + b)` as one op (the ResNet block's residual join); its backward
/// hands the same masked gradient to both inputs.
pub fn add_relu(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    if a.dtype() != DType::F32 || !a.device().is_cpu() || a.shape() != b.shape() {
        return (a + b)?.relu();
    }
    a.apply_f32_op2(b, AddRelu)
}

/// A 2-D convolution (`weight`: `out x in x k x k`, optional bias).
#[derive(Debug, Clone)]
pub struct Conv2d {
    weight: Tensor,
    bias: Option<Tensor>,
    stride: usize,
    padding: usize,
}

impl Conv2d {
    /// Creates a conv with weights `N(0, std)` and zero bias (if `bias`), named
    /// `weight` / `bias` under `vb`.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        vb: VarBuilder,
        c_in: usize,
        c_out: usize,
        k: usize,
        stride: usize,
        padding: usize,
        bias: bool,
        std: f64,
    ) -> Result<Self> {
        let weight = vb.get_with_hints(
            (c_out, c_in, k, k),
            "weight",
            Init::Randn {
                mean: 0.0,
                stdev: std,
            },
        )?;
        let bias = if bias {
            Some(vb.get_with_hints(c_out, "bias", Init::Const(0.0))?)
        } else {
            None
        };
        Ok(Self {
            weight,
            bias,
            stride,
            padding,
        })
    }
}

/// `t[..., start : start + len * stride : stride, ...]` along `dim` (the tensor
/// must have at least `start + len * stride` entries there).
fn strided_narrow(
    t: &Tensor,
    dim: usize,
    start: usize,
    len: usize,
    stride: usize,
) -> Result<Tensor> {
    if stride == 1 {
        return t.narrow(dim, start, len);
    }
    let y = t.narrow(dim, start, len * stride)?;
    let mut dims = y.dims().to_vec();
    dims[dim] = len;
    dims.insert(dim + 1, stride);
    y.reshape(dims)?.narrow(dim + 1, 0, 1)?.squeeze(dim + 1)
}

/// 2-D convolution as im2col (strided views stacked with tensor ops) plus one
/// matmul, so that forward and backward are dominated by GEMMs.
pub fn conv2d_im2col(x: &Tensor, weight: &Tensor, stride: usize, padding: usize) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    let (co, ci, kh, kw) = weight.dims4()?;
    if ci != c {
        candle_core::bail!("conv2d_im2col: input has {c} channels, kernel expects {ci}");
    }
    let ho = (h + 2 * padding - kh) / stride + 1;
    let wo = (w + 2 * padding - kw) / stride + 1;
    let wmat = weight.reshape((co, ci * kh * kw))?;
    if kh == 1 && kw == 1 && padding == 0 {
        let xs = strided_narrow(&strided_narrow(x, 2, 0, ho, stride)?, 3, 0, wo, stride)?;
        let cols = xs.contiguous()?.reshape((b, c, ho * wo))?;
        return wmat.broadcast_matmul(&cols)?.reshape((b, co, ho, wo));
    }
    // Pad so that every strided view fits: need (k - 1) + ho * stride rows.
    let need_h = kh - 1 + ho * stride;
    let need_w = kw - 1 + wo * stride;
    let xp = x
        .pad_with_zeros(2, padding, need_h.saturating_sub(h + padding))?
        .pad_with_zeros(3, padding, need_w.saturating_sub(w + padding))?;
    let mut views = Vec::with_capacity(kh * kw);
    for di in 0..kh {
        let rows = strided_narrow(&xp, 2, di, ho, stride)?;
        for dj in 0..kw {
            views.push(strided_narrow(&rows, 3, dj, wo, stride)?);
        }
    }
    let cols = Tensor::stack(&views, 2)?.reshape((b, c * kh * kw, ho * wo))?;
    wmat.broadcast_matmul(&cols)?.reshape((b, co, ho, wo))
}

/// 2-D convolution (f32, CPU) with candle's fast forward and a GEMM-based
/// backward (see the crate docs); numerically equal to `x.conv2d(w, padding, stride, 1, 1)`.
pub fn conv2d_fast(x: &Tensor, weight: &Tensor, stride: usize, padding: usize) -> Result<Tensor> {
    if x.dtype() != DType::F32 || !x.device().is_cpu() {
        return x.conv2d(weight, padding, stride, 1, 1);
    }
    x.contiguous()?
        .apply_f32_op2(&weight.contiguous()?, FastConv2d { stride, padding })
}

/// Convolution back-end used by [`Conv2d`]; chosen once from the
/// `PERSPNET_CONV` environment variable (`fast` (default), `builtin`, `im2col`).
fn conv_backend() -> &'static str {
    static B: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    B.get_or_init(|| std::env::var("PERSPNET_CONV").unwrap_or_else(|_| "fast".into()))
}

impl Module for Conv2d {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let y = match conv_backend() {
            "builtin" => x.conv2d(&self.weight, self.padding, self.stride, 1, 1)?,
            "im2col" => conv2d_im2col(x, &self.weight, self.stride, self.padding)?,
            _ => conv2d_fast(x, &self.weight, self.stride, self.padding)?,
        };
        match &self.bias {
            Some(b) => y.broadcast_add(&b.reshape((1, (), 1, 1))?),
            None => Ok(y),
        }
    }
}

/// candle's own batch norm initialised like the official code (kept as the
/// reference for [`BatchNorm2d`]): weight `N(1, std)`, bias 0,
/// running mean 0, running variance 1.
pub fn batch_norm(
    vb: VarBuilder,
    c: usize,
    std: f64,
    eps: f64,
    momentum: f64,
) -> Result<BatchNorm> {
    let running_mean = vb.get_with_hints(c, "running_mean", Init::Const(0.0))?;
    let running_var = vb.get_with_hints(c, "running_var", Init::Const(1.0))?;
    let weight = vb.get_with_hints(
        c,
        "weight",
        Init::Randn {
            mean: 1.0,
            stdev: std,
        },
    )?;
    let bias = vb.get_with_hints(c, "bias", Init::Const(0.0))?;
    BatchNorm::new_with_momentum(c, running_mean, running_var, weight, bias, eps, momentum)
}

/// A per-point linear layer (the official `Conv1d(c_in, c_out, 1)`) applied to
/// `... x C` features (any leading dimensions): `y = x Wᵀ + b`, variables
/// `weight` (`c_out x c_in`) and `bias`. On f32 CPU tensors it is one op whose
/// backward is three products over all points at once (`dx = g W`,
/// `dW = gᵀ x`, `db` the column sums of `g`), instead of candle's `Linear`,
/// which broadcasts the weight over the batch and sums the per-batch weight
/// and bias gradients back with strided reductions.
#[derive(Debug, Clone)]
pub struct PointLinear {
    weight: Tensor,
    bias: Tensor,
}

impl PointLinear {
    /// The layer with initialisation like the official code: weight
    /// `N(0, std)`, bias 0.
    pub fn new(vb: VarBuilder, c_in: usize, c_out: usize, std: f64) -> Result<Self> {
        let l = linear(vb, c_in, c_out, std)?;
        let bias = l.bias().cloned().expect("linear() makes a bias");
        Ok(Self {
            weight: l.weight().clone(),
            bias,
        })
    }

    /// The `c_out x c_in` weight.
    pub fn weight(&self) -> &Tensor {
        &self.weight
    }

    /// The bias (`c_out`).
    pub fn bias(&self) -> &Tensor {
        &self.bias
    }
}

impl Module for PointLinear {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        point_linear(x, &self.weight, Some(&self.bias))
    }
}

/// `x Wᵀ (+ b)` over the last dimension of `x` (any leading shape), one op on
/// f32 CPU tensors (see [`PointLinear`]); `weight` is `c_out x c_in`.
pub fn point_linear(x: &Tensor, weight: &Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
    if x.dtype() != DType::F32 || !x.device().is_cpu() {
        return Linear::new(weight.clone(), bias.cloned()).forward(x);
    }
    // Without a bias, a constant zero one (not tracked: no gradient is formed).
    let bias = match bias {
        Some(b) => b.contiguous()?,
        None => Tensor::zeros(weight.dim(0)?, DType::F32, x.device())?,
    };
    x.contiguous()?
        .apply_f32_op3(&weight.contiguous()?, &bias, PointLinearOp)
}

/// `relu(h + r)` where `h` is `B x M x C` and `r` (`B x 1 x C`) is added to
/// every row of its batch: one op; the backward hands `h` the masked gradient
/// and `r` its sum over the `M` rows (candle's broadcast would add a strided
/// reduction and three more tensors).
pub fn add_rows_relu(h: &Tensor, r: &Tensor) -> Result<Tensor> {
    let (b, _m, c) = h.dims3()?;
    if h.dtype() != DType::F32 || !h.device().is_cpu() || r.dims() != [b, 1, c] {
        return relu(&h.broadcast_add(r)?);
    }
    h.contiguous()?.apply_f32_op2(&r.contiguous()?, AddRowsRelu)
}

/// A per-point linear layer (the official `Conv1d(c_in, c_out, 1)`) applied
/// to `B x N x C` features; weight `N(0, std)`, bias 0 (candle's `Linear`;
/// [`PointLinear`] is the layer the model uses).
pub fn linear(vb: VarBuilder, c_in: usize, c_out: usize, std: f64) -> Result<Linear> {
    let w = vb.get_with_hints(
        (c_out, c_in),
        "weight",
        Init::Randn {
            mean: 0.0,
            stdev: std,
        },
    )?;
    let b = vb.get_with_hints(c_out, "bias", Init::Const(0.0))?;
    Ok(Linear::new(w, Some(b)))
}

/// Conv (no bias) + batch norm + activation.
#[derive(Debug, Clone)]
pub(crate) struct ConvBn {
    conv: Conv2d,
    bn: BatchNorm2d,
    act: Act,
}

impl ConvBn {
    /// Creates `conv` (named `{vb}.0`) and `bn` (named `{vb}.1`), mirroring an
    /// `nn.Sequential(Conv2d, BatchNorm2d, act)`.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        vb: VarBuilder,
        c_in: usize,
        c_out: usize,
        k: usize,
        stride: usize,
        act: Act,
        std: f64,
        eps: f64,
        momentum: f64,
    ) -> Result<Self> {
        let conv = Conv2d::new(vb.pp("0"), c_in, c_out, k, stride, k / 2, false, std)?;
        let bn = BatchNorm2d::new(vb.pp("1"), c_out, std, eps, momentum)?;
        Ok(Self { conv, bn, act })
    }

    /// Creates a conv + BN pair with explicit names (ResNet style).
    #[allow(clippy::too_many_arguments)]
    pub fn named(
        vb_conv: VarBuilder,
        vb_bn: VarBuilder,
        c_in: usize,
        c_out: usize,
        k: usize,
        stride: usize,
        act: Act,
        std: f64,
        eps: f64,
        momentum: f64,
    ) -> Result<Self> {
        let conv = Conv2d::new(vb_conv, c_in, c_out, k, stride, k / 2, false, std)?;
        let bn = BatchNorm2d::new(vb_bn, c_out, std, eps, momentum)?;
        Ok(Self { conv, bn, act })
    }
}

impl ModuleT for ConvBn {
    fn forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        self.bn.forward_act(&self.conv.forward(x)?, train, self.act)
    }
}

/// Mean over the points axis of `B x N x C` features, keeping `B x 1 x C`
/// (the official `AdaptiveAvgPool1d(1)`).
pub fn mean_points(x: &Tensor) -> Result<Tensor> {
    if x.dtype() != DType::F32 || !x.device().is_cpu() || x.rank() != 3 {
        return x.mean_keepdim(1);
    }
    x.contiguous()?.apply_f32_op1(MeanPoints)
}

/// The entropy `-sum(exp(l) l)` of each row of log-probabilities `l` (last
/// dimension), one op on f32 CPU tensors with a one-pass backward
/// (`dl = -g exp(l) (1 + l)`); the result drops the last dimension.
pub fn row_entropy(log_p: &Tensor) -> Result<Tensor> {
    if log_p.dtype() != DType::F32 || !log_p.device().is_cpu() || log_p.rank() == 0 {
        return (log_p.exp()? * log_p)?.sum(D::Minus1)?.neg();
    }
    log_p.contiguous()?.apply_f32_op1(RowEntropy)
}

/// Softmax over the last dimension computed as `exp(log_softmax)`.
pub(crate) fn softmax_last(x: &Tensor) -> Result<Tensor> {
    log_softmax_last(x)?.exp()
}

/// Log-softmax over the last dimension. On f32 CPU tensors one op, one pass
/// per row forward and one backward (`dx = g - softmax(x) sum(g)`, the softmax
/// read from the output), instead of candle's six ops and their backward
/// (the assignment logits are `B x M x 1,220`, the largest tensors of a step).
pub fn log_softmax_last(x: &Tensor) -> Result<Tensor> {
    if x.dtype() != DType::F32 || !x.device().is_cpu() || x.rank() == 0 {
        return candle_nn::ops::log_softmax(x, D::Minus1);
    }
    x.contiguous()?.apply_f32_op1(LogSoftmaxLast)
}

/// 2-D batch norm (PyTorch `BatchNorm2d` semantics: biased batch variance for
/// normalisation, unbiased for the running variance, momentum update) with a
/// fused CPU kernel for forward and backward. Variables: `weight`, `bias`,
/// `running_mean`, `running_var`.
#[derive(Debug, Clone)]
pub struct BatchNorm2d {
    weight: Tensor,
    bias: Tensor,
    running_mean: candle_core::Var,
    running_var: candle_core::Var,
    eps: f64,
    momentum: f64,
}

impl BatchNorm2d {
    /// Creates the layer initialised like the official code (weight `N(1, std)`,
    /// bias 0, running mean 0, running variance 1).
    pub fn new(vb: VarBuilder, c: usize, std: f64, eps: f64, momentum: f64) -> Result<Self> {
        let running_mean = vb.get_with_hints(c, "running_mean", Init::Const(0.0))?;
        let running_var = vb.get_with_hints(c, "running_var", Init::Const(1.0))?;
        let weight = vb.get_with_hints(
            c,
            "weight",
            Init::Randn {
                mean: 1.0,
                stdev: std,
            },
        )?;
        let bias = vb.get_with_hints(c, "bias", Init::Const(0.0))?;
        Ok(Self {
            weight,
            bias,
            running_mean: candle_core::Var::from_tensor(&running_mean)?,
            running_var: candle_core::Var::from_tensor(&running_var)?,
            eps,
            momentum,
        })
    }
}

impl ModuleT for BatchNorm2d {
    fn forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        self.forward_act(x, train, Act::None)
    }
}

impl BatchNorm2d {
    /// Batch norm followed by `act`, in one kernel forward and backward (the
    /// activation's own tensors and backward ops are skipped; measured with
    /// `cargo bench --bench perspnet`, see the README).
    pub fn forward_act(&self, x: &Tensor, train: bool, act: Act) -> Result<Tensor> {
        if x.dtype() != DType::F32 || !x.device().is_cpu() {
            candle_core::bail!("BatchNorm2d: f32 CPU tensors only");
        }
        let x = x.contiguous()?;
        let (n, c, h, w) = x.dims4()?;
        let (mean, invstd) = if train {
            let hw = h * w;
            let cnt = (n * hw) as f64;
            // Per channel, planes in batch order (deterministic).
            let (mut mean, sq): (Vec<f64>, Vec<f64>) = with_f32(&x, |xv| {
                (0..c)
                    .into_par_iter()
                    .map(|ci| {
                        let (mut s, mut s2) = (0f64, 0f64);
                        for ni in 0..n {
                            let o = (ni * c + ci) * hw;
                            for &v in &xv[o..o + hw] {
                                s += v as f64;
                                s2 += (v as f64) * (v as f64);
                            }
                        }
                        (s, s2)
                    })
                    .unzip()
            })?;
            let mut var = vec![0f64; c];
            for ci in 0..c {
                mean[ci] /= cnt;
                var[ci] = (sq[ci] / cnt - mean[ci] * mean[ci]).max(0.0);
            }
            // Running statistics (unbiased variance), PyTorch momentum convention.
            let mom = self.momentum;
            let unbias = if cnt > 1.0 { cnt / (cnt - 1.0) } else { 1.0 };
            let rm = self.running_mean.as_tensor().to_vec1::<f32>()?;
            let rv = self.running_var.as_tensor().to_vec1::<f32>()?;
            let nm: Vec<f32> = (0..c)
                .map(|i| ((1.0 - mom) * rm[i] as f64 + mom * mean[i]) as f32)
                .collect();
            let nv: Vec<f32> = (0..c)
                .map(|i| ((1.0 - mom) * rv[i] as f64 + mom * var[i] * unbias) as f32)
                .collect();
            self.running_mean
                .set(&Tensor::from_vec(nm, c, x.device())?)?;
            self.running_var
                .set(&Tensor::from_vec(nv, c, x.device())?)?;
            let invstd = var
                .iter()
                .map(|v| (1.0 / (v + self.eps).sqrt()) as f32)
                .collect();
            (mean.into_iter().map(|m| m as f32).collect(), invstd)
        } else {
            let rm = self.running_mean.as_tensor().to_vec1::<f32>()?;
            let rv = self.running_var.as_tensor().to_vec1::<f32>()?;
            let invstd = rv
                .iter()
                .map(|v| 1.0 / (*v as f64 + self.eps).sqrt() as f32)
                .collect();
            (rm, invstd)
        };
        let op = FusedBn {
            mean,
            invstd,
            batch_stats: train,
            act,
        };
        x.apply_f32_op3(&self.weight.contiguous()?, &self.bias.contiguous()?, op)
    }
}
