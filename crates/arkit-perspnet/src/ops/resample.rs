//! Resampling ops: the separable bilinear resize with `align_corners=True` (and its
//! interpolation weights), the bilinear sampling of points, the gathering of pixels and
//! the 3x3 stride-2 max pool.

use super::custom_op::{F32Op, like, with_f32};
use candle_core::{Layout, Result, Shape, Tensor};
use rayon::prelude::*;

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
