//! Synthetic input shared with the workspace's root tests.

/// A synthetic BIWI-shaped `hpdb` folder (the root's `tests/support/biwi_writer.rs`,
/// shared: its paths are `arkit_data`'s and `arkit_core`'s).
#[path = "../../../../tests/support/biwi_writer.rs"]
pub mod biwi_writer;
