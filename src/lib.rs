//! `arkit_tool`: the library behind the `arkit-tool` command, one name for the
//! workspace's crates.
//!
//! - [`arkit_core`] (re-exported module by module): conventions, bounded readers of the
//!   release's files, the rasterizer core; neither polars nor candle.
//! - [`arkit_data`] (re-exported module by module, so `arkit_tool::render` is
//!   `arkit_data::render`): converted datasets, rendering, augmentation, PnP, metrics,
//!   the loader of the Python package.
//! - [`perspnet`] (feature `model`, on by default): the reference PerspNet in candle,
//!   its training and its predictions, from the `arkit-perspnet` crate.
//! - [`report`] and [`demo`]: pictures of each stage in one `index.html`, and the whole
//!   pipeline on synthetic data.
//!
//! Build without the network (no candle) with `--no-default-features`: every command
//! but `train`, `predict --model` and `demo`.

#![warn(missing_docs)]

pub use arkit_data::*;

#[cfg(feature = "model")]
pub mod demo;
pub mod report;

#[cfg(feature = "model")]
pub use arkit_perspnet as perspnet;
