//! `video`: head poses along a video.
//!
//! Takes a video file or a folder of frames; gives frames, face tracks, smoothed poses
//! and their rows. [`VideoSource`] decodes an H.264 MP4/MOV or reads a folder of
//! numbered frames, one frame at a time (`source.rs`); [`Tracker`] matches the faces of
//! successive frames into tracks with stable ids (`track.rs`); [`PoseFilter`] smooths
//! each track's pose with a One-Euro filter on SO(3) (`smooth.rs`); [`RowWriter`]
//! writes the rows as JSON lines, CSV or Parquet (`table.rs`); [`Mp4Encoder`] writes
//! frames as an H.264 MP4 (`encode.rs`); [`ClipPlan`] plans the synthetic clips that
//! measure all this, [`rest_jitter_deg`] and [`lag_frames`] the figures (`clip.rs`).
//! Guarantees: memory does not grow with a video's length; the same frames and boxes
//! give the same tracks and poses; outputs appear complete or not at all. Depends on
//! `picture`, `store` (Parquet) and `arkit_core`.

pub(crate) mod clip;
pub(crate) mod encode;
pub(crate) mod smooth;
pub(crate) mod source;
pub(crate) mod table;
pub(crate) mod track;

pub use self::{
    clip::{ClipKind, ClipPlan, lag_frames, rest_jitter_deg},
    encode::Mp4Encoder,
    smooth::{OneEuroParams, PoseFilter},
    source::{Frame, VideoSource, codec_name, convert_hint, video_codecs},
    table::{FrameRow, RowPose, RowWriter, json_row},
    track::{TrackedBox, Tracker, TrackerOptions, iou},
};
