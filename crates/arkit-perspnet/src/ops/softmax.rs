//! Ops on the rows of the correspondence head's assignment logits: the row entropy and
//! the log-softmax over the last axis.

use super::custom_op::{F32Op, like, with_f32};
use candle_core::{Layout, Result, Shape, Tensor};
use rayon::prelude::*;

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
