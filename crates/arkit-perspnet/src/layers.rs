//! Building blocks that candle 0.11 does not provide in a differentiable form:
//! bilinear x2 up-sampling with `align_corners=True`, grid-sample-style
//! bilinear point reads (`align_corners=False`, zero padding), 3x3/2 max
//! pooling with padding, channel-wise dropout, the official 2D sine/cosine
//! position encoding, ImageNet normalisation, and conv / batch-norm layers
//! initialised like the official `init_weights(init_type='normal', 0.02)`.
//!
//! On f32 CPU tensors the layers on the training path are single candle ops
//! with our own kernels and one-pass backwards (convolution via
//! [`super::conv`], batch norm fused with its activation, ReLU, the residual
//! join, log-softmax, entropy, per-point linear layers, the up-sampling):
//! candle's backward creates and accumulates a gradient tensor per node, so
//! every node removed from a large tensor's path saves passes over it. Each
//! is tested against the candle composition it replaces, which stays the
//! path on other devices. Measured: the `paper` training step 12.5 -> 2.4 s
//! (`cargo bench --bench perspnet`, README).

use super::blas::{self, Mat};
use super::conv::{self, ConvShape};
use candle_core::{D, DType, Device, Module, ModuleT, Result, Tensor};
use candle_nn::{BatchNorm, Init, Linear, VarBuilder};
use rayon::prelude::*;

/// ImageNet channel means and standard deviations (RGB) used by [`imagenet_normalize`]:
/// the loader's, one definition.
pub use arkit_data::loader::{IMAGENET_MEAN, IMAGENET_STD};

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

/// The `(out, n)` matrix of 1-D linear interpolation from `n` to `out`
/// samples with `align_corners=True` (source position `i * (n-1)/(out-1)`).
pub fn interp_matrix_align_corners(n: usize, out: usize) -> Vec<f32> {
    let mut m = vec![0f32; out * n];
    for i in 0..out {
        let src = if out > 1 && n > 1 {
            i as f64 * (n - 1) as f64 / (out - 1) as f64
        } else {
            0.0
        };
        let i0 = (src.floor() as usize).min(n - 1);
        let i1 = (i0 + 1).min(n - 1);
        let w1 = (src - i0 as f64) as f32;
        m[i * n + i0] += 1.0 - w1;
        m[i * n + i1] += w1;
    }
    m
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
    x.contiguous()?.apply_op1(ResizeAlignCorners {
        rows: Taps::new(h, out_h),
        cols: Taps::new(w, out_w),
    })
}

/// The two source samples and weights of each output sample of a 1-D linear
/// resize with `align_corners=True` (the rows of
/// [`interp_matrix_align_corners`]).
#[derive(Debug, Clone)]
struct Taps {
    n: usize,
    taps: Vec<(usize, usize, f32, f32)>,
}

impl Taps {
    fn new(n: usize, out: usize) -> Self {
        let m = interp_matrix_align_corners(n, out);
        let taps = (0..out)
            .map(|i| {
                let row = &m[i * n..(i + 1) * n];
                let i0 = row.iter().position(|v| *v != 0.0).unwrap_or(0);
                let i1 = (i0 + 1).min(n - 1);
                if i1 == i0 {
                    (i0, i1, row[i0], 0.0)
                } else {
                    (i0, i1, row[i0], row[i1])
                }
            })
            .collect();
        Self { n, taps }
    }

    fn out(&self) -> usize {
        self.taps.len()
    }

    /// `dst[o] = w0 src[i0] + w1 src[i1]`.
    fn resize_line(&self, src: &[f32], dst: &mut [f32]) {
        for (d, &(i0, i1, w0, w1)) in dst.iter_mut().zip(&self.taps) {
            *d = w0 * src[i0] + w1 * src[i1];
        }
    }

    /// The adjoint of [`Self::resize_line`]: `dst[i] = sum over o of w(o, i) src[o]`.
    fn scatter_line(&self, src: &[f32], dst: &mut [f32]) {
        dst.fill(0.0);
        for (g, &(i0, i1, w0, w1)) in src.iter().zip(&self.taps) {
            dst[i0] += w0 * g;
            dst[i1] += w1 * g;
        }
    }
}

/// Separable bilinear resize with `align_corners=True` on `B x C x H x W`
/// (f32, CPU): along the width, then along the height, each output from two
/// inputs; the backward pass is the adjoint, in the reverse order. Replaces
/// two dense matmuls with the interpolation matrices, which cost `H` (resp.
/// `W`) multiply-adds per output instead of two.
#[derive(Debug, Clone)]
struct ResizeAlignCorners {
    rows: Taps,
    cols: Taps,
}

