//! PerspNet: ResNet-18 encoder, a 2D decoder (segmentation + image features),
//! a 3D decoder (UV position map), and the correspondence head that predicts a
//! soft assignment of sampled pixels to the 1,220 ARKit face-mesh vertices; and the
//! paper's "Direct 6DoF Regress" baseline on the same encoder ([`direct`]).
//!
//! Shapes follow the official PyTorch code (`models/model_repository.py`
//! `Resnet18_8s`, `models/network.py` `DeformNetUV2`, `models/loss.py` `Loss8`).
//!
//! The crate `arkit-perspnet` of the workspace: the only one that needs candle. The
//! model and its layers here; [`training`]: examples from a converted dataset, the
//! training loop, checkpoints, the network's predictions.

#![warn(missing_docs)]

pub mod adam;
mod blas;
pub mod config;
pub mod conv;
pub mod direct;
pub mod layers;
pub mod loss;
pub mod model;
pub use weights::safetensors_file;
pub mod training;
pub mod weights;

pub use adam::Adam;
pub use config::{Architecture, LossVariant, PerspNetConfig};
pub use direct::DirectNet;
pub use loss::{CorrTarget, LossTargets, LossTerms, LossWeights, PerspNetLoss};
pub use model::{PerspNet, PerspNetOutput};
