//! The end-to-end tests of the `arkit-tool` command (and of what only the whole
//! workspace can check: the Python loader's files, the shard processes, the official
//! crop against OpenCV), one test binary. The libraries' own behaviour is tested in
//! their crates' `tests/`.

mod support;

mod biwi;
mod charts;
mod cli;
mod cloud;
mod convert;
#[cfg(feature = "model")]
mod direct_commands;
mod hostile;
mod import_arkit;
mod kill;
mod kill_all;
mod official_crop;
mod options;
mod ownership;
#[cfg(feature = "model")]
mod photo_defects;
#[cfg(feature = "model")]
mod photo_mesh;
#[cfg(feature = "model")]
mod photos;
#[cfg(unix)]
mod readers;
#[cfg(feature = "model")]
mod report_browser;
mod shard_processes;
#[cfg(feature = "model")]
mod shipped_model;
mod synth_dataset;
#[cfg(feature = "model")]
mod video;
#[cfg(feature = "model")]
mod weights;