impl ResizeAlignCorners {
    /// Resizes each `h x w` plane of `x` to `oh x ow` (`forward`), or maps each
    /// `oh x ow` plane of a gradient back to `h x w` (the adjoint).
    fn run(&self, x: &[f32], forward: bool) -> Vec<f32> {
        let (h, w, oh, ow) = (self.rows.n, self.cols.n, self.rows.out(), self.cols.out());
        let (src_plane, dst_plane) = if forward {
            (h * w, oh * ow)
        } else {
            (oh * ow, h * w)
        };
        let planes = x.len() / src_plane;
        let mut y = vec![0f32; planes * dst_plane];
        y.par_chunks_mut(dst_plane)
            .zip(x.par_chunks(src_plane))
            .for_each(|(dst, src)| {
                if forward {
                    // Width first (h x ow), then each output row from two rows.
                    let mut mid = vec![0f32; h * ow];
                    for (s, d) in src.chunks(w).zip(mid.chunks_mut(ow)) {
                        self.cols.resize_line(s, d);
                    }
                    for (d, &(i0, i1, w0, w1)) in dst.chunks_mut(ow).zip(&self.rows.taps) {
                        let (r0, r1) = (&mid[i0 * ow..(i0 + 1) * ow], &mid[i1 * ow..(i1 + 1) * ow]);
                        for ((d, a), b) in d.iter_mut().zip(r0).zip(r1) {
                            *d = w0 * a + w1 * b;
                        }
                    }
                } else {
                    // Adjoint of the height pass (oh x ow -> h x ow), then of the width pass.
                    let mut mid = vec![0f32; h * ow];
                    for (g, &(i0, i1, w0, w1)) in src.chunks(ow).zip(&self.rows.taps) {
                        for (j, gv) in g.iter().enumerate() {
                            mid[i0 * ow + j] += w0 * gv;
                            mid[i1 * ow + j] += w1 * gv;
                        }
                    }
                    for (s, d) in mid.chunks(ow).zip(dst.chunks_mut(w)) {
                        self.cols.scatter_line(s, d);
                    }
                }
            });
        y
    }
}

