//! The custom candle ops behind [`crate::layers`] on contiguous f32 CPU tensors:
//! their forward kernels and one-pass backwards. Each op implements [`F32Op`] (its
//! name, a forward from the inputs' values and layouts, a backward giving each
//! input's gradient); the one generic wrapper [`Op`] turns it into candle's
//! `CustomOp1`, `CustomOp2` or `CustomOp3`, so the storage handling, the result's
//! wrapping and the gradient plumbing are written once. Each op is tested against
//! the candle composition it replaces (forward and gradients), which stays the path
//! on other devices and dtypes.

use crate::blas::{self, Mat};
use crate::conv::{self, ConvShape};
use candle_core::{CpuStorage, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// Activation following a `crate::layers::ConvBn`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Act {
    /// No activation.
    None,
    /// ReLU.
    Relu,
    /// LeakyReLU with the given negative slope.
    Leaky(f64),
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

/// A custom op with `N` inputs on contiguous f32 CPU tensors.
pub(crate) trait F32Op<const N: usize>: Send + Sync + 'static {
    /// candle's name of the op.
    const NAME: &'static str;

    /// The output's values and shape from each input's values and layout.
    fn forward(&self, inputs: [(&[f32], &Layout); N]) -> Result<(Vec<f32>, Shape)>;

    /// Each input's gradient (`None` where there is none) from the inputs, the output
    /// `res` and the output's gradient `grad`.
    fn backward(
        &self,
        inputs: [&Tensor; N],
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; N]>;
}

/// An [`F32Op`] as a candle custom op.
struct Op<T>(T);

/// Runs `op`'s forward on CPU storages, each checked contiguous f32.
fn cpu_forward<const N: usize, T: F32Op<N>>(
    op: &T,
    storages: [(&CpuStorage, &Layout); N],
) -> Result<(CpuStorage, Shape)> {
    let mut inputs: [(&[f32], &Layout); N] = storages.map(|(_, l)| (&[][..], l));
    for (k, (s, l)) in storages.into_iter().enumerate() {
        inputs[k].0 = contiguous_f32(s, l)?;
    }
    let (y, shape) = op.forward(inputs)?;
    Ok((CpuStorage::F32(y), shape))
}

impl<T: F32Op<1>> candle_core::CustomOp1 for Op<T> {
    fn name(&self) -> &'static str {
        T::NAME
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        cpu_forward(&self.0, [(s, l)])
    }

    fn bwd(&self, x: &Tensor, res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let [g] = self.0.backward([x], res, grad)?;
        Ok(g)
    }
}

impl<T: F32Op<2>> candle_core::CustomOp2 for Op<T> {
    fn name(&self) -> &'static str {
        T::NAME
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        cpu_forward(&self.0, [(s1, l1), (s2, l2)])
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let [ga, gb] = self.0.backward([a, b], res, grad)?;
        Ok((ga, gb))
    }
}

impl<T: F32Op<3>> candle_core::CustomOp3 for Op<T> {
    fn name(&self) -> &'static str {
        T::NAME
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        cpu_forward(&self.0, [(s1, l1), (s2, l2), (s3, l3)])
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        c: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let [ga, gb, gc] = self.0.backward([a, b, c], res, grad)?;
        Ok((ga, gb, gc))
    }
}

/// Applying an [`F32Op`] to tensors (the first input is `self`).
pub(crate) trait ApplyF32Op {
    /// A one-input op.
    fn apply_f32_op1<T: F32Op<1>>(&self, op: T) -> Result<Tensor>;
    /// A two-input op.
    fn apply_f32_op2<T: F32Op<2>>(&self, b: &Tensor, op: T) -> Result<Tensor>;
    /// A three-input op.
    fn apply_f32_op3<T: F32Op<3>>(&self, b: &Tensor, c: &Tensor, op: T) -> Result<Tensor>;
}

impl ApplyF32Op for Tensor {
    fn apply_f32_op1<T: F32Op<1>>(&self, op: T) -> Result<Tensor> {
        self.apply_op1(Op(op))
    }

    fn apply_f32_op2<T: F32Op<2>>(&self, b: &Tensor, op: T) -> Result<Tensor> {
        self.apply_op2(b, Op(op))
    }

    fn apply_f32_op3<T: F32Op<3>>(&self, b: &Tensor, c: &Tensor, op: T) -> Result<Tensor> {
        self.apply_op3(b, c, Op(op))
    }
}

