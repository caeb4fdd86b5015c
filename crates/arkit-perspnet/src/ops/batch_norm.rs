//! The fused batch norm (with its activation) over `N x C x H x W`, in training mode
//! (batch statistics) and eval mode (running statistics).

use super::activation::Act;
use super::custom_op::{F32Op, with_f32};
use candle_core::{Layout, Result, Shape, Tensor};
use rayon::prelude::*;

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