impl candle_core::CustomOp1 for ResizeAlignCorners {
    fn name(&self) -> &'static str {
        "resize-align-corners"
    }

    fn cpu_fwd(
        &self,
        s: &candle_core::CpuStorage,
        l: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let (b, c, h, w) = l.shape().dims4()?;
        if (h, w) != (self.rows.n, self.cols.n) {
            candle_core::bail!(
                "resize: input {h}x{w}, op built for {}x{}",
                self.rows.n,
                self.cols.n
            );
        }
        let y = self.run(contiguous_f32(s, l)?, true);
        let shape = candle_core::Shape::from((b, c, self.rows.out(), self.cols.out()));
        Ok((candle_core::CpuStorage::F32(y), shape))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let v = with_f32(grad, |g| self.run(g, false))?;
        Ok(Some(Tensor::from_vec(v, x.shape(), x.device())?))
    }
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
    pub fn from_uv(uv: &[Vec<f32>], height: usize, width: usize, device: &Device) -> Result<Self> {
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
            return map.contiguous()?.apply_op1(SamplePoints {
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

/// The CPU op behind [`PointSampler::sample`]: each output is the weighted sum
/// of its four texels; the backward scatters each output's gradient onto them
/// (one zeroed map and `4 P` additions per channel, instead of candle's
/// `index_select` backward, broadcast and strided sum).
#[derive(Debug, Clone)]
struct SamplePoints {
    taps: std::sync::Arc<(Vec<u32>, Vec<f32>)>,
    points: usize,
}

impl candle_core::CustomOp1 for SamplePoints {
    fn name(&self) -> &'static str {
        "sample-points"
    }

    fn cpu_fwd(
        &self,
        s: &candle_core::CpuStorage,
        l: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let x = contiguous_f32(s, l)?;
        let (b, c, h, w) = l.shape().dims4()?;
        let (idx, wts) = &*self.taps;
        let p = self.points;
        let mut y = vec![0f32; b * c * p];
        y.par_chunks_mut(p.max(1))
            .zip(x.par_chunks((h * w).max(1)))
            .for_each(|(y, plane)| {
                for (k, y) in y.iter_mut().enumerate() {
                    *y = (0..4)
                        .map(|n| wts[n * p + k] * plane[idx[n * p + k] as usize])
                        .sum();
                }
            });
        Ok((candle_core::CpuStorage::F32(y), (b, c, p).into()))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let (b, c, h, w) = x.dims4()?;
        let (idx, wts) = &*self.taps;
        let p = self.points;
        let v = with_f32(grad, |g| {
            let mut dx = vec![0f32; b * c * h * w];
            dx.par_chunks_mut((h * w).max(1))
                .zip(g.par_chunks(p.max(1)))
                .for_each(|(dx, g)| {
                    for n in 0..4 {
                        for (k, g) in g.iter().enumerate() {
                            dx[idx[n * p + k] as usize] += wts[n * p + k] * g;
                        }
                    }
                });
            dx
        })?;
        Ok(Some(Tensor::from_vec(v, x.shape(), x.device())?))
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
        return feat.contiguous()?.apply_op1(GatherPixels {
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

/// The CPU op behind [`gather_pixels`] (`ids`: `B x M` flat pixel indices).
#[derive(Debug, Clone)]
struct GatherPixels {
    ids: std::sync::Arc<Vec<u32>>,
    m: usize,
}

impl candle_core::CustomOp1 for GatherPixels {
    fn name(&self) -> &'static str {
        "gather-pixels"
    }

    fn cpu_fwd(
        &self,
        s: &candle_core::CpuStorage,
        l: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let x = contiguous_f32(s, l)?;
        let (b, c, h, w) = l.shape().dims4()?;
        let (m, hw) = (self.m, h * w);
        let mut y = vec![0f32; b * m * c];
        for bi in 0..b {
            for (k, &id) in self.ids[bi * m..(bi + 1) * m].iter().enumerate() {
                let row = &mut y[(bi * m + k) * c..(bi * m + k + 1) * c];
                for (ci, v) in row.iter_mut().enumerate() {
                    *v = x[(bi * c + ci) * hw + id as usize];
                }
            }
        }
        Ok((candle_core::CpuStorage::F32(y), (b, m, c).into()))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let (b, c, h, w) = x.dims4()?;
        let (m, hw) = (self.m, h * w);
        let v = with_f32(grad, |g| {
            let mut dx = vec![0f32; b * c * hw];
            for bi in 0..b {
                for (k, &id) in self.ids[bi * m..(bi + 1) * m].iter().enumerate() {
                    let row = &g[(bi * m + k) * c..(bi * m + k + 1) * c];
                    for (ci, v) in row.iter().enumerate() {
                        dx[(bi * c + ci) * hw + id as usize] += v;
                    }
                }
            }
            dx
        })?;
        Ok(Some(Tensor::from_vec(v, x.shape(), x.device())?))
    }
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
pub fn positional_encoding_points(
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
    x.contiguous()?.apply_op1(MaxPool3x3S2)
}

/// The op behind [`max_pool_3x3_s2_p1`].
#[derive(Debug, Clone, Copy)]
struct MaxPool3x3S2;

impl MaxPool3x3S2 {
    /// For each output of one `h x w` plane, the flat index of its window's
    /// first maximum, passed to `out(output index, input index)`.
    fn scan(x: &[f32], h: usize, w: usize, mut out: impl FnMut(usize, usize)) {
        let (oh, ow) = (h.div_ceil(2), w.div_ceil(2));
        for oy in 0..oh {
            let rows = (2 * oy).saturating_sub(1)..(2 * oy + 2).min(h);
            for ox in 0..ow {
                let cols = (2 * ox).saturating_sub(1)..(2 * ox + 2).min(w);
                let mut best = rows.start * w + cols.start;
                for iy in rows.clone() {
                    for ix in cols.clone() {
                        let i = iy * w + ix;
                        if x[i] > x[best] {
                            best = i;
                        }
                    }
                }
                out(oy * ow + ox, best);
            }
        }
    }
}

impl candle_core::CustomOp1 for MaxPool3x3S2 {
    fn name(&self) -> &'static str {
        "max-pool-3x3-s2-p1"
    }

    fn cpu_fwd(
        &self,
        s: &candle_core::CpuStorage,
        l: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let x = contiguous_f32(s, l)?;
        let (b, c, h, w) = l.shape().dims4()?;
        let (oh, ow) = (h.div_ceil(2), w.div_ceil(2));
        let mut y = vec![0f32; b * c * oh * ow];
        if h * w > 0 {
            y.par_chunks_mut(oh * ow)
                .zip(x.par_chunks(h * w))
                .for_each(|(y, x)| Self::scan(x, h, w, |o, i| y[o] = x[i]));
        }
        Ok((candle_core::CpuStorage::F32(y), (b, c, oh, ow).into()))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let (b, c, h, w) = x.dims4()?;
        let (oh, ow) = (h.div_ceil(2), w.div_ceil(2));
        let v = with_f32(x, |xv| {
            with_f32(grad, |g| {
                let mut dx = vec![0f32; b * c * h * w];
                if h * w > 0 {
                    dx.par_chunks_mut(h * w)
                        .zip(xv.par_chunks(h * w).zip(g.par_chunks(oh * ow)))
                        .for_each(|(dx, (x, g))| Self::scan(x, h, w, |o, i| dx[i] += g[o]));
                }
                dx
            })
        })??;
        Ok(Some(Tensor::from_vec(v, x.shape(), x.device())?))
    }
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
pub fn dropout2d(x: &Tensor, p: f64, rng: Option<&mut arkit_data::rng::Rng>) -> Result<Tensor> {
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

/// LeakyReLU with negative slope `slope` (one fused op, see [`activate`]).
pub fn leaky_relu(x: &Tensor, slope: f64) -> Result<Tensor> {
    activate(x, Act::Leaky(slope))
}

/// ReLU as one fused op (see [`activate`]).
pub fn relu(x: &Tensor) -> Result<Tensor> {
    activate(x, Act::Relu)
}

/// An activation as one op whose backward is one pass, `grad * act'(y)` read
/// from the output `y` (ReLU and LeakyReLU keep the sign), instead of candle's
/// five tensors for `relu`'s backward (compare, convert, multiply, ...).
/// f32 CPU tensors; other devices fall back to candle's ops.
pub fn activate(x: &Tensor, act: Act) -> Result<Tensor> {
    if x.dtype() != DType::F32 || !x.device().is_cpu() {
        return match act {
            Act::None => Ok(x.clone()),
            Act::Relu => x.relu(),
            Act::Leaky(s) => x.relu()?.affine(1.0 - s, 0.0)? + x.affine(s, 0.0)?,
        };
    }
    x.apply_op1(Activation(act))
}

/// `relu(a + b)` as one op (the ResNet block's residual join); its backward
/// hands the same masked gradient to both inputs.
pub fn add_relu(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    if a.dtype() != DType::F32 || !a.device().is_cpu() || a.shape() != b.shape() {
        return (a + b)?.relu();
    }
    a.apply_op2(b, AddRelu)
}

/// The fused op behind [`activate`].
#[derive(Debug, Clone, Copy)]
struct Activation(Act);

/// The masked gradient `grad * act'(y)` from the output `y`.
fn activation_grad(act: Act, res: &Tensor, grad: &Tensor) -> Result<Tensor> {
    let v = with_f32(res, |y| {
        with_f32(grad, |g| {
            g.par_iter()
                .zip(y)
                .map(|(g, y)| g * act.slope(*y))
                .collect::<Vec<f32>>()
        })
    })??;
    Tensor::from_vec(v, res.shape(), res.device())
}

impl candle_core::CustomOp1 for Activation {
    fn name(&self) -> &'static str {
        "activation"
    }

    fn cpu_fwd(
        &self,
        s: &candle_core::CpuStorage,
        l: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let x = contiguous_f32(s, l)?;
        let y = x.par_iter().map(|v| self.0.apply(*v)).collect();
        Ok((candle_core::CpuStorage::F32(y), l.shape().clone()))
    }

    fn bwd(&self, _x: &Tensor, res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(activation_grad(self.0, res, grad)?))
    }
}

/// The fused op behind [`add_relu`].
#[derive(Debug, Clone, Copy)]
struct AddRelu;

impl candle_core::CustomOp2 for AddRelu {
    fn name(&self) -> &'static str {
        "add-relu"
    }

    fn cpu_fwd(
        &self,
        s1: &candle_core::CpuStorage,
        l1: &candle_core::Layout,
        s2: &candle_core::CpuStorage,
        l2: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let (a, b) = (contiguous_f32(s1, l1)?, contiguous_f32(s2, l2)?);
        if a.len() != b.len() {
            candle_core::bail!("add-relu: {:?} and {:?} differ", l1.shape(), l2.shape());
        }
        let y = a.par_iter().zip(b).map(|(a, b)| (a + b).max(0.0)).collect();
        Ok((candle_core::CpuStorage::F32(y), l1.shape().clone()))
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let g = activation_grad(Act::Relu, res, grad)?;
        Ok((a.track_op().then(|| g.clone()), b.track_op().then_some(g)))
    }
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

impl Conv2d {
    /// The convolution through candle's built-in `conv2d` (fast forward, but its
    /// CPU backward goes through a naive `conv_transpose2d` and a whole-image
    /// kernel, which is very slow).
    pub fn forward_builtin(&self, x: &Tensor) -> Result<Tensor> {
        let y = x.conv2d(&self.weight, self.padding, self.stride, 1, 1)?;
        self.add_bias(y)
    }

    fn add_bias(&self, y: Tensor) -> Result<Tensor> {
        match &self.bias {
            Some(b) => y.broadcast_add(&b.reshape((1, (), 1, 1))?),
            None => Ok(y),
        }
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

/// Convolution with its own CPU kernels for the forward pass and both
/// gradients ([`super::conv`]: im2col + GEMM over cache-sized blocks, col2im
/// for the input gradient). The input gradient is computed only when the input
/// is tracked (not for the network's input image).
#[derive(Debug, Clone, Copy)]
struct FastConv2d {
    stride: usize,
    padding: usize,
}

impl FastConv2d {
    fn shape(&self, x: &[usize], w: &[usize]) -> Result<ConvShape> {
        let (&[b, c, h, wd], &[co, ci, kh, kw]) = (x, w) else {
            candle_core::bail!("fast-conv2d: 4-D input and kernel expected, got {x:?} and {w:?}");
        };
        if ci != c || h + 2 * self.padding < kh || wd + 2 * self.padding < kw {
            candle_core::bail!("fast-conv2d: input {x:?} does not fit kernel {w:?}");
        }
        Ok(ConvShape {
            b,
            c,
            h,
            w: wd,
            co,
            kh,
            kw,
            stride: self.stride,
            pad: self.padding,
        })
    }
}

/// The contiguous f32 values of a CPU storage.
fn contiguous_f32<'a>(
    s: &'a candle_core::CpuStorage,
    l: &candle_core::Layout,
) -> Result<&'a [f32]> {
    let data = s.as_slice::<f32>()?;
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&data[a..b]),
        None => candle_core::bail!("expected a contiguous f32 tensor"),
    }
}

/// Runs `f` on the contiguous f32 values of a CPU tensor (copying only when the
/// tensor is not contiguous).
fn with_f32<R>(t: &Tensor, f: impl FnOnce(&[f32]) -> R) -> Result<R> {
    let t = t.contiguous()?;
    let (storage, layout) = t.storage_and_layout();
    match &*storage {
        candle_core::Storage::Cpu(cpu) => Ok(f(contiguous_f32(cpu, layout)?)),
        _ => candle_core::bail!("expected a CPU tensor"),
    }
}

impl candle_core::CustomOp2 for FastConv2d {
    fn name(&self) -> &'static str {
        "fast-conv2d"
    }

    fn cpu_fwd(
        &self,
        s1: &candle_core::CpuStorage,
        l1: &candle_core::Layout,
        s2: &candle_core::CpuStorage,
        l2: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let s = self.shape(l1.dims(), l2.dims())?;
        let y = conv::forward(contiguous_f32(s1, l1)?, contiguous_f32(s2, l2)?, &s);
        let shape = candle_core::Shape::from((s.b, s.co, s.ho(), s.wo()));
        Ok((candle_core::CpuStorage::F32(y), shape))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let s = self.shape(x.dims(), w.dims())?;
        let dev = x.device();
        let gx = if x.track_op() {
            let v = with_f32(grad, |g| with_f32(w, |wv| conv::input_grad(g, wv, &s)))??;
            Some(Tensor::from_vec(v, x.shape(), dev)?)
        } else {
            None
        };
        let gw = if w.track_op() {
            let v = with_f32(x, |xv| with_f32(grad, |g| conv::kernel_grad(xv, g, &s)))??;
            Some(Tensor::from_vec(v, w.shape(), dev)?)
        } else {
            None
        };
        Ok((gx, gw))
    }
}

/// `B x (C*kh*kw) x (Ho*Wo)` patches of `x` (the im2col matrix), built from
/// strided views (differentiable).
pub fn im2col(x: &Tensor, kh: usize, kw: usize, stride: usize, padding: usize) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    let ho = (h + 2 * padding - kh) / stride + 1;
    let wo = (w + 2 * padding - kw) / stride + 1;
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
    Tensor::stack(&views, 2)?.reshape((b, c * kh * kw, ho * wo))
}

/// 2-D convolution (f32, CPU) with candle's fast forward and a GEMM-based
/// backward (see the crate docs); numerically equal to `x.conv2d(w, padding, stride, 1, 1)`.
pub fn conv2d_fast(x: &Tensor, weight: &Tensor, stride: usize, padding: usize) -> Result<Tensor> {
    if x.dtype() != DType::F32 || !x.device().is_cpu() {
        return x.conv2d(weight, padding, stride, 1, 1);
    }
    x.contiguous()?
        .apply_op2(&weight.contiguous()?, FastConv2d { stride, padding })
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
        .apply_op3(&weight.contiguous()?, &bias, PointLinearOp)
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
    h.contiguous()?.apply_op2(&r.contiguous()?, AddRowsRelu)
}

/// The fused op behind [`add_rows_relu`].
#[derive(Debug, Clone, Copy)]
struct AddRowsRelu;

impl candle_core::CustomOp2 for AddRowsRelu {
    fn name(&self) -> &'static str {
        "add-rows-relu"
    }

    fn cpu_fwd(
        &self,
        s1: &candle_core::CpuStorage,
        l1: &candle_core::Layout,
        s2: &candle_core::CpuStorage,
        l2: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let (h, r) = (contiguous_f32(s1, l1)?, contiguous_f32(s2, l2)?);
        let (b, m, c) = l1.shape().dims3()?;
        if r.len() != b * c {
            candle_core::bail!("add-rows-relu: {:?} and {:?}", l1.shape(), l2.shape());
        }
        let mut y = vec![0f32; h.len()];
        y.par_chunks_mut(m * c)
            .zip(h.par_chunks(m * c).zip(r.par_chunks(c)))
            .for_each(|(y, (h, r))| {
                for (yr, hr) in y.chunks_mut(c).zip(h.chunks(c)) {
                    for ((y, h), r) in yr.iter_mut().zip(hr).zip(r) {
                        *y = (h + r).max(0.0);
                    }
                }
            });
        Ok((candle_core::CpuStorage::F32(y), l1.shape().clone()))
    }

    fn bwd(
        &self,
        h: &Tensor,
        r: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (b, m, c) = h.dims3()?;
        let gh = activation_grad(Act::Relu, res, grad)?;
        let gr = if r.track_op() {
            let v = with_f32(&gh, |g| {
                let mut sums = vec![0f32; b * c];
                for (s, gb) in sums.chunks_mut(c).zip(g.chunks(m * c)) {
                    for row in gb.chunks(c) {
                        for (s, v) in s.iter_mut().zip(row) {
                            *s += v;
                        }
                    }
                }
                sums
            })?;
            Some(Tensor::from_vec(v, (b, 1, c), h.device())?)
        } else {
            None
        };
        Ok((h.track_op().then_some(gh), gr))
    }
}

