//! `video`: head poses along a video.
//!
//! [`VideoSource`] decodes an H.264 MP4/MOV or reads a folder of numbered frames, one
//! frame at a time ([`source`]); [`Tracker`] matches the faces of successive frames
//! into tracks with stable ids ([`track`]); [`PoseFilter`] smooths each track's pose
//! with a One-Euro filter on SO(3) ([`smooth`]); [`Mp4Encoder`] writes frames as an
//! H.264 MP4 ([`encode`]); [`clip`] plans the synthetic clips that measure all this.
//! Depends on `picture` and `arkit_core`.

pub mod clip;
pub mod encode;
pub mod smooth;
pub mod source;
pub mod table;
pub mod track;

pub use self::{
    clip::{ClipKind, ClipPlan, lag_frames, rest_jitter_deg},
    encode::Mp4Encoder,
    smooth::{OneEuroParams, PoseFilter},
    source::{Frame, VideoSource, codec_name, convert_hint, video_codecs},
    table::{FrameRow, RowPose, RowWriter},
    track::{TrackedBox, Tracker, TrackerOptions, iou},
};
