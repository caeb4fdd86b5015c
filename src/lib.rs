//! `arkit_tool`: the library half of the `arkit-tool` command: what the command adds
//! to the workspace's crates. The pipeline itself is in those crates, each at its own
//! path:
//!
//! - `arkit_core`: conventions, bounded readers of the release's files, the rasterizer
//!   core; neither polars nor candle.
//! - `arkit_data`: converted datasets, rendering, augmentation, PnP, metrics, the loader
//!   of the Python package, one folder per stage.
//! - `arkit_perspnet` (feature `model`, on by default): the reference PerspNet in candle,
//!   its training and its predictions.
//!
//! This crate holds [`report`] and [`demo`] (pictures of each stage in one `index.html`,
//! and the whole pipeline on synthetic data), [`folder_state`] (what state each output of
//! a dataset folder is in, for `inspect`) and [`allocator`] (the process's allocator
//! settings, applied by the binary at start-up).
//!
//! Build without the network (no candle) with `--no-default-features`: every command
//! but `train`, `predict --model` and `demo`.

#![deny(missing_docs)]

pub mod allocator;
#[cfg(feature = "model")]
pub mod demo;
pub mod folder_state;
pub mod report;
