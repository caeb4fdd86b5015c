//! From 2D-3D correspondences to a pose in the release's form, and the oracle
//! predictor that checks the whole evaluation path.
//!
//! [`pose_from_correspondences`] is the one bridge between the network's output (crop
//! pixels and the canonical points they show) and [`crate::pose::pnp`]: crop pixels are
//! mapped to full-image pixels through the stored crop transform, with pixel `(i, j)` at
//! its centre `(i + 0.5, j + 0.5)` (at `(i, j)` for targets rendered with the official
//! rules, which sample there), the release camera's pinhole intrinsics are used for
//! the image's own size (the official evaluation hard-codes 800x800), and OpenCV's
//! `(R, t)` becomes the release's `R_t` by [`Pose::from_opencv`].
//!
//! The **oracle** takes the ground-truth correspondences that `render` stored (the
//! sampled face pixels and the canonical points under them), optionally adds Gaussian
//! pixel noise and outliers, and runs the same PnP: with no noise every pose metric
//! must be ~0, which checks render, the crop transform, PnP and eval together; with
//! 1 px noise it gives the floor any model meets.

use crate::crop::CropTransform;
use crate::pose::pnp::{self, Intrinsics, RansacParams};
use crate::store::targets_table::{self, TargetsRecord};
use arkit_core::PredictionRecord;
use arkit_core::Rng;
use arkit_core::SampleKey;
use arkit_core::conventions::{Camera, Pose};
use arkit_core::{Error, Result};
use nalgebra::{Point2, Point3};
use rayon::prelude::*;
use std::collections::HashMap;
use std::path::Path;

/// The image point of crop pixel index `pixel` (row-major in a `crop.size` square): its
/// centre or its corner, as the crop's [`RuleSet`](crate::crop::RuleSet) says.
pub fn crop_pixel_to_image(crop: &CropTransform, pixel: u32) -> Point2<f64> {
    let (u, v) = crop.pixel_to_image(pixel % crop.size, pixel / crop.size);
    Point2::new(u, v)
}

/// The intrinsics of the release camera for an image of `width` x `height`.
pub fn intrinsics(width: u32, height: u32) -> Intrinsics {
    let k = Camera::release(width, height).pinhole();
    Intrinsics {
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
    }
}

/// The pose of a face whose canonical points `object` are seen at image points `image`
/// (RANSAC, then refinement on the inliers), with the inlier count.
pub fn pose_from_correspondences(
    object: &[Point3<f64>],
    image: &[Point2<f64>],
    k: &Intrinsics,
    params: &RansacParams,
) -> std::result::Result<(Pose, usize), pnp::PnpError> {
    let s = pnp::solve_pnp_ransac(object, image, k, params)?;
    Ok((
        Pose::from_opencv(&s.rotation, &s.translation),
        s.inliers.len(),
    ))
}

/// Options of the oracle.
#[derive(Clone, Debug)]
pub struct OracleOptions {
    /// Gaussian noise added to each image point, pixels (standard deviation).
    pub noise_px: f64,
    /// Share of points replaced by uniformly random image points.
    pub outliers: f64,
    /// Seed of the noise.
    pub seed: u64,
    /// Only samples of this split (`None`: all), as `eval` chooses them.
    pub split: Option<String>,
    /// PnP settings.
    pub ransac: RansacParams,
}

/// What the oracle did.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct OracleSummary {
    /// Samples predicted.
    pub samples: usize,
    /// PnP failures (null `R_t` written).
    pub failures: usize,
    /// Samples of the split with no targets row (not predicted): those `render` could
    /// not render (listed in `targets/errors/`). A shard without its targets file is
    /// refused instead.
    pub without_targets: usize,
    /// Mean distinct points per sample.
    pub mean_points: f64,
}

/// Canonical points and the image points where they are seen.
pub type Correspondences = (Vec<Point3<f64>>, Vec<Point2<f64>>);

/// The correspondences of one stored targets row: distinct sampled pixels as image
/// points, and the canonical points under them.
fn stored_correspondences(
    record: &TargetsRecord,
    verts: &[Point3<f32>],
) -> Result<Correspondences> {
    let d = targets_table::dense(record, verts)?;
    let mut seen = std::collections::HashSet::new();
    let (mut object, mut image) = (Vec::new(), Vec::new());
    for (px, c) in d.chosen_pixels.iter().zip(&d.coords) {
        if seen.insert(*px) {
            object.push(Point3::new(c[0] as f64, c[1] as f64, c[2] as f64));
            image.push(crop_pixel_to_image(&record.crop, *px));
        }
    }
    Ok((object, image))
}

