//! Training the reference PerspNet on a rendered dataset, by job:
//!
//! - [`data`]: examples from the `samples` and `targets` tables, the view of an
//!   example the network sees in one step (crop shift, colour jitter, fresh face
//!   pixels), batches as candle tensors;
//! - [`run`]: the training loop, its options, its schedule and its seeded initial
//!   weights;
//! - [`checkpoint`]: the checkpoint folder (`perspnet.json`, `model.safetensors`,
//!   `adam.safetensors`, `loss.csv` and the record `checkpoint.json`), written
//!   atomically, checked on resume, loaded for prediction; the shipped model.

pub mod checkpoint;
pub mod data;
pub mod run;
