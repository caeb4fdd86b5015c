//! `picture`: images in and out, for people and for the pipeline.
//!
//! Takes image files and the pipeline's meshes, boxes and figures. Gives decoded images
//! ([`read_rgb8_checked`]), faces found in a photo ([`detect_faces`]), the demo's square
//! crop ([`demo_crop`]), and pictures for people: mesh overlays ([`draw_projected_mesh`]),
//! SVG charts ([`bars_svg`], [`log_line_svg`]), contact sheets and preview JPEGs
//! ([`contact_sheet`], [`jpeg_bytes`]). Guarantees: every image the tool reads is decoded
//! here, its size checked from the header ([`ImageHeader`]) before any pixel buffer is
//! made. Depends on `mesh` and `arkit_core`.

pub(crate) mod detect;
pub(crate) mod encode;
pub(crate) mod image_decode;
pub(crate) mod overlay;
pub(crate) mod photo;
pub(crate) mod plot;

pub use self::{
    detect::{DetectOptions, DetectedFace, detect_faces},
    encode::{contact_sheet, jpeg_bytes},
    image_decode::{ImageHeader, check_jpeg_framing, read_photo_upright, read_rgb8_checked},
    overlay::{MeshStyle, draw_box, draw_projected_mesh},
    photo::{DEMO_SIDE, DemoSquare, demo_crop},
    plot::{Bars, Histogram, LINE_PLOT, PANEL_HEIGHT, PANEL_WIDTH, Series, bars_svg, log_line_svg},
};
