//! The custom candle ops behind [`crate::layers`] on contiguous f32 CPU tensors:
//! their forward kernels and one-pass backwards. Each op implements [`F32Op`] (its
//! name, a forward from the inputs' values and layouts, a backward giving each
//! input's gradient); the one generic wrapper [`Op`] turns it into candle's
//! `CustomOp1`, `CustomOp2` or `CustomOp3`, so the storage handling, the result's
//! wrapping and the gradient plumbing are written once. Each op is tested against
//! the candle composition it replaces (forward and gradients), which stays the path
//! on other devices and dtypes.
//!
//! One file per concern: [`custom_op`] (the wrapper), [`resample`], [`activation`],
//! [`convolution`], [`points`], [`softmax`] and [`batch_norm`].

mod activation;
mod batch_norm;
mod convolution;
mod custom_op;
mod points;
mod resample;
mod softmax;

pub use activation::Act;
pub(crate) use activation::{Activation, AddRelu};
pub(crate) use batch_norm::FusedBn;
pub(crate) use convolution::FastConv2d;
pub(crate) use custom_op::{ApplyF32Op, with_f32};
pub(crate) use points::{AddRowsRelu, MeanPoints, PointLinearOp};
pub use resample::interp_matrix_align_corners;
pub(crate) use resample::{GatherPixels, MaxPool3x3S2, ResizeAlignCorners, SamplePoints, Taps};
pub(crate) use softmax::{LogSoftmaxLast, RowEntropy};