/// Runs the oracle over a rendered dataset (`targets_dir` holds `targets/`).
pub fn oracle_predictions(
    dataset: &Path,
    targets_dir: &Path,
    options: &OracleOptions,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<(Vec<PredictionRecord>, OracleSummary)> {
    if !(options.noise_px.is_finite() && options.noise_px >= 0.0) {
        return Err(Error::invalid(
            "--noise-px",
            format!(
                "{} is not a non-negative number of pixels",
                options.noise_px
            ),
        ));
    }
    if !(0.0..1.0).contains(&options.outliers) {
        return Err(Error::invalid(
            "--outliers",
            format!("{} is not a share in [0, 1)", options.outliers),
        ));
    }
    let data = crate::store::dataset::Dataset::open(dataset)?;
    let splits = crate::store::splits::SplitLookup::read(dataset)?;
    // Opened with the dataset and checked to be of its generation: served to the end.
    let rendered = crate::store::RenderedTargets::open(targets_dir, &data)?;
    data.confirm_unchanged()?;
    let mut out = Vec::new();
    let mut summary = OracleSummary::default();
    let mut points = 0usize;
    for shard in data.shards() {
        let rows = data.read_samples(shard)?;
        let tpath = rendered.shard_path(shard.index);
        // A shard without its targets file is a render that has not finished (or has
        // not run): refused, never predicted as if its samples had no targets.
        if !rendered.has(shard.index) {
            rendered.confirm_unchanged()?;
            return Err(Error::format(
                &tpath,
                "no targets for this shard: `arkit-tool render` has not finished here (`arkit-tool inspect` says how far it got); rerun it",
            ));
        }
        let targets: HashMap<SampleKey, TargetsRecord> = rendered.by_key(shard.index)?;
        let chosen: Vec<_> = rows
            .iter()
            .enumerate()
            .filter(|(_, r)| splits.keeps(r, options.split.as_deref()))
            .collect();
        let results: Vec<Option<(PredictionRecord, usize)>> = chosen
            .par_iter()
            .map(|(i, r)| -> Result<Option<(PredictionRecord, usize)>> {
                let Some(t) = targets.get(&r.key) else {
                    progress(1);
                    return Ok(None);
                };
                let verts: Vec<Point3<f32>> = r
                    .verts
                    .chunks_exact(3)
                    .map(|c| Point3::new(c[0], c[1], c[2]))
                    .collect();
                let (object, mut image) = stored_correspondences(t, &verts)?;
                let mut rng = Rng::for_stream(options.seed, (shard.index as u64) << 32 | *i as u64);
                for p in &mut image {
                    if rng.next_f64() < options.outliers {
                        *p = Point2::new(
                            rng.uniform(0.0, r.image_width as f64),
                            rng.uniform(0.0, r.image_height as f64),
                        );
                    } else if options.noise_px > 0.0 {
                        p.x += options.noise_px * rng.normal();
                        p.y += options.noise_px * rng.normal();
                    }
                }
                let k = intrinsics(r.image_width, r.image_height);
                let params = RansacParams {
                    seed: options.ransac.seed ^ *i as u64,
                    ..options.ransac
                };
                let rt = pose_from_correspondences(&object, &image, &k, &params)
                    .ok()
                    .map(|(pose, _)| pose.to_release_rt());
                progress(1);
                Ok(Some((
                    PredictionRecord {
                        key: r.key.clone(),
                        rt,
                        verts: None,
                        mask_rle: None,
                    },
                    object.len(),
                )))
            })
            .collect::<Result<_>>()?;
        for r in results {
            match r {
                None => summary.without_targets += 1,
                Some((p, n)) => {
                    summary.samples += 1;
                    summary.failures += p.rt.is_none() as usize;
                    points += n;
                    out.push(p);
                }
            }
        }
    }
    summary.mean_points = points as f64 / summary.samples.max(1) as f64;
    Ok((out, summary))
}

/// The trivial baseline: one pose for every sample, the mean of a set of poses (the
/// training split's). The rotation is the chordal L2 mean (the rotation nearest, in
/// Frobenius norm, to the average of the rotation matrices: SVD projection onto
/// SO(3)); the translation is the arithmetic mean.
pub fn mean_pose(poses: &[Pose]) -> Result<Pose> {
    if poses.is_empty() {
        return Err(Error::invalid("mean pose", "no poses to average"));
    }
    let n = poses.len() as f64;
    let mut m = nalgebra::Matrix3::zeros();
    let mut t = nalgebra::Vector3::zeros();
    for p in poses {
        m += p.rotation().matrix();
        t += p.translation_m();
    }
    let svd = (m / n).svd(true, true);
    let (u, v_t) = (svd.u.expect("u"), svd.v_t.expect("v_t"));
    // det(U V^T) = -1 would give a reflection: flip the last singular direction.
    let d = (u * v_t).determinant().signum();
    let r = u * nalgebra::Matrix3::from_diagonal(&nalgebra::Vector3::new(1.0, 1.0, d)) * v_t;
    Ok(Pose::new(
        nalgebra::Rotation3::from_matrix_unchecked(r),
        t / n,
    ))
}

/// What [`mean_pose_predictions`] did.
#[derive(Clone, Debug, serde::Serialize)]
pub struct MeanPoseSummary {
    /// Poses averaged (the `fit` split).
    pub fitted_on: usize,
    /// Samples predicted.
    pub samples: usize,
    /// The mean pose as the release's row-vector `R_t`.
    pub rt: [f64; 16],
    /// Its Euler angles (yaw, pitch, roll), degrees.
    pub euler_deg: [f64; 3],
}

/// Predicts the mean pose of the `fit` split (`None`: all samples) for every sample of
/// `split`: the baseline a trained model must beat.
pub fn mean_pose_predictions(
    dataset: &Path,
    fit: Option<&str>,
    split: Option<&str>,
) -> Result<(Vec<PredictionRecord>, MeanPoseSummary)> {
    let data = crate::store::dataset::Dataset::open(dataset)?;
    let splits = crate::store::splits::SplitLookup::read(dataset)?;
    data.confirm_unchanged()?;
    let mut fitted = Vec::new();
    let mut keys = Vec::new();
    for shard in data.shards() {
        for r in data.read_samples(shard)? {
            if splits.keeps(&r, fit) {
                fitted.push(Pose::from_release_rt(&r.rt)?);
            }
            if splits.keeps(&r, split) {
                keys.push(r.key);
            }
        }
    }
    if fitted.is_empty() {
        let fit = fit.unwrap_or("all");
        return Err(Error::invalid(
            dataset.display().to_string(),
            format!(
                "no samples in the {fit:?} split to fit the mean pose on (a BIWI conversion \
                 holds test samples only; run `arkit-tool split` on a dataset with several \
                 subjects, or fit the baseline on another dataset)"
            ),
        ));
    }
    let mean = mean_pose(&fitted)?;
    let rt = mean.to_release_rt();
    let e = mean.euler();
    let rows = keys
        .into_iter()
        .map(|key| PredictionRecord {
            key,
            rt: Some(rt),
            verts: None,
            mask_rle: None,
        })
        .collect::<Vec<_>>();
    Ok((
        rows.clone(),
        MeanPoseSummary {
            fitted_on: fitted.len(),
            samples: rows.len(),
            rt,
            euler_deg: [e.yaw_deg, e.pitch_deg, e.roll_deg],
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crop_pixels_map_to_their_centres_or_corners() {
        let mut crop = CropTransform {
            x0: 100.0,
            y0: 50.0,
            side: 96.0,
            side_y: 96.0,
            size: 192,
            rules: crate::crop::RuleSet::Exact,
        };
        // Pixel (3, 2) of the crop: centre at (3.5, 2.5) crop px = half-size image px.
        let p = crop_pixel_to_image(&crop, 2 * 192 + 3);
        assert_eq!((p.x, p.y), (101.75, 51.25));
        crop.rules = crate::crop::RuleSet::Official;
        let q = crop_pixel_to_image(&crop, 2 * 192 + 3);
        assert_eq!((q.x, q.y), (101.5, 51.0));
        // A taller box scales rows by its own height.
        crop.side_y = 192.0;
        let r = crop_pixel_to_image(&crop, 2 * 192 + 3);
        assert_eq!((r.x, r.y), (101.5, 52.0));
    }

    #[test]
    fn mean_pose_of_symmetric_poses_is_the_middle() {
        use arkit_core::conventions::EulerAngles;
        use nalgebra::Vector3;
        let p = |yaw: f64, pitch: f64, tz: f64| {
            Pose::from_euler(
                EulerAngles::new(yaw, pitch, 0.0),
                Vector3::new(0.01, 0.0, tz),
            )
        };
        // One pose: itself.
        let one = mean_pose(&[p(20.0, 5.0, -0.4)]).unwrap();
        assert!(one.rotation_angle_to_deg(&p(20.0, 5.0, -0.4)) < 1e-9);
        // Yaw +-30 about the same pitch: the mean has yaw 0 and that pitch, and the
        // translation is the average by hand.
        let m = mean_pose(&[p(30.0, 10.0, -0.3), p(-30.0, 10.0, -0.5)]).unwrap();
        let e = m.euler();
        assert!(e.yaw_deg.abs() < 1e-9, "{e:?}");
        assert!((e.pitch_deg - 10.0).abs() < 1e-9, "{e:?}");
        assert!((m.translation_m() - Vector3::new(0.01, 0.0, -0.4)).norm() < 1e-12);
        // A proper rotation.
        assert!((m.rotation().matrix().determinant() - 1.0).abs() < 1e-12);
        assert!(mean_pose(&[]).is_err());
    }
}
