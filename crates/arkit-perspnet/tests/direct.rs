//! The "Direct 6DoF Regress" baseline ([`arkit_perspnet::DirectNet`]): shapes, every
//! output a rotation, the tensor and scalar Gram-Schmidt agree, the targets' round
//! trip through the crop and the camera, and a tiny run trained, saved, loaded,
//! predicted and evaluated (the commands on such a model: the root's
//! `tests/direct_commands.rs`).

use arkit_core::Rng;
use arkit_core::conventions::{Camera, EulerAngles, Pose};
use arkit_data::crop::CropTransform;
use arkit_data::eval::EvalOptions;
use arkit_data::ingest::synth::{self, FaceSource, SynthOptions};
use arkit_data::ingest::{self, ConvertOptions, ValidationContext};
use arkit_data::pose::RansacParams;
use arkit_data::render::FaceRenderer;
use arkit_data::render::RenderOptions;
use arkit_perspnet::TrainOptions;
use arkit_perspnet::{Architecture, PerspNetConfig};
use arkit_perspnet::{
    DirectNet, OUTPUT_OFFSET, direct_loss, direct_target, pose_from_output, rotation_from_6d,
    rotation_from_6d_f64,
};
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use nalgebra::{Matrix3, Vector3};
use std::path::Path;

fn direct_tiny() -> PerspNetConfig {
    PerspNetConfig {
        architecture: Architecture::Direct,
        ..PerspNetConfig::tiny()
    }
}

fn assert_rotation(r: &Matrix3<f64>, tol: f64) {
    let dev = (r.transpose() * r - Matrix3::identity()).abs().max();
    assert!(dev < tol, "not orthonormal: {dev:e}\n{r}");
    assert!(
        (r.determinant() - 1.0).abs() < tol,
        "det {}",
        r.determinant()
    );
}

#[test]
fn forward_shapes_and_every_output_is_a_rotation() {
    let cfg = direct_tiny();
    let dev = Device::Cpu;
    let vm = VarMap::new();
    let net = DirectNet::new(&cfg, VarBuilder::from_varmap(&vm, DType::F32, &dev)).unwrap();
    arkit_perspnet::reseed(&vm, 1, cfg.init_std).unwrap();
    let img = Tensor::randn(0f32, 1.0, (3, 3, 64, 64), &dev).unwrap();
    let out = net.forward(&img, false).unwrap();
    assert_eq!(out.dims(), &[3, 9]);
    // Weights at N(0, 0.02): the output starts near the offset pose.
    let o = out.to_vec2::<f32>().unwrap();
    for row in &o {
        for (v, c) in row.iter().zip(OUTPUT_OFFSET) {
            assert!((v - c).abs() < 0.5, "{row:?}");
        }
    }
    // Any 6 numbers give a rotation, in candle and in f64, and the two agree.
    let mut rng = Rng::new(4);
    let raw: Vec<f32> = (0..6 * 50).map(|_| rng.normal() as f32 * 2.0).collect();
    let t = Tensor::from_vec(raw.clone(), (50, 6), &dev).unwrap();
    let r = rotation_from_6d(&t).unwrap();
    assert_eq!(r.dims(), &[50, 3, 3]);
    let r = r.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    for b in 0..50 {
        let a: [f64; 6] = std::array::from_fn(|i| raw[6 * b + i] as f64);
        let m = rotation_from_6d_f64(&a);
        assert_rotation(&m, 1e-9);
        let from_tensor = Matrix3::from_row_slice(
            &r[9 * b..9 * b + 9]
                .iter()
                .map(|&v| v as f64)
                .collect::<Vec<_>>(),
        );
        assert!((from_tensor - m).abs().max() < 1e-5, "{b}");
        // The first column keeps a1's direction.
        let a1 = Vector3::new(a[0], a[1], a[2]).normalize();
        assert!((m.column(0) - a1).norm() < 1e-12);
    }
}