/// The fused op behind [`PointLinear`]: `x` is `R x c_in` (any leading shape).
#[derive(Debug, Clone, Copy)]
struct PointLinearOp;

impl candle_core::CustomOp3 for PointLinearOp {
    fn name(&self) -> &'static str {
        "point-linear"
    }

    fn cpu_fwd(
        &self,
        s1: &candle_core::CpuStorage,
        l1: &candle_core::Layout,
        s2: &candle_core::CpuStorage,
        l2: &candle_core::Layout,
        s3: &candle_core::CpuStorage,
        l3: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let (x, w, b) = (
            contiguous_f32(s1, l1)?,
            contiguous_f32(s2, l2)?,
            contiguous_f32(s3, l3)?,
        );
        let (co, ci) = l2.shape().dims2()?;
        let dims = l1.dims();
        if dims.last() != Some(&ci) || b.len() != co {
            candle_core::bail!(
                "point-linear: input {dims:?}, weight {co}x{ci}, bias {}",
                b.len()
            );
        }
        let r = x.len() / ci.max(1);
        let mut y: Vec<f32> = b.iter().copied().cycle().take(r * co).collect();
        blas::gemm_par(
            &mut y,
            Mat::row_major(r, co, co),
            x,
            Mat::row_major(r, ci, ci),
            w,
            Mat::row_major(co, ci, ci).transposed(),
            true,
        );
        let mut out = dims.to_vec();
        *out.last_mut().expect("rank >= 1") = co;
        Ok((
            candle_core::CpuStorage::F32(y),
            candle_core::Shape::from(out),
        ))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (co, ci) = w.dims2()?;
        let r = x.elem_count() / ci.max(1);
        let dev = x.device();
        let dx = if x.track_op() {
            let v = with_f32(grad, |g| {
                with_f32(w, |wv| {
                    let mut dx = vec![0f32; r * ci];
                    blas::gemm_par(
                        &mut dx,
                        Mat::row_major(r, ci, ci),
                        g,
                        Mat::row_major(r, co, co),
                        wv,
                        Mat::row_major(co, ci, ci),
                        false,
                    );
                    dx
                })
            })??;
            Some(Tensor::from_vec(v, x.shape(), dev)?)
        } else {
            None
        };
        let dw = if w.track_op() {
            let v = with_f32(grad, |g| {
                with_f32(x, |xv| {
                    let mut dw = vec![0f32; co * ci];
                    blas::gemm_par(
                        &mut dw,
                        Mat::row_major(co, ci, ci),
                        g,
                        Mat::row_major(r, co, co).transposed(),
                        xv,
                        Mat::row_major(r, ci, ci),
                        false,
                    );
                    dw
                })
            })??;
            Some(Tensor::from_vec(v, w.shape(), dev)?)
        } else {
            None
        };
        let db = if b.track_op() {
            let v = with_f32(grad, |g| {
                let mut db = vec![0f32; co];
                for row in g.chunks(co) {
                    for (d, v) in db.iter_mut().zip(row) {
                        *d += v;
                    }
                }
                db
            })?;
            Some(Tensor::from_vec(v, co, dev)?)
        } else {
            None
        };
        Ok((dx, dw, db))
    }
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

