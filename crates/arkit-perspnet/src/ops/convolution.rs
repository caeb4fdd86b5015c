//! The convolution op: its forward and both gradients on the kernels of
//! [`crate::conv`].

use super::custom_op::{F32Op, like, with_f32};
use crate::conv::{self, ConvShape};
use candle_core::{Layout, Result, Shape, Tensor};

/// Convolution with its own CPU kernels for the forward pass and both
/// gradients ([`crate::conv`]: im2col + GEMM over cache-sized blocks, col2im
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