#[test]
fn targets_map_back_to_the_pose_through_crop_and_camera() {
    let k = arkit_data::pose::intrinsics(256, 256);
    let mut rng = Rng::new(9);
    for i in 0..40 {
        let pose = Pose::from_euler(
            EulerAngles::new(
                rng.uniform(-80.0, 80.0),
                rng.uniform(-40.0, 40.0),
                rng.uniform(-30.0, 30.0),
            ),
            Vector3::new(
                rng.uniform(-0.05, 0.05),
                rng.uniform(-0.05, 0.05),
                -rng.uniform(0.3, 0.7),
            ),
        );
        let crop = CropTransform {
            x0: rng.uniform(60.0, 100.0),
            y0: rng.uniform(60.0, 100.0),
            side: rng.uniform(60.0, 120.0),
            side_y: rng.uniform(60.0, 120.0),
            size: 64,
            rules: Default::default(),
        };
        let t = direct_target(&pose, &crop, &k, (0, 0));
        // The network's 6D is R's first two columns; R is row-major in the target.
        let out = [t[0], t[3], t[6], t[1], t[4], t[7], t[9], t[10], t[11]];
        let back = pose_from_output(&out, &crop, &k).unwrap();
        let (r0, r1) = (pose.rotation(), back.rotation());
        assert!((r0.matrix() - r1.matrix()).abs().max() < 1e-6, "{i}");
        assert!(
            (pose.translation_m() - back.translation_m()).norm() < 1e-5,
            "{i}: {} vs {}",
            pose.translation_m(),
            back.translation_m()
        );
        assert!(t[11] > 0.0);
        // A crop shifted by d pixels moves the face's origin by d / S in the box.
        let s = direct_target(&pose, &crop, &k, (3, -2));
        assert!((s[9] - t[9] - 3.0 / 64.0).abs() < 1e-6);
        assert!((s[10] - t[10] + 2.0 / 64.0).abs() < 1e-6);
        assert_eq!(s[11], t[11]);
    }
    // No pose behind the camera or from non-finite numbers.
    let crop = CropTransform::around_landmarks(&[0.0, 0.0, 10.0, 10.0], 64);
    let mut out = OUTPUT_OFFSET;
    out[8] = -0.5;
    assert!(pose_from_output(&out, &crop, &k).is_none());
    out[8] = f32::NAN;
    assert!(pose_from_output(&out, &crop, &k).is_none());
}

/// The loss is zero at the target and its rotation term is the mean L1 over R.
#[test]
fn loss_hand_values() {
    let dev = Device::Cpu;
    let k = arkit_data::pose::intrinsics(256, 256);
    let pose = Pose::from_euler(
        EulerAngles::new(20.0, -10.0, 5.0),
        Vector3::new(0.01, 0.0, -0.5),
    );
    let crop = CropTransform::around_landmarks(&[100.0, 100.0, 150.0, 160.0], 64);
    let t = direct_target(&pose, &crop, &k, (0, 0));
    let out = [t[0], t[3], t[6], t[1], t[4], t[7], t[9], t[10], t[11]];
    let out = Tensor::from_slice(&out, (1, 9), &dev).unwrap();
    let target = Tensor::from_slice(&t, (1, 12), &dev).unwrap();
    let (total, rot, trans) = direct_loss(&out, &target).unwrap();
    assert!(total.to_scalar::<f32>().unwrap() < 1e-6);
    // Translation off by (0.3, 0, 0): 0.1 mean; rotation unchanged.
    let shifted = out
        .broadcast_add(
            &Tensor::from_slice(&[0f32, 0., 0., 0., 0., 0., 0.3, 0., 0.], (1, 9), &dev).unwrap(),
        )
        .unwrap();
    let (_, rot2, trans2) = direct_loss(&shifted, &target).unwrap();
    assert!((trans2.to_scalar::<f32>().unwrap() - 0.1).abs() < 1e-6);
    assert_eq!(
        rot2.to_scalar::<f32>().unwrap(),
        rot.to_scalar::<f32>().unwrap()
    );
    assert!(trans.to_scalar::<f32>().unwrap() < 1e-6);
    // The identity against R = diag(1, -1, -1): entries off by 2 at four places of nine.
    let id = Tensor::from_slice(
        &[1f32, 0., 0., 0., 1., 0., t[9], t[10], t[11]],
        (1, 9),
        &dev,
    )
    .unwrap();
    let flip = [1f32, 0., 0., 0., -1., 0., 0., 0., -1., t[9], t[10], t[11]];
    let (_, rot3, _) =
        direct_loss(&id, &Tensor::from_slice(&flip, (1, 12), &dev).unwrap()).unwrap();
    assert!((rot3.to_scalar::<f32>().unwrap() - 4.0 / 9.0).abs() < 1e-6);
}