/// Activation following a [`ConvBn`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Act {
    /// No activation.
    None,
    /// ReLU.
    Relu,
    /// LeakyReLU with the given negative slope.
    Leaky(f64),
}

/// Conv (no bias) + batch norm + activation.
#[derive(Debug, Clone)]
pub struct ConvBn {
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
    x.contiguous()?.apply_op1(MeanPoints)
}

/// The op behind [`mean_points`] on f32 CPU tensors: contiguous row sums
/// forward, the gradient over `N` copied to every row backward (candle's
/// `mean_keepdim(1)` reduces with a strided walk).
#[derive(Debug, Clone, Copy)]
struct MeanPoints;

impl candle_core::CustomOp1 for MeanPoints {
    fn name(&self) -> &'static str {
        "mean-points"
    }

    fn cpu_fwd(
        &self,
        s: &candle_core::CpuStorage,
        l: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let x = contiguous_f32(s, l)?;
        let (b, n, c) = l.shape().dims3()?;
        let mut y = vec![0f64; b * c];
        for (yb, xb) in y.chunks_mut(c).zip(x.chunks(n * c.max(1))) {
            for row in xb.chunks(c) {
                for (s, v) in yb.iter_mut().zip(row) {
                    *s += *v as f64;
                }
            }
        }
        let y = y
            .into_iter()
            .map(|v| (v / n.max(1) as f64) as f32)
            .collect();
        Ok((candle_core::CpuStorage::F32(y), (b, 1, c).into()))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let (b, n, c) = x.dims3()?;
        let v = with_f32(grad, |g| {
            let scale = 1.0 / n.max(1) as f32;
            let mut dx = Vec::with_capacity(b * n * c);
            for gb in g.chunks(c) {
                for _ in 0..n {
                    dx.extend(gb.iter().map(|v| v * scale));
                }
            }
            dx
        })?;
        Ok(Some(Tensor::from_vec(v, (b, n, c), x.device())?))
    }
}