/// A tensor of the values `v` with the shape and device of `like`.
pub(crate) fn like(v: Vec<f32>, like: &Tensor) -> Result<Tensor> {
    Tensor::from_vec(v, like.shape(), like.device())
}

/// The two source samples and weights of each output sample of a 1-D linear
/// resize with `align_corners=True` (the rows of
/// [`interp_matrix_align_corners`]).
#[derive(Debug, Clone)]
pub(crate) struct Taps {
    pub(crate) n: usize,
    pub(crate) taps: Vec<(usize, usize, f32, f32)>,
}

impl Taps {
    pub(crate) fn new(n: usize, out: usize) -> Self {
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
pub(crate) struct ResizeAlignCorners {
    pub(crate) rows: Taps,
    pub(crate) cols: Taps,
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

impl F32Op<1> for ResizeAlignCorners {
    const NAME: &'static str = "resize-align-corners";

    fn forward(&self, [(x, l)]: [(&[f32], &Layout); 1]) -> Result<(Vec<f32>, Shape)> {
        let (b, c, h, w) = l.shape().dims4()?;
        if (h, w) != (self.rows.n, self.cols.n) {
            candle_core::bail!(
                "resize: input {h}x{w}, op built for {}x{}",
                self.rows.n,
                self.cols.n
            );
        }
        let y = self.run(x, true);
        let shape = candle_core::Shape::from((b, c, self.rows.out(), self.cols.out()));
        Ok((y, shape))
    }

    fn backward(
        &self,
        [x]: [&Tensor; 1],
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; 1]> {
        let v = with_f32(grad, |g| self.run(g, false))?;
        Ok([Some(like(v, x)?)])
    }
}

/// The CPU op behind [`PointSampler::sample`]: each output is the weighted sum
/// of its four texels; the backward scatters each output's gradient onto them
/// (one zeroed map and `4 P` additions per channel, instead of candle's
/// `index_select` backward, broadcast and strided sum).
#[derive(Debug, Clone)]
pub(crate) struct SamplePoints {
    pub(crate) taps: std::sync::Arc<(Vec<u32>, Vec<f32>)>,
    pub(crate) points: usize,
}

impl F32Op<1> for SamplePoints {
    const NAME: &'static str = "sample-points";

    fn forward(&self, [(x, l)]: [(&[f32], &Layout); 1]) -> Result<(Vec<f32>, Shape)> {
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
        Ok((y, (b, c, p).into()))
    }

    fn backward(
        &self,
        [x]: [&Tensor; 1],
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; 1]> {
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
        Ok([Some(like(v, x)?)])
    }
}

/// The CPU op behind [`gather_pixels`] (`ids`: `B x M` flat pixel indices).
#[derive(Debug, Clone)]
pub(crate) struct GatherPixels {
    pub(crate) ids: std::sync::Arc<Vec<u32>>,
    pub(crate) m: usize,
}

impl F32Op<1> for GatherPixels {
    const NAME: &'static str = "gather-pixels";

    fn forward(&self, [(x, l)]: [(&[f32], &Layout); 1]) -> Result<(Vec<f32>, Shape)> {
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
        Ok((y, (b, m, c).into()))
    }

    fn backward(
        &self,
        [x]: [&Tensor; 1],
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; 1]> {
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
        Ok([Some(like(v, x)?)])
    }
}

/// The op behind [`max_pool_3x3_s2_p1`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct MaxPool3x3S2;

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

impl F32Op<1> for MaxPool3x3S2 {
    const NAME: &'static str = "max-pool-3x3-s2-p1";

    fn forward(&self, [(x, l)]: [(&[f32], &Layout); 1]) -> Result<(Vec<f32>, Shape)> {
        let (b, c, h, w) = l.shape().dims4()?;
        let (oh, ow) = (h.div_ceil(2), w.div_ceil(2));
        let mut y = vec![0f32; b * c * oh * ow];
        if h * w > 0 {
            y.par_chunks_mut(oh * ow)
                .zip(x.par_chunks(h * w))
                .for_each(|(y, x)| Self::scan(x, h, w, |o, i| y[o] = x[i]));
        }
        Ok((y, (b, c, oh, ow).into()))
    }

    fn backward(
        &self,
        [x]: [&Tensor; 1],
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; 1]> {
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
        Ok([Some(like(v, x)?)])
    }
}

/// The fused op behind [`activate`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct Activation(pub(crate) Act);

/// The masked gradient `grad * act'(y)` from the output `y`.
pub(crate) fn activation_grad(act: Act, res: &Tensor, grad: &Tensor) -> Result<Tensor> {
    let v = with_f32(res, |y| {
        with_f32(grad, |g| {
            g.par_iter()
                .zip(y)
                .map(|(g, y)| g * act.slope(*y))
                .collect::<Vec<f32>>()
        })
    })??;
    like(v, res)
}

impl F32Op<1> for Activation {
    const NAME: &'static str = "activation";

    fn forward(&self, [(x, l)]: [(&[f32], &Layout); 1]) -> Result<(Vec<f32>, Shape)> {
        let y = x.par_iter().map(|v| self.0.apply(*v)).collect();
        Ok((y, l.shape().clone()))
    }

    fn backward(
        &self,
        [_x]: [&Tensor; 1],
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; 1]> {
        Ok([Some(activation_grad(self.0, res, grad)?)])
    }
}

/// The fused op behind [`add_relu`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct AddRelu;

impl F32Op<2> for AddRelu {
    const NAME: &'static str = "add-relu";

    fn forward(&self, [(x1, l1), (x2, l2)]: [(&[f32], &Layout); 2]) -> Result<(Vec<f32>, Shape)> {
        let (a, b) = (x1, x2);
        if a.len() != b.len() {
            candle_core::bail!("add-relu: {:?} and {:?} differ", l1.shape(), l2.shape());
        }
        let y = a.par_iter().zip(b).map(|(a, b)| (a + b).max(0.0)).collect();
        Ok((y, l1.shape().clone()))
    }

    fn backward(
        &self,
        [a, b]: [&Tensor; 2],
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; 2]> {
        let g = activation_grad(Act::Relu, res, grad)?;
        Ok([a.track_op().then(|| g.clone()), b.track_op().then_some(g)])
    }
}

/// Convolution with its own CPU kernels for the forward pass and both
/// gradients ([`super::conv`]: im2col + GEMM over cache-sized blocks, col2im
/// for the input gradient). The input gradient is computed only when the input
/// is tracked (not for the network's input image).
#[derive(Debug, Clone, Copy)]
pub(crate) struct FastConv2d {
    pub(crate) stride: usize,
    pub(crate) padding: usize,
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
pub(crate) fn contiguous_f32<'a>(
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
pub(crate) fn with_f32<R>(t: &Tensor, f: impl FnOnce(&[f32]) -> R) -> Result<R> {
    let t = t.contiguous()?;
    let (storage, layout) = t.storage_and_layout();
    match &*storage {
        candle_core::Storage::Cpu(cpu) => Ok(f(contiguous_f32(cpu, layout)?)),
        _ => candle_core::bail!("expected a CPU tensor"),
    }
}

impl F32Op<2> for FastConv2d {
    const NAME: &'static str = "fast-conv2d";

    fn forward(&self, [(x1, l1), (x2, l2)]: [(&[f32], &Layout); 2]) -> Result<(Vec<f32>, Shape)> {
        let s = self.shape(l1.dims(), l2.dims())?;
        let y = conv::forward(x1, x2, &s);
        let shape = candle_core::Shape::from((s.b, s.co, s.ho(), s.wo()));
        Ok((y, shape))
    }

    fn backward(
        &self,
        [x, w]: [&Tensor; 2],
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; 2]> {
        let s = self.shape(x.dims(), w.dims())?;
        let gx = if x.track_op() {
            let v = with_f32(grad, |g| with_f32(w, |wv| conv::input_grad(g, wv, &s)))??;
            Some(like(v, x)?)
        } else {
            None
        };
        let gw = if w.track_op() {
            let v = with_f32(x, |xv| with_f32(grad, |g| conv::kernel_grad(xv, g, &s)))??;
            Some(like(v, w)?)
        } else {
            None
        };
        Ok([gx, gw])
    }
}

/// The fused op behind [`add_rows_relu`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct AddRowsRelu;

impl F32Op<2> for AddRowsRelu {
    const NAME: &'static str = "add-rows-relu";

    fn forward(&self, [(x1, l1), (x2, l2)]: [(&[f32], &Layout); 2]) -> Result<(Vec<f32>, Shape)> {
        let (h, r) = (x1, x2);
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
        Ok((y, l1.shape().clone()))
    }

    fn backward(
        &self,
        [h, r]: [&Tensor; 2],
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; 2]> {
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
        Ok([h.track_op().then_some(gh), gr])
    }
}

/// The fused op behind [`PointLinear`]: `x` is `R x c_in` (any leading shape).
#[derive(Debug, Clone, Copy)]
pub(crate) struct PointLinearOp;

impl F32Op<3> for PointLinearOp {
    const NAME: &'static str = "point-linear";

    fn forward(
        &self,
        [(x1, l1), (x2, l2), (x3, _)]: [(&[f32], &Layout); 3],
    ) -> Result<(Vec<f32>, Shape)> {
        let (x, w, b) = (x1, x2, x3);
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
        Ok((y, candle_core::Shape::from(out)))
    }

    fn backward(
        &self,
        [x, w, b]: [&Tensor; 3],
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; 3]> {
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
            Some(like(v, x)?)
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
            Some(like(v, w)?)
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
        Ok([dx, dw, db])
    }
}

/// The op behind [`mean_points`] on f32 CPU tensors: contiguous row sums
/// forward, the gradient over `N` copied to every row backward (candle's
/// `mean_keepdim(1)` reduces with a strided walk).
#[derive(Debug, Clone, Copy)]
pub(crate) struct MeanPoints;

impl F32Op<1> for MeanPoints {
    const NAME: &'static str = "mean-points";

    fn forward(&self, [(x, l)]: [(&[f32], &Layout); 1]) -> Result<(Vec<f32>, Shape)> {
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
        Ok((y, (b, 1, c).into()))
    }

    fn backward(
        &self,
        [x]: [&Tensor; 1],
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; 1]> {
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
        Ok([Some(Tensor::from_vec(v, (b, n, c), x.device())?)])
    }
}

/// The op behind [`row_entropy`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct RowEntropy;

impl F32Op<1> for RowEntropy {
    const NAME: &'static str = "row-entropy";

    fn forward(&self, [(x, l)]: [(&[f32], &Layout); 1]) -> Result<(Vec<f32>, Shape)> {
        let dims = l.dims();
        let n = dims[dims.len() - 1].max(1);
        let y: Vec<f32> = x
            .par_chunks(n)
            .map(|row| -row.iter().map(|l| l.exp() * l).sum::<f32>())
            .collect();
        Ok((y, candle_core::Shape::from(&dims[..dims.len() - 1])))
    }

    fn backward(
        &self,
        [x]: [&Tensor; 1],
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; 1]> {
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
        Ok([Some(like(v, x)?)])
    }
}

/// The fused op behind [`log_softmax_last`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct LogSoftmaxLast;

impl F32Op<1> for LogSoftmaxLast {
    const NAME: &'static str = "log-softmax-last";

    fn forward(&self, [(x, l)]: [(&[f32], &Layout); 1]) -> Result<(Vec<f32>, Shape)> {
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
        Ok((y, l.shape().clone()))
    }

    fn backward(
        &self,
        [_x]: [&Tensor; 1],
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; 1]> {
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
        Ok([Some(like(v, res)?)])
    }
}

/// Fused batch-norm kernel over `N x C x H x W` (f32, CPU), with the statistics
/// computed beforehand. `batch_stats` selects the training-mode backward (the
/// statistics depend on the batch) or the eval-mode one (constants).
#[derive(Debug, Clone)]
pub(crate) struct FusedBn {
    pub(crate) mean: Vec<f32>,
    pub(crate) invstd: Vec<f32>,
    pub(crate) batch_stats: bool,
    pub(crate) act: Act,
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

impl F32Op<3> for FusedBn {
    const NAME: &'static str = "fused-batch-norm";

    fn forward(
        &self,
        [(x1, l1), (x2, _), (x3, _)]: [(&[f32], &Layout); 3],
    ) -> Result<(Vec<f32>, Shape)> {
        let x = x1;
        let g = x2;
        let b = x3;
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
        Ok((y, l1.shape().clone()))
    }

    fn backward(
        &self,
        [x, gamma, beta]: [&Tensor; 3],
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<[Option<Tensor>; 3]> {
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
        Ok([
            Some(Tensor::from_vec(dx, (n, c, h, w), dev)?),
            Some(Tensor::from_vec(sgx, c, dev)?),
            Some(Tensor::from_vec(sg, c, dev)?),
        ])
    }
}
