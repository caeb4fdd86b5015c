//! The activations: [`Act`] (none, ReLU, LeakyReLU) with its value and slope, and the
//! fused ops that apply one (alone, or after an addition).

use super::custom_op::{F32Op, like, with_f32};
use candle_core::{Layout, Result, Shape, Tensor};
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

impl Act {
    /// The activation of one value.
    #[inline]
    pub(super) fn apply(self, z: f32) -> f32 {
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
    pub(super) fn slope(self, z: f32) -> f32 {
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
