//! Ops on the sampled points' features (`B x N x C`): the fused residual add and ReLU,
//! the point-wise linear layer and the mean over the points.

use super::activation::{Act, activation_grad};
use super::custom_op::{F32Op, like, with_f32};
use crate::blas::{self, Mat};
use candle_core::{Layout, Result, Shape, Tensor};
use rayon::prelude::*;

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
