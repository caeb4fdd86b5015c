//! `augment`: more training samples by face profiling.
//!
//! Contract: [`sample`] rotates one sample's face out of plane through its mesh (and
//! rolls or mirrors it), changing the image and the annotation together; [`dataset`]
//! picks the samples from a rule and writes them in the release's download layout, so
//! `convert` reads them as it reads the release. Depends on `store`, `picture`, `mesh`
//! and `arkit_core`.

pub mod dataset;
pub mod sample;
