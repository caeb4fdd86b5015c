//! `augment`: more training samples by face profiling.
//!
//! Takes a converted dataset (`store`) and a [`ProfilingRule`]. Gives new samples:
//! [`profile`] rotates one sample's face out of plane through its mesh ([`roll`] and
//! [`mirror`] roll or mirror it), and [`augment_dataset`] picks the samples from the rule
//! and writes them in the release's download layout, so `convert` reads them as it reads
//! the release. Guarantees: the image and the annotation change together (one mesh
//! moved, one picture resampled from it); a sample that cannot be profiled is reported
//! ([`Skip`]) and left out. Depends on `store`, `picture`, `mesh` and
//! `arkit_core`.

pub(crate) mod dataset;
pub(crate) mod sample;

pub use self::{
    dataset::{
        AugmentOptions, AugmentSummary, AugmentedRecord, AxisChoice, ProfilingRule,
        augment_dataset, drawn,
    },
    sample::{
        Axis, FaceImage, NOSE_TIP_LANDMARK, ProfileMesh, Skip, mirror, profile, profile_mesh, roll,
    },
};