/// The entropy `-sum(exp(l) l)` of each row of log-probabilities `l` (last
/// dimension), one op on f32 CPU tensors with a one-pass backward
/// (`dl = -g exp(l) (1 + l)`); the result drops the last dimension.
pub fn row_entropy(log_p: &Tensor) -> Result<Tensor> {
    if log_p.dtype() != DType::F32 || !log_p.device().is_cpu() || log_p.rank() == 0 {
        return (log_p.exp()? * log_p)?.sum(D::Minus1)?.neg();
    }
    log_p.contiguous()?.apply_op1(RowEntropy)
}

/// The op behind [`row_entropy`].
#[derive(Debug, Clone, Copy)]
struct RowEntropy;

impl candle_core::CustomOp1 for RowEntropy {
    fn name(&self) -> &'static str {
        "row-entropy"
    }

    fn cpu_fwd(
        &self,
        s: &candle_core::CpuStorage,
        l: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let x = contiguous_f32(s, l)?;
        let dims = l.dims();
        let n = dims[dims.len() - 1].max(1);
        let y: Vec<f32> = x
            .par_chunks(n)
            .map(|row| -row.iter().map(|l| l.exp() * l).sum::<f32>())
            .collect();
        Ok((
            candle_core::CpuStorage::F32(y),
            candle_core::Shape::from(&dims[..dims.len() - 1]),
        ))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let n = x.dims().last().copied().unwrap_or(1).max(1);
        let v = with_f32(x, |l| {
            with_f32(grad, |g| {
                let mut dx = vec![0f32; l.len()];
                dx.par_chunks_mut(n)
                    .zip(l.par_chunks(n).zip(g.par_chunks(1)))
                    .for_each(|(dx, (l, g))| {
                        for (d, l) in dx.iter_mut().zip(l) {
                            *d = -g[0] * l.exp() * (1.0 + l);
                        }
                    });
                dx
            })
        })??;
        Ok(Some(Tensor::from_vec(v, x.shape(), x.device())?))
    }
}