/// A converted, rendered synthetic dataset of 2 subjects x 4 images, split 1/1.
fn dataset(dir: &Path) {
    let release = dir.join("release");
    let options = SynthOptions {
        subjects: 2,
        images_per_subject: 4,
        width: 256,
        height: 256,
        seed: 5,
        ..SynthOptions::default()
    };
    synth::generate(&FaceSource::builtin(), &options, &release, &|| {}).unwrap();
    let topology = arkit_data::mesh::builtin().topology.clone();
    let ctx = ValidationContext {
        projection: Camera::release_projection(),
        topology: topology.clone(),
        embed_images: false,
    };
    let copts = ConvertOptions {
        input: release,
        output: dir.join("pq"),
        resources: None,
        rows_per_shard: 100,
        embed_images: false,
        shard_index: 0,
        shard_count: 1,
        overwrite: false,
    };
    ingest::convert(&copts, &ctx, &|_| {}).unwrap();
    let renderer = FaceRenderer::new(topology, Camera::release_projection()).unwrap();
    let ro = RenderOptions {
        size: 64,
        uv_size: 16,
        points: 256,
        seed: 1,
        shard: (0, 1),
        full_mask: false,
        output: dir.join("pq"),
    };
    arkit_data::render::render_dataset(&dir.join("pq"), &renderer, &ro, &|_| {}).unwrap();
}

#[test]
fn trains_saves_loads_predicts_and_evaluates() {
    let dir = tempfile::tempdir().unwrap();
    dataset(dir.path());
    let pq = dir.path().join("pq");
    let topology = arkit_data::mesh::builtin().topology.clone();
    let cfg = direct_tiny();
    let examples = arkit_perspnet::read_examples(&pq, &pq, &cfg, None).unwrap();
    assert_eq!(examples.len(), 8);
    // Overfit four samples (no augmentation): the loss falls well below its start.
    let model = dir.path().join("model");
    let topts = TrainOptions {
        config: cfg.clone(),
        epochs: 40,
        max_steps: None,
        batch: 4,
        learning_rate: 2e-3,
        lr_hold: 0.5,
        augmentation: arkit_perspnet::Augmentation::NONE,
        seed: 2,
        resume: false,
        lowered_start: false,
        output: model.clone(),
    };
    let (ck, log) = arkit_perspnet::train(&examples[..4], &topology, &topts, &|_| {}).unwrap();
    assert_eq!(
        (ck.steps, ck.config.architecture),
        (40, Architecture::Direct)
    );
    let first = log[0].total;
    let last = log
        .iter()
        .rev()
        .take(3)
        .map(|s| s.total)
        .fold(f32::MAX, f32::min);
    assert!(last < 0.5 * first, "loss {first} -> {last}");
    assert!(log.iter().all(|s| s.kl == 0.0 && s.seg == 0.0));
    let csv = std::fs::read_to_string(model.join("loss.csv")).unwrap();
    assert!(
        csv.starts_with("step,epoch,total,rotation,translation"),
        "{csv}"
    );
    // The folder holds the encoder under PerspNet's names and the head.
    let w = candle_core::safetensors::load(model.join("model.safetensors"), &Device::Cpu).unwrap();
    assert!(w.contains_key("cnn.resnet18_8s.layer4.1.conv2.weight"));
    assert!(w.contains_key("direct_head.2.weight") && !w.contains_key("cnn.uv.weight"));

    // Loaded back, it predicts the same every time, valid rotations only.
    let predict = || {
        let m = arkit_perspnet::load(&model, &topology).unwrap();
        arkit_perspnet::model_predictions(
            &pq,
            &m,
            None,
            arkit_data::crop::RuleSet::Exact,
            None,
            0,
            &RansacParams::default(),
            &|_| {},
        )
        .unwrap()
    };
    let (rows, summary) = predict();
    assert_eq!((summary.samples, summary.failures), (8, 0));
    assert_eq!(rows, predict().0);
    for p in &rows {
        let rt = p.rt.unwrap();
        Pose::check_release_rt(&rt).unwrap();
        let pose = Pose::from_release_rt(&rt).unwrap();
        assert_rotation(pose.rotation().matrix(), 1e-9);
        assert!(p.verts.is_none() && p.mask_rle.is_none());
    }
    // The trained samples are predicted better than the mean pose of the untrained
    // network (the offset pose): it learned from its targets.
    let ev = arkit_data::eval::evaluate(
        &pq,
        &rows,
        &EvalOptions {
            split: None,
            ..EvalOptions::default()
        },
    )
    .unwrap();
    assert_eq!(ev.summary.samples, 8);
    assert!(ev.summary.recon_mean_mm.is_none() && ev.summary.mask.is_none());
    let cols = ev.summary.columns();
    assert_eq!(cols[11], ("3DRecon", "-".to_string()));
    assert!(ev.summary.mae_r_deg.is_finite());
}
