//! Model folders converted: the official network's PyTorch `state_dict` imported into a
//! model folder and exported from one ([`import_weights`], [`export_weights`]), and a
//! model folder rewritten at half precision ([`write_half_model`]). They read and write
//! through `weights` and the checkpoint folder of `training`.

mod half;
mod import_export;

pub use half::write_half_model;
pub use import_export::{export_weights, import_weights};