/// Softmax over the last dimension computed as `exp(log_softmax)`.
pub fn softmax_last(x: &Tensor) -> Result<Tensor> {
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
    x.contiguous()?.apply_op1(LogSoftmaxLast)
}

/// The fused op behind [`log_softmax_last`].
#[derive(Debug, Clone, Copy)]
struct LogSoftmaxLast;

impl candle_core::CustomOp1 for LogSoftmaxLast {
    fn name(&self) -> &'static str {
        "log-softmax-last"
    }

    fn cpu_fwd(
        &self,
        s: &candle_core::CpuStorage,
        l: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let x = contiguous_f32(s, l)?;
        let n = l.dims().last().copied().unwrap_or(1).max(1);
        let mut y = vec![0f32; x.len()];
        y.par_chunks_mut(n).zip(x.par_chunks(n)).for_each(|(y, x)| {
            let max = x.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            let sum: f32 = x.iter().map(|v| (v - max).exp()).sum();
            let shift = max + sum.ln();
            for (y, x) in y.iter_mut().zip(x) {
                *y = x - shift;
            }
        });
        Ok((candle_core::CpuStorage::F32(y), l.shape().clone()))
    }

    fn bwd(&self, _x: &Tensor, res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let n = res.dims().last().copied().unwrap_or(1).max(1);
        let v = with_f32(res, |y| {
            with_f32(grad, |g| {
                let mut dx = vec![0f32; g.len()];
                dx.par_chunks_mut(n)
                    .zip(y.par_chunks(n).zip(g.par_chunks(n)))
                    .for_each(|(dx, (y, g))| {
                        let total: f32 = g.iter().sum();
                        for ((d, y), g) in dx.iter_mut().zip(y).zip(g) {
                            *d = g - y.exp() * total;
                        }
                    });
                dx
            })
        })??;
        Ok(Some(Tensor::from_vec(v, res.shape(), res.device())?))
    }
}

/// Fused batch-norm kernel over `N x C x H x W` (f32, CPU), with the statistics
/// computed beforehand. `batch_stats` selects the training-mode backward (the
/// statistics depend on the batch) or the eval-mode one (constants).
#[derive(Debug, Clone)]
struct FusedBn {
    mean: Vec<f32>,
    invstd: Vec<f32>,
    batch_stats: bool,
    act: Act,
}

impl Act {
    /// The activation of one value.
    #[inline]
    fn apply(self, z: f32) -> f32 {
        match self {
            Act::None => z,
            Act::Relu => z.max(0.0),
            Act::Leaky(s) => {
                if z > 0.0 {
                    z
                } else {
                    z * s as f32
                }
            }
        }
    }

