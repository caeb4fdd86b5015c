//! Poses of the faces in a photo, as the official `demo.py` finds them: the photo padded
//! to a square and resized to 800 px ([`DemoSquare`]), each face box cut by the 0.75 rule
//! into the network's crop ([`demo_crop`]), the network's mask, chosen pixels and
//! correspondences (all the faces of a photo in one batch, [`predict_crops`]), and the pose by our PnP in the camera asked for
//! ([`face_pose`]).

use crate::inference::{CropInput, NetworkPrediction, predict_crops};
use crate::training::checkpoint::TrainedModel;
use arkit_core::Result;
use arkit_data::crop::CropTransform;
use arkit_data::loader::normalise;
use arkit_data::picture::{DEMO_SIDE, DemoSquare, demo_crop};
use arkit_data::pose::RansacParams;
use arkit_data::pose::{FacePose, PhotoCamera, check_box, face_pose};
use image::RgbImage;

/// One face of a photo, every stage kept so that each can be checked.
#[derive(Clone, Debug)]
pub struct PhotoFace {
    /// The face box `[x0, y0, x1, y1]` in the photo's pixels, as given or detected.
    pub bbox: [f64; 4],
    /// The crop, in the demo's square.
    pub crop: CropTransform,
    /// The crop fed to the network (8-bit RGB, before normalisation).
    pub crop_image: RgbImage,
    /// The network's mask, chosen pixels, correspondences and mesh.
    pub prediction: NetworkPrediction,
    /// The pose, or `None` when PnP failed.
    pub pose: Option<FacePose>,
}

/// The seed of the pixels chosen for face `face` of a photo predicted with `seed`:
/// `seed ^ face`, so that face 0 uses `seed` itself, as sample `i` of shard `k` uses
/// `seed ^ (k << 32 | i)` in `predict --dataset`. RANSAC takes `ransac`'s seed for
/// every face, as `predict --dataset` does for every sample.
pub fn face_seed(seed: u64, face: usize) -> u64 {
    seed ^ face as u64
}

/// Predicts the pose of each face box of `photo` with a PerspNet (the direct baseline is
/// refused: it regresses a pose in the crop's own camera). Face `k` chooses its pixels
/// with [`face_seed`]`(seed, k)`; RANSAC runs with `ransac` as given.
pub fn predict_photo(
    model: &TrainedModel,
    photo: &RgbImage,
    boxes: &[[f64; 4]],
    camera: &PhotoCamera,
    seed: u64,
    ransac: &RansacParams,
) -> Result<Vec<PhotoFace>> {
    model.net.perspnet("predict --image")?;
    camera.check()?;
    let (w, h) = photo.dimensions();
    for b in boxes {
        check_box(*b, w, h)?;
    }
    if boxes.is_empty() {
        return Ok(Vec::new());
    }
    let size = model.checkpoint.config.input_size as u32;
    let square = DemoSquare::of(w, h, DEMO_SIDE);
    let padded = square.image(photo);
    let mut crops = Vec::with_capacity(boxes.len());
    for b in boxes {
        let crop = demo_crop(square.box_to_square(*b), size)?;
        let crop_image = crop.crop_image(&padded);
        let input = normalise(crop_image.as_raw());
        crops.push((crop, crop_image, input));
    }
    // The faces go through the network together (one batch), each with its own seed.
    let inputs: Vec<CropInput> = crops
        .iter()
        .enumerate()
        .map(|(k, (_, _, input))| CropInput {
            input,
            seed: face_seed(seed, k),
            truth: None,
        })
        .collect();
    let predictions = predict_crops(model, &inputs, false)?;
    boxes
        .iter()
        .zip(crops)
        .zip(predictions)
        .map(|((b, (crop, crop_image, _)), (prediction, _))| {
            let pose = face_pose(
                &square,
                &crop,
                camera,
                &prediction.pixels,
                &prediction.points,
                ransac,
            )?;
            Ok(PhotoFace {
                bbox: *b,
                crop,
                crop_image,
                prediction,
                pose,
            })
        })
        .collect()
}
