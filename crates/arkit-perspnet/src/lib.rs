//! PerspNet: ResNet-18 encoder, a 2D decoder (segmentation + image features),
//! a 3D decoder (UV position map), and the correspondence head that predicts a
//! soft assignment of sampled pixels to the 1,220 ARKit face-mesh vertices; and the
//! paper's "Direct 6DoF Regress" baseline on the same encoder ([`DirectNet`]).
//!
//! Shapes follow the official PyTorch code (`models/model_repository.py`
//! `Resnet18_8s`, `models/network.py` `DeformNetUV2`, `models/loss.py` `Loss8`).
//!
//! The crate `arkit-perspnet` of the workspace: the only one that needs candle. Its
//! modules are private and everything public is listed below, by job:
//!
//! - the network ([`PerspNet`], [`DirectNet`], [`Network`], [`PerspNetConfig`]) and
//!   its building blocks ([`layers`]: the candle layers and custom ops);
//! - its losses ([`PerspNetLoss`]) and optimiser ([`Adam`]);
//! - training ([`train`]): examples from a converted, rendered dataset
//!   ([`ShardedExamples`]), the view of an example the network sees in a step
//!   ([`Example`]), the loop, checkpoints ([`Checkpoint`], [`load`]);
//! - weights ([`load_weights`], [`import_weights`], [`export_weights`],
//!   [`write_half_model`]);
//! - inference ([`predict_crop`], [`predict_crops`] for a batch, [`model_predictions`]) and the faces of a photo
//!   ([`predict_photo`]);
//! - ONNX export ([`export_onnx`]: the network as two ONNX graphs, docs/onnx.md).
//!
//! What the network sees as input (docs/train.md, "What the network sees"): the
//! `S x S` crop, ImageNet-normalised ([`network_input`]); in training, that crop
//! colour-jittered by torchvision's `ColorJitter` rule ([`Augmentation::colour`],
//! the same jitter as the Python loader's) and shifted by whole pixels.

#![deny(missing_docs)]

mod adam;
mod blas;
mod candle_error;
mod config;
mod conv;
mod direct;
#[doc(hidden)]
pub mod fuzz_entry;
mod inference;
pub mod layers;
mod loss;
mod model;
mod model_conversion;
mod network;
mod onnx;
mod ops;
mod photo;
mod training;
mod weights;

pub use adam::Adam;
pub use config::{Architecture, LossVariant, PerspNetConfig};
pub use direct::{
    DirectNet, OUTPUT_OFFSET, direct_loss, direct_target, pose_from_output, rotation_from_6d,
    rotation_from_6d_f64,
};
pub use inference::{
    CropInput, MAX_CROP_BATCH, ModelPredictSummary, NetworkPrediction, RawOutputs, direct_pose,
    model_predictions, model_predictions_dump, pose_of, predict_crop, predict_crop_raw,
    predict_crops, write_dump,
};
pub use loss::{
    CorrTarget, LossTargets, LossTerms, LossWeights, PerspNetLoss, kl_loss, perspnet_loss,
    seg_cross_entropy, smooth_l1_sum_mean,
};
pub use model::{
    DenseOutput, EncoderFeatures, PerspNet, PerspNetOutput, UV_SCALE, named_trainable_vars,
    parameter_count, synthetic_vertex_uv, trainable_vars,
};
pub use model_conversion::{export_weights, import_weights, write_half_model};
pub use network::{Network, vertex_uv};
pub use onnx::{
    ONNX_FILES, ONNX_OPSET, OnnxExport, OnnxGraphInfo, OnnxManifest, OnnxValue, POINT_SELECTION,
    export_onnx,
};
pub use photo::{PhotoFace, face_seed, predict_photo};
pub use training::checkpoint::{
    ADAM_FILE, CHECKPOINT_RECORD, Checkpoint, SHIPPED_MODEL_DIR, StepLoss, TrainedModel, load,
    shipped_checkpoint, shipped_model, verify_checkpoint, verify_model,
};
pub use training::data::{
    Augmentation, Batch, Example, ExampleShards, NOCS_SCALE, ShardedExamples, batch, example,
    network_input, read_examples,
};
pub use training::run::{
    TrainOptions, learning_rate_at, reseed, steps_per_epoch, total_steps, train,
};
pub use weights::safetensors_file::SafetensorsFile;
pub use weights::state_dict::{export_state_dict, state_dict_entries};
pub use weights::{load_weights, open_weights};