    /// Its derivative at `z` (PyTorch's: 0, or the slope, at `z = 0`).
    #[inline]
    fn slope(self, z: f32) -> f32 {
        match self {
            Act::None => 1.0,
            Act::Relu => {
                if z > 0.0 {
                    1.0
                } else {
                    0.0
                }
            }
            Act::Leaky(s) => {
                if z > 0.0 {
                    1.0
                } else {
                    s as f32
                }
            }
        }
    }
}

impl FusedBn {
    /// Scale and shift of channel `ci`: `y = act(x a + sh)`.
    fn affine(&self, gamma: &[f32], beta: &[f32], ci: usize) -> (f32, f32) {
        let a = gamma[ci] * self.invstd[ci];
        (a, beta[ci] - self.mean[ci] * a)
    }
}

impl candle_core::CustomOp3 for FusedBn {
    fn name(&self) -> &'static str {
        "fused-batch-norm"
    }

    fn cpu_fwd(
        &self,
        s1: &candle_core::CpuStorage,
        l1: &candle_core::Layout,
        s2: &candle_core::CpuStorage,
        l2: &candle_core::Layout,
        s3: &candle_core::CpuStorage,
        l3: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let x = contiguous_f32(s1, l1)?;
        let g = contiguous_f32(s2, l2)?;
        let b = contiguous_f32(s3, l3)?;
        let (_n, c, h, w) = l1.shape().dims4()?;
        let hw = (h * w).max(1);
        let mut y = vec![0f32; x.len()];
        let act = self.act;
        y.par_chunks_mut(hw)
            .zip(x.par_chunks(hw))
            .enumerate()
            .for_each(|(plane, (y, x))| {
                let (a, sh) = self.affine(g, b, plane % c);
                for (yv, xv) in y.iter_mut().zip(x) {
                    *yv = act.apply(xv * a + sh);
                }
            });
        Ok((candle_core::CpuStorage::F32(y), l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        gamma: &Tensor,
        beta: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (n, c, h, w) = x.dims4()?;
        let hw = (h * w).max(1);
        let cnt = (n * hw) as f32;
        let gam = gamma.to_vec1::<f32>()?;
        let bet = beta.to_vec1::<f32>()?;
        let act = self.act;
        // The gradient through the activation (pre-activation recomputed from x).
        let gz = |g: f32, x: f32, a: f32, sh: f32| g * act.slope(x * a + sh);
        let (dx, sg, sgx) = with_f32(x, |xv| {
            with_f32(grad, |gv| {
                // Per channel: sum of gz and of gz * x_hat, planes in batch order.
                let (sg, sgx): (Vec<f32>, Vec<f32>) = (0..c)
                    .into_par_iter()
                    .map(|ci| {
                        let (a, sh) = self.affine(&gam, &bet, ci);
                        let (m, is) = (self.mean[ci], self.invstd[ci]);
                        let (mut s, mut sx) = (0f32, 0f32);
                        for ni in 0..n {
                            let o = (ni * c + ci) * hw;
                            let (mut ps, mut psx) = (0f32, 0f32);
                            for (g, xx) in gv[o..o + hw].iter().zip(&xv[o..o + hw]) {
                                let g = gz(*g, *xx, a, sh);
                                ps += g;
                                psx += g * (xx - m) * is;
                            }
                            s += ps;
                            sx += psx;
                        }
                        (s, sx)
                    })
                    .unzip();
                let mut dx = vec![0f32; xv.len()];
                dx.par_chunks_mut(hw)
                    .zip(xv.par_chunks(hw).zip(gv.par_chunks(hw)))
                    .enumerate()
                    .for_each(|(plane, (dx, (xv, gv)))| {
                        let ci = plane % c;
                        let (a, sh) = self.affine(&gam, &bet, ci);
                        let (m, is) = (self.mean[ci], self.invstd[ci]);
                        let k = gam[ci] * is;
                        if self.batch_stats {
                            let (mg, mgx) = (sg[ci] / cnt, sgx[ci] / cnt);
                            for ((d, x), g) in dx.iter_mut().zip(xv).zip(gv) {
                                let xh = (x - m) * is;
                                *d = k * (gz(*g, *x, a, sh) - mg - xh * mgx);
                            }
                        } else {
                            for ((d, x), g) in dx.iter_mut().zip(xv).zip(gv) {
                                *d = k * gz(*g, *x, a, sh);
                            }
                        }
                    });
                (dx, sg, sgx)
            })
        })??;
        let dev = x.device();
        Ok((
            Some(Tensor::from_vec(dx, (n, c, h, w), dev)?),
            Some(Tensor::from_vec(sgx, c, dev)?),
            Some(Tensor::from_vec(sg, c, dev)?),
        ))
    }
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
        x.apply_op3(&self.weight.contiguous()?, &self.bias.contiguous()?, op)
    }
}
