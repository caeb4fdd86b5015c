//! The faces of a photo go through the network in one batch and one forward pass
//! (`predict_photo`, `predict_crops`). Checked against the path it replaced, written
//! out here from the network's public parts: each face alone, the dense network run
//! once for the mask and again inside the full forward pass. The shipped tiny model on
//! synthetic group photos (`synth --group-photo`'s) of 1 and 3 faces, and on more
//! crops than one batch holds.

use arkit_data::ingest::synth::{FaceSource, SynthOptions, group_photo};
use arkit_data::loader::normalise;
use arkit_data::picture::{DEMO_SIDE, DemoSquare, demo_crop};
use arkit_data::pose::{FacePose, PhotoCamera, RansacParams, face_pose};
use arkit_perspnet::{
    CropInput, MAX_CROP_BATCH, NetworkPrediction, TrainedModel, UV_SCALE, face_seed, predict_crop,
    predict_crops, predict_photo,
};
use candle_core::{Device, Tensor};

const TINY: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../models/tiny-synthetic");

fn tiny() -> TrainedModel {
    let topology = arkit_data::mesh::builtin().topology.clone();
    arkit_perspnet::load(std::path::Path::new(TINY), &topology).unwrap()
}

/// The old path for one crop: the dense network for the mask, the pixels chosen from
/// it, then the whole network again (its dense part recomputed) for the
/// correspondences and the mesh.
fn two_pass_prediction(model: &TrainedModel, input: &[f32], seed: u64) -> NetworkPrediction {
    let net = model.net.perspnet("test").unwrap();
    let cfg = &model.checkpoint.config;
    let s = cfg.input_size;
    let img = Tensor::from_slice(input, (1, 3, s, s), &Device::Cpu).unwrap();
    let dense = net.forward_dense(&img, false).unwrap();
    let logits = dense.seg_logits.squeeze(0).unwrap();
    let face = logits
        .get(1)
        .unwrap()
        .ge(&logits.get(0).unwrap())
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<u8>()
        .unwrap();
    let mask: Vec<bool> = face.iter().map(|&v| v != 0).collect();
    let mut candidates: Vec<u32> = (0..mask.len() as u32)
        .filter(|&i| mask[i as usize])
        .collect();
    if candidates.is_empty() {
        candidates = (0..mask.len() as u32).collect();
    }
    let picks = arkit_data::render::sample_points(candidates.len(), cfg.points, seed);
    let pixels: Vec<u32> = picks.iter().map(|&k| candidates[k as usize]).collect();
    let choose = Tensor::from_slice(&pixels, (1, cfg.points), &Device::Cpu).unwrap();
    let out = net.forward(&img, &choose, false).unwrap();
    let corr = out
        .correspondences()
        .unwrap()
        .affine(1.0 / UV_SCALE, 0.0)
        .unwrap()
        .squeeze(0)
        .unwrap()
        .to_vec2::<f32>()
        .unwrap();
    let verts = out
        .vertices
        .affine(1.0 / UV_SCALE, 0.0)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    NetworkPrediction {
        mask,
        pixels,
        points: corr.iter().map(|p| [p[0], p[1], p[2]]).collect(),
        verts,
    }
}

fn assert_same_prediction(a: &NetworkPrediction, b: &NetworkPrediction, what: &str) {
    assert_eq!(a.mask, b.mask, "{what}: mask");
    assert_eq!(a.pixels, b.pixels, "{what}: chosen pixels");
    assert_eq!(a.points, b.points, "{what}: correspondences, bit for bit");
    assert_eq!(a.verts, b.verts, "{what}: mesh, bit for bit");
}

#[test]
fn one_batched_forward_gives_the_two_pass_poses_on_photos_of_1_and_3_faces() {
    let model = tiny();
    let size = model.checkpoint.config.input_size as u32;
    let ransac = RansacParams::default();
    let options = SynthOptions {
        width: 1280,
        height: 720,
        seed: 1,
        ..SynthOptions::default()
    };
    let seed = 0x5eed;
    for faces in [1, 3] {
        let photo = group_photo(&FaceSource::builtin(), &options, faces).unwrap();
        let boxes: Vec<[f64; 4]> = photo.faces.iter().map(|f| f.bbox).collect();
        for camera in [PhotoCamera::Demo, PhotoCamera::FocalPx(photo.focal_px)] {
            let new = predict_photo(&model, &photo.image, &boxes, &camera, seed, &ransac).unwrap();
            assert_eq!(new.len(), faces);
            let (w, h) = photo.image.dimensions();
            let square = DemoSquare::of(w, h, DEMO_SIDE);
            let padded = square.image(&photo.image);
            let mut posed = 0;
            for (k, (face, b)) in new.iter().zip(&boxes).enumerate() {
                let crop = demo_crop(square.box_to_square(*b), size).unwrap();
                let input = normalise(crop.crop_image(&padded).as_raw());
                let old = two_pass_prediction(&model, &input, face_seed(seed, k));
                let what = format!("{faces} faces, face {k}, {camera:?}");
                assert_same_prediction(&face.prediction, &old, &what);
                let old_pose: Option<FacePose> =
                    face_pose(&square, &crop, &camera, &old.pixels, &old.points, &ransac).unwrap();
                assert_eq!(face.pose, old_pose, "{what}: the pose, bit for bit");
                posed += old_pose.is_some() as usize;
            }
            assert_eq!(posed, faces, "every face is posed");
        }
    }
}

#[test]
fn crops_beyond_one_batch_each_give_their_own_prediction() {
    let model = tiny();
    let s = model.checkpoint.config.input_size;
    // More crops than one batch holds, each different (a ramp shifted per crop).
    let n = MAX_CROP_BATCH + 2;
    let inputs: Vec<Vec<f32>> = (0..n)
        .map(|k| {
            (0..3 * s * s)
                .map(|i| ((i * 7 + k * 131) % 97) as f32 / 48.0 - 1.0)
                .collect()
        })
        .collect();
    let crops: Vec<CropInput> = inputs
        .iter()
        .enumerate()
        .map(|(k, input)| CropInput {
            input,
            seed: 100 + k as u64,
            truth: None,
        })
        .collect();
    let batched = predict_crops(&model, &crops, false).unwrap();
    assert_eq!(batched.len(), n);
    for (k, ((p, raw), input)) in batched.iter().zip(&inputs).enumerate() {
        assert!(raw.is_none());
        let alone = predict_crop(&model, input, 100 + k as u64, None).unwrap();
        assert_same_prediction(p, &alone, &format!("crop {k}"));
        assert_same_prediction(
            p,
            &two_pass_prediction(&model, input, 100 + k as u64),
            &format!("crop {k} against the two passes"),
        );
    }
    // A crop of the wrong size is refused, naming the sizes.
    let short = [0f32; 10];
    let bad = [CropInput {
        input: &short,
        seed: 0,
        truth: None,
    }];
    let e = predict_crops(&model, &bad, false).unwrap_err().to_string();
    assert!(e.contains("10 values"), "{e}");
}
