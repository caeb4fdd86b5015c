//! `picture`: images in and out, for people and for the pipeline.
//!
//! Contract: every image the tool reads is decoded by [`image_decode`], its size checked
//! from the header before any pixel buffer is made; every picture it writes for people
//! (mesh overlays, SVG charts, contact sheets, preview JPEGs) is drawn and encoded here. Depends on
//! `mesh` and `arkit_core`.

pub mod detect;
pub mod encode;
pub mod image_decode;
pub mod overlay;
pub mod photo;
pub mod plot;
