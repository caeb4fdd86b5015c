//! `detect`: face boxes found in a photo, for `predict --image` when no box is given.
//!
//! The detector is SeetaFace's funnel-structured cascade (Wu et al., 2016) through the
//! `rustface` crate, with the frontal model that crate ships (`seeta_fd_frontal_v1.0.bin`,
//! BSD-2-Clause, Copyright (c) 2016 VIPL, ICT, CAS), embedded at build time: nothing is
//! downloaded when it runs. It finds roughly frontal faces (up to about 45 degrees of
//! yaw) of at least [`DetectOptions::min_face_px`] pixels in the grey photo; profile
//! views, strong tilt and small or blurred faces are often missed. Its boxes are square
//! and tight around the eyes, nose and mouth, much like the boxes the official demo's
//! 0.75 rule expects from a RetinaFace detector (6dof_face issue #13).

use arkit_core::{Error, Result};
use image::RgbImage;

/// The embedded model (see the module docs).
static MODEL: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/seeta_fd_frontal.bin"));

/// Settings of [`detect_faces`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DetectOptions {
    /// The smallest face side searched for, pixels (at least 20).
    pub min_face_px: u32,
    /// The cascade's score a window needs to count as a face (rustface's example uses
    /// 2.0; higher finds fewer faces and fewer false ones).
    pub score_threshold: f64,
}

impl Default for DetectOptions {
    fn default() -> Self {
        DetectOptions {
            min_face_px: 40,
            score_threshold: 2.0,
        }
    }
}

/// One detected face.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DetectedFace {
    /// `[x0, y0, x1, y1]` in the photo's pixels.
    pub bbox: [f64; 4],
    /// The cascade's score (higher is surer).
    pub score: f64,
}

/// The faces SeetaFace's frontal detector finds in `photo`, left to right (then top to
/// bottom), boxes clipped to the photo. An empty list when there is none; the same
/// list for the same photo and options.
pub fn detect_faces(photo: &RgbImage, options: &DetectOptions) -> Result<Vec<DetectedFace>> {
    let (w, h) = photo.dimensions();
    if w == 0 || h == 0 {
        return Err(Error::invalid("photo", "has no pixels"));
    }
    if options.min_face_px < 20 || !options.score_threshold.is_finite() {
        return Err(Error::invalid(
            "face detector",
            format!(
                "minimum face {} px and score {}: the size must be at least 20 px and the score finite",
                options.min_face_px, options.score_threshold
            ),
        ));
    }
    let model = rustface::read_model(MODEL)
        .map_err(|e| Error::invalid("face detector", format!("its embedded model: {e}")))?;
    let mut detector = rustface::create_detector_with_model(model);
    detector.set_min_face_size(options.min_face_px);
    detector.set_score_thresh(options.score_threshold);
    detector.set_pyramid_scale_factor(0.8);
    detector.set_slide_window_step(4, 4);
    // ITU-R BT.601 luma, rounded: the grey image the cascade was trained on.
    let grey: Vec<u8> = photo
        .pixels()
        .map(|p| {
            let [r, g, b] = p.0;
            ((299 * r as u32 + 587 * g as u32 + 114 * b as u32 + 500) / 1000) as u8
        })
        .collect();
    let found = detector.detect(&rustface::ImageData::new(&grey, w, h));
    let mut faces: Vec<DetectedFace> = found
        .iter()
        .filter_map(|f| {
            let r = f.bbox();
            let x0 = (r.x() as f64).clamp(0.0, w as f64);
            let y0 = (r.y() as f64).clamp(0.0, h as f64);
            let x1 = (r.x() as f64 + r.width() as f64).clamp(0.0, w as f64);
            let y1 = (r.y() as f64 + r.height() as f64).clamp(0.0, h as f64);
            (x1 > x0 && y1 > y0).then_some(DetectedFace {
                bbox: [x0, y0, x1, y1],
                score: f.score(),
            })
        })
        .collect();
    faces.sort_by(|a, b| {
        (a.bbox[0], a.bbox[1])
            .partial_cmp(&(b.bbox[0], b.bbox[1]))
            .expect("finite boxes")
    });
    Ok(faces)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flat_photo_has_no_face() {
        let photo = RgbImage::from_pixel(320, 200, image::Rgb([128, 120, 110]));
        assert!(
            detect_faces(&photo, &DetectOptions::default())
                .unwrap()
                .is_empty()
        );
    }

    #[test]
    fn bad_options_and_empty_photos_are_refused() {
        let photo = RgbImage::new(0, 0);
        assert!(detect_faces(&photo, &DetectOptions::default()).is_err());
        let photo = RgbImage::new(64, 64);
        let small = DetectOptions {
            min_face_px: 10,
            ..DetectOptions::default()
        };
        assert!(detect_faces(&photo, &small).is_err());
    }

    /// The detector's own test photo, shipped in rustface's package (a 1927 group
    /// photo of 29 people, 1666 x 1136, most faces frontal, 40-60 px): read from the
    /// package, not copied into this repository.
    #[test]
    fn the_faces_of_a_group_photo_are_found() {
        let path = std::path::Path::new(env!("ARKIT_RUSTFACE_PACKAGE")).join("test.png");
        let Ok(photo) = image::open(&path) else {
            eprintln!("SKIPPED: {} is not readable", path.display());
            return;
        };
        let photo = photo.to_rgb8();
        let faces = detect_faces(&photo, &DetectOptions::default()).unwrap();
        assert!((25..=32).contains(&faces.len()), "{} faces", faces.len());
        for f in &faces {
            let [x0, y0, x1, y1] = f.bbox;
            assert!(x0 >= 0.0 && y0 >= 0.0 && x1 <= 1666.0 && y1 <= 1136.0);
            assert!((30.0..90.0).contains(&(x1 - x0)), "{:?}", f.bbox);
            // The faces sit in the upper half, above the caption.
            assert!(y1 < 700.0, "{:?}", f.bbox);
            assert!(f.score >= 2.0);
        }
        // Left to right, then top to bottom; the same list again.
        assert!(faces.windows(2).all(|w| w[0].bbox[0] <= w[1].bbox[0]));
        assert_eq!(
            detect_faces(&photo, &DetectOptions::default()).unwrap(),
            faces
        );
        // A higher score threshold keeps a subset.
        let strict = DetectOptions {
            score_threshold: 10.0,
            ..DetectOptions::default()
        };
        let fewer = detect_faces(&photo, &strict).unwrap();
        assert!(fewer.len() < faces.len() && fewer.iter().all(|f| faces.contains(f)));
    }

    #[test]
    fn the_embedded_model_is_the_released_file() {
        assert_eq!(MODEL.len(), 1_209_904);
        assert!(rustface::read_model(MODEL).is_ok());
    }
}
