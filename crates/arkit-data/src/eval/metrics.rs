//! The paper's evaluation metrics, exactly as the official evaluation computes them.
//!
//! One home for every metric of `arkit-tool eval`. Per sample ([`sample_errors`]):
//! - **Euler errors**: yaw, pitch and roll of both poses (SciPy `as_euler('yxz')` of
//!   `R_t[:3,:3]^T`, see [`arkit_core::conventions::EulerAngles`]) and their absolute differences in
//!   degrees. The official code subtracts the angles as they are, so a yaw of 179 degrees
//!   against -179 degrees counts as a 358 degree error; [`EulerDifference::Wrapped`]
//!   offers the shortest angular difference instead. The default is the official one.
//! - **Translation errors**: `|t_pred - t_gt|` per axis, `t = R_t[3, :3]`, in mm.
//! - **ADD**: the mean over the ground-truth vertices `v` of
//!   `|[v 1] R_t_pred - [v 1] R_t_gt|`, in mm.
//! - **Geodesic rotation error** (degrees) and **translation distance** (mm), used by the
//!   success rates: "5 deg 5 cm" counts rotation < 5 and translation < 50 mm. The official
//!   code prints a second rate as "5°10cm" but counts rotation < 10 degrees and
//!   translation < 5 cm: we report it under its true name, `10deg5cm`, and also the rate
//!   its label promises, `5deg10cm`.
//! - **PnP failure**: a predicted pose with `tz > 0` or `tz < -100` m (or a missing or
//!   non-finite one) is a failure, counted, and replaced by the identity `R_t` before the
//!   errors are computed, as the official evaluation does. A sample with no prediction at
//!   all counts the same way: it is never silently dropped.
//! - **3D reconstruction error**: the mean distance between predicted and ground-truth
//!   vertices in the canonical frame (mm), when the prediction carries `verts`.
//! - **Mask** accuracy, IoU and precision against the rendered target mask (same crop),
//!   when the prediction carries a mask.
//!
//! [`Summary`] averages them over samples (means; medians where a mean hides the tail).

#[cfg(test)]
use arkit_core::conventions::EulerAngles;
use arkit_core::conventions::{AngleConvention, geodesic_angle_deg};
use nalgebra::{Matrix3, Matrix4, Rotation3, Vector3};
use serde::Serialize;

/// How Euler angle differences are taken.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Default)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum EulerDifference {
    /// `|a - b|` as the official evaluation does (no wrap-around at +/-180).
    #[default]
    Official,
    /// The shortest angular difference, in [0, 180].
    Wrapped,
}

impl EulerDifference {
    /// The difference of two angles in degrees.
    pub fn of(self, a: f64, b: f64) -> f64 {
        let d = (a - b).abs();
        match self {
            EulerDifference::Official => d,
            EulerDifference::Wrapped => {
                let d = d.rem_euclid(360.0);
                d.min(360.0 - d)
            }
        }
    }
}

/// Why a prediction was replaced by the identity pose.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PoseFailure {
    /// No prediction row for this sample.
    Missing,
    /// The predictor reported a failure (a null `R_t`).
    NoPose,
    /// A non-finite number in the predicted `R_t`.
    NonFinite,
    /// `tz > 0`: the face behind the camera.
    BehindCamera,
    /// `tz < -100 m`.
    TooFar,
}

impl PoseFailure {
    /// A short name for tables.
    pub fn name(self) -> &'static str {
        match self {
            PoseFailure::Missing => "missing",
            PoseFailure::NoPose => "no_pose",
            PoseFailure::NonFinite => "non_finite",
            PoseFailure::BehindCamera => "behind_camera",
            PoseFailure::TooFar => "too_far",
        }
    }
}

/// The identity `R_t` that replaces a failed prediction.
pub const IDENTITY_RT: [f64; 16] = [
    1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
];

/// Checks a predicted `R_t` as the official evaluation does; `Err` says why it is
/// replaced by the identity.
pub fn check_prediction(rt: Option<&[f64; 16]>) -> Result<[f64; 16], PoseFailure> {
    let rt = rt.ok_or(PoseFailure::NoPose)?;
    if rt.iter().any(|v| !v.is_finite()) {
        return Err(PoseFailure::NonFinite);
    }
    if rt[14] > 0.0 {
        return Err(PoseFailure::BehindCamera);
    }
    if rt[14] < -100.0 {
        return Err(PoseFailure::TooFar);
    }
    Ok(*rt)
}

/// The rotation of a row-vector `R_t` in column-vector form (`R_t[:3,:3]^T`), projected
/// onto the nearest rotation as SciPy's `from_matrix` does for a not quite orthonormal
/// input.
fn rotation_of(rt: &[f64; 16]) -> Rotation3<f64> {
    let m = Matrix3::new(
        rt[0], rt[4], rt[8], rt[1], rt[5], rt[9], rt[2], rt[6], rt[10],
    );
    Rotation3::from_matrix_eps(&m, 1e-12, 100, Rotation3::identity())
}

/// The translation `R_t[3, :3]` in metres.
fn translation_of(rt: &[f64; 16]) -> Vector3<f64> {
    Vector3::new(rt[12], rt[13], rt[14])
}

/// Errors of one sample's pose (and, where given, shape and mask).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SampleErrors {
    /// Why the prediction was replaced by the identity, if it was.
    pub failure: Option<PoseFailure>,
    /// |yaw error|, degrees.
    pub yaw_deg: f64,
    /// |pitch error|, degrees.
    pub pitch_deg: f64,
    /// |roll error|, degrees.
    pub roll_deg: f64,
    /// |tx error|, mm.
    pub tx_mm: f64,
    /// |ty error|, mm.
    pub ty_mm: f64,
    /// |tz error|, mm.
    pub tz_mm: f64,
    /// ADD, mm.
    pub add_mm: f64,
    /// Geodesic rotation error, degrees.
    pub rotation_deg: f64,
    /// Translation distance, mm.
    pub translation_mm: f64,
    /// Mean vertex distance in the canonical frame, mm (when `verts` were predicted).
    pub recon_mm: Option<f64>,
    /// Mask scores (when a mask was predicted).
    pub mask: Option<MaskScores>,
}

/// Pixel scores of a predicted mask against the target mask.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct MaskScores {
    /// Share of pixels labelled correctly.
    pub accuracy: f64,
    /// |P and G| / |P or G| (1 when both are empty).
    pub iou: f64,
    /// |P and G| / |P| (1 when P is empty).
    pub precision: f64,
}

/// Scores a predicted mask against the target; both are row-major over the same crop.
pub fn mask_scores(pred: &[bool], target: &[bool]) -> MaskScores {
    assert_eq!(pred.len(), target.len(), "masks of different sizes");
    let (mut both, mut either, mut p, mut right) = (0usize, 0usize, 0usize, 0usize);
    for (&a, &b) in pred.iter().zip(target) {
        both += (a && b) as usize;
        either += (a || b) as usize;
        p += a as usize;
        right += (a == b) as usize;
    }
    let ratio = |n: usize, d: usize| if d == 0 { 1.0 } else { n as f64 / d as f64 };
    MaskScores {
        accuracy: ratio(right, pred.len()),
        iou: ratio(both, either),
        precision: ratio(both, p),
    }
}

/// The errors of one sample. `prediction` is the predicted `R_t` (`None` when there is
/// none); `gt_verts` and `pred_verts` are 1220 x 3 row-major, metres.
pub fn sample_errors(
    gt_rt: &[f64; 16],
    prediction: Result<[f64; 16], PoseFailure>,
    gt_verts: &[f32],
    pred_verts: Option<&[f32]>,
    euler: EulerDifference,
) -> SampleErrors {
    sample_errors_in(
        gt_rt,
        prediction,
        gt_verts,
        pred_verts,
        euler,
        AngleConvention::Official,
    )
}

/// [`sample_errors`] with yaw, pitch and roll read in another tool's convention
/// (`eval --angles`; [`AngleConvention::euler_of`]); every other error is the same.
pub fn sample_errors_in(
    gt_rt: &[f64; 16],
    prediction: Result<[f64; 16], PoseFailure>,
    gt_verts: &[f32],
    pred_verts: Option<&[f32]>,
    euler: EulerDifference,
    angles: AngleConvention,
) -> SampleErrors {
    let (failure, rt) = match prediction {
        Ok(rt) => (None, rt),
        Err(f) => (Some(f), IDENTITY_RT),
    };
    let (rg, rp) = (rotation_of(gt_rt), rotation_of(&rt));
    let (eg, ep) = (angles.euler_of(&rg), angles.euler_of(&rp));
    let (tg, tp) = (translation_of(gt_rt), translation_of(&rt));
    let mg = Matrix4::from_row_slice(gt_rt);
    let mp = Matrix4::from_row_slice(&rt);
    let mut add = 0.0;
    let n = gt_verts.len() / 3;
    for v in gt_verts.chunks_exact(3) {
        let row = nalgebra::RowVector4::new(v[0] as f64, v[1] as f64, v[2] as f64, 1.0);
        let d = row * mp - row * mg;
        add += (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    }
    let recon_mm = pred_verts.map(|p| {
        let s: f64 = p
            .chunks_exact(3)
            .zip(gt_verts.chunks_exact(3))
            .map(|(a, b)| {
                let d = Vector3::new(
                    (a[0] - b[0]) as f64,
                    (a[1] - b[1]) as f64,
                    (a[2] - b[2]) as f64,
                );
                d.norm()
            })
            .sum();
        1000.0 * s / n.max(1) as f64
    });
    SampleErrors {
        failure,
        yaw_deg: euler.of(eg.yaw_deg, ep.yaw_deg),
        pitch_deg: euler.of(eg.pitch_deg, ep.pitch_deg),
        roll_deg: euler.of(eg.roll_deg, ep.roll_deg),
        tx_mm: 1000.0 * (tg.x - tp.x).abs(),
        ty_mm: 1000.0 * (tg.y - tp.y).abs(),
        tz_mm: 1000.0 * (tg.z - tp.z).abs(),
        add_mm: 1000.0 * add / n.max(1) as f64,
        rotation_deg: geodesic_angle_deg(&rg, &rp),
        translation_mm: 1000.0 * (tg - tp).norm(),
        recon_mm,
        mask: None,
    }
}

/// The evaluation of a set of samples: the paper's table and more.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Summary {
    /// Samples evaluated (every sample of the chosen split, predicted or not).
    pub samples: usize,
    /// Predictions replaced by the identity (missing ones included).
    pub pose_failures: usize,
    /// Of those, samples with no prediction row.
    pub missing: usize,
    /// Euler difference rule used.
    pub euler_difference: EulerDifference,
    /// Mean |yaw error|, degrees.
    pub yaw_mae_deg: f64,
    /// Mean |pitch error|, degrees.
    pub pitch_mae_deg: f64,
    /// Mean |roll error|, degrees.
    pub roll_mae_deg: f64,
    /// Mean of the three, degrees (MAE_r).
    pub mae_r_deg: f64,
    /// Mean |tx error|, mm.
    pub tx_mae_mm: f64,
    /// Mean |ty error|, mm.
    pub ty_mae_mm: f64,
    /// Mean |tz error|, mm.
    pub tz_mae_mm: f64,
    /// Mean of the three, mm (MAE_t).
    pub mae_t_mm: f64,
    /// Mean ADD, mm.
    pub add_mm: f64,
    /// Mean geodesic rotation error, degrees.
    pub rotation_mean_deg: f64,
    /// Median geodesic rotation error, degrees.
    pub rotation_median_deg: f64,
    /// Median translation distance, mm.
    pub translation_median_mm: f64,
    /// Share with rotation < 5 deg and translation < 5 cm, percent.
    pub success_5deg5cm_pct: f64,
    /// Share with rotation < 5 deg and translation < 10 cm, percent.
    pub success_5deg10cm_pct: f64,
    /// Share with rotation < 10 deg and translation < 5 cm (the official "5°10cm"), percent.
    pub success_10deg5cm_pct: f64,
    /// Mean 3D reconstruction error, mm (samples with predicted verts).
    pub recon_mean_mm: Option<f64>,
    /// Median 3D reconstruction error, mm.
    pub recon_median_mm: Option<f64>,
    /// Mean mask scores (samples with a predicted mask).
    pub mask: Option<MaskScores>,
}

fn mean(v: impl IntoIterator<Item = f64>) -> f64 {
    let (mut s, mut n) = (0.0, 0usize);
    for x in v {
        s += x;
        n += 1;
    }
    if n == 0 { f64::NAN } else { s / n as f64 }
}

/// The median of some values (NaN when there are none).
pub fn median(v: impl IntoIterator<Item = f64>) -> f64 {
    let mut v: Vec<f64> = v.into_iter().collect();
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let m = v.len() / 2;
    if v.len() % 2 == 1 {
        v[m]
    } else {
        0.5 * (v[m - 1] + v[m])
    }
}

/// Summarises per-sample errors.
pub fn summarize(errors: &[SampleErrors], euler: EulerDifference) -> Summary {
    let m = |f: &dyn Fn(&SampleErrors) -> f64| mean(errors.iter().map(f));
    let (yaw, pitch, roll) = (m(&|e| e.yaw_deg), m(&|e| e.pitch_deg), m(&|e| e.roll_deg));
    let (tx, ty, tz) = (m(&|e| e.tx_mm), m(&|e| e.ty_mm), m(&|e| e.tz_mm));
    let rate = |r: f64, t_mm: f64| {
        let n = errors
            .iter()
            .filter(|e| e.rotation_deg < r && e.translation_mm < t_mm)
            .count();
        if errors.is_empty() {
            f64::NAN
        } else {
            100.0 * n as f64 / errors.len() as f64
        }
    };
    let recon: Vec<f64> = errors.iter().filter_map(|e| e.recon_mm).collect();
    let masks: Vec<MaskScores> = errors.iter().filter_map(|e| e.mask).collect();
    Summary {
        samples: errors.len(),
        pose_failures: errors.iter().filter(|e| e.failure.is_some()).count(),
        missing: errors
            .iter()
            .filter(|e| e.failure == Some(PoseFailure::Missing))
            .count(),
        euler_difference: euler,
        yaw_mae_deg: yaw,
        pitch_mae_deg: pitch,
        roll_mae_deg: roll,
        mae_r_deg: (yaw + pitch + roll) / 3.0,
        tx_mae_mm: tx,
        ty_mae_mm: ty,
        tz_mae_mm: tz,
        mae_t_mm: (tx + ty + tz) / 3.0,
        add_mm: m(&|e| e.add_mm),
        rotation_mean_deg: m(&|e| e.rotation_deg),
        rotation_median_deg: median(errors.iter().map(|e| e.rotation_deg)),
        translation_median_mm: median(errors.iter().map(|e| e.translation_mm)),
        success_5deg5cm_pct: rate(5.0, 50.0),
        success_5deg10cm_pct: rate(5.0, 100.0),
        success_10deg5cm_pct: rate(10.0, 50.0),
        recon_mean_mm: (!recon.is_empty()).then(|| mean(recon.iter().copied())),
        recon_median_mm: (!recon.is_empty()).then(|| median(recon.iter().copied())),
        mask: (!masks.is_empty()).then(|| MaskScores {
            accuracy: mean(masks.iter().map(|s| s.accuracy)),
            iou: mean(masks.iter().map(|s| s.iou)),
            precision: mean(masks.iter().map(|s| s.precision)),
        }),
    }
}

impl Summary {
    /// The table's columns: header and formatted value (the paper's order).
    pub fn columns(&self) -> [(&'static str, String); 12] {
        [
            ("yaw", format!("{:.2}", self.yaw_mae_deg)),
            ("pitch", format!("{:.2}", self.pitch_mae_deg)),
            ("roll", format!("{:.2}", self.roll_mae_deg)),
            ("MAE_r", format!("{:.2}", self.mae_r_deg)),
            ("tx", format!("{:.2}", self.tx_mae_mm)),
            ("ty", format!("{:.2}", self.ty_mae_mm)),
            ("tz", format!("{:.2}", self.tz_mae_mm)),
            ("MAE_t", format!("{:.2}", self.mae_t_mm)),
            ("ADD", format!("{:.2}", self.add_mm)),
            ("5deg5cm", format!("{:.2}", self.success_5deg5cm_pct)),
            ("10deg5cm", format!("{:.2}", self.success_10deg5cm_pct)),
            (
                "3DRecon",
                self.recon_mean_mm
                    .map_or("-".to_string(), |v| format!("{v:.2}")),
            ),
        ]
    }

    /// The paper's table as aligned text: one header line, one value line, then the
    /// extra figures.
    pub fn table(&self) -> String {
        let cols = self.columns();
        let widths: Vec<usize> = cols.iter().map(|(h, v)| h.len().max(v.len())).collect();
        let line = |f: &dyn Fn(&(&str, String)) -> String| {
            cols.iter()
                .zip(&widths)
                .map(|(c, w)| format!("{:>w$}", f(c), w = *w))
                .collect::<Vec<_>>()
                .join("  ")
        };
        let mut out = String::new();
        out += &format!(
            "{} samples, {} PnP failures ({} missing); angles in degrees ({:?} differences), distances in mm, rates in %\n",
            self.samples, self.pose_failures, self.missing, self.euler_difference
        );
        out += &line(&|c| c.0.to_string());
        out.push('\n');
        out += &line(&|c| c.1.clone());
        out.push('\n');
        out += &format!(
            "geodesic rotation error: mean {:.3} deg, median {:.3} deg; translation error median {:.2} mm; 5deg10cm {:.2}%\n",
            self.rotation_mean_deg,
            self.rotation_median_deg,
            self.translation_median_mm,
            self.success_5deg10cm_pct
        );
        if let Some(m) = self.recon_median_mm {
            out += &format!("3D reconstruction error median {m:.2} mm\n");
        }
        if let Some(m) = &self.mask {
            out += &format!(
                "mask: accuracy {:.4}, IoU {:.4}, precision {:.4}\n",
                m.accuracy, m.iou, m.precision
            );
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use arkit_core::conventions::Pose;

    fn face() -> Vec<f32> {
        // A few points spread like a face (metres).
        vec![
            0.0, 0.0, 0.05, 0.07, 0.0, 0.0, -0.07, 0.0, 0.0, 0.0, 0.09, 0.0, 0.0, -0.09, 0.01,
        ]
    }

    fn rt(yaw: f64, pitch: f64, roll: f64, t: [f64; 3]) -> [f64; 16] {
        Pose::from_euler(EulerAngles::new(yaw, pitch, roll), Vector3::from(t)).to_release_rt()
    }

    #[test]
    fn ground_truth_against_itself_is_zero() {
        let g = rt(30.0, -10.0, 5.0, [0.02, -0.01, -0.5]);
        let e = sample_errors(&g, Ok(g), &face(), Some(&face()), EulerDifference::Official);
        for v in [
            e.yaw_deg,
            e.pitch_deg,
            e.roll_deg,
            e.tx_mm,
            e.ty_mm,
            e.tz_mm,
            e.add_mm,
            e.rotation_deg,
            e.translation_mm,
            e.recon_mm.unwrap(),
        ] {
            assert!(v.abs() < 1e-9, "{e:?}");
        }
    }

    #[test]
    fn three_degrees_of_yaw_by_hand() {
        // Pure yaw about the face origin: Euler 'yxz' with pitch = roll = 0 is a single
        // rotation about y, so only yaw changes, by exactly 3 degrees.
        let t = [0.0, 0.0, -0.6];
        let g = rt(10.0, 0.0, 0.0, t);
        let p = rt(13.0, 0.0, 0.0, t);
        let verts = face();
        let e = sample_errors(&g, Ok(p), &verts, None, EulerDifference::Official);
        assert!((e.yaw_deg - 3.0).abs() < 1e-9);
        assert!(e.pitch_deg < 1e-9 && e.roll_deg < 1e-9);
        assert!(e.tx_mm < 1e-9 && e.tz_mm < 1e-9);
        assert!((e.rotation_deg - 3.0).abs() < 1e-9);
        // A point at distance r from the y axis moves by the chord 2 r sin(1.5 deg).
        let chord = |x: f64, z: f64| 2.0 * (x * x + z * z).sqrt() * (1.5f64.to_radians()).sin();
        let expected = 1000.0
            * (chord(0.0, 0.05) + chord(0.07, 0.0) + chord(-0.07, 0.0) + 0.0 + chord(0.0, 0.01))
            / 5.0;
        // The vertices are float32: agreement to a nanometre.
        assert!(
            (e.add_mm - expected).abs() < 1e-6,
            "{} vs {expected}",
            e.add_mm
        );
    }

    #[test]
    fn failures_become_the_identity() {
        let g = rt(0.0, 0.0, 0.0, [0.0, 0.0, -0.5]);
        let mut behind = g;
        behind[14] = 0.5;
        assert_eq!(
            check_prediction(Some(&behind)),
            Err(PoseFailure::BehindCamera)
        );
        let mut far = g;
        far[14] = -101.0;
        assert_eq!(check_prediction(Some(&far)), Err(PoseFailure::TooFar));
        let mut nan = g;
        nan[3] = f64::NAN;
        assert_eq!(check_prediction(Some(&nan)), Err(PoseFailure::NonFinite));
        assert_eq!(check_prediction(None), Err(PoseFailure::NoPose));
        // The identity sits at the camera centre: tz error = 500 mm.
        let e = sample_errors(
            &g,
            Err(PoseFailure::Missing),
            &face(),
            None,
            EulerDifference::Official,
        );
        assert_eq!(e.failure, Some(PoseFailure::Missing));
        assert!((e.tz_mm - 500.0).abs() < 1e-9);
        let s = summarize(&[e], EulerDifference::Official);
        assert_eq!((s.pose_failures, s.missing), (1, 1));
        assert_eq!(s.success_5deg5cm_pct, 0.0);
    }

    #[test]
    fn wrapped_differences_take_the_short_way() {
        assert_eq!(EulerDifference::Official.of(179.0, -179.0), 358.0);
        assert!((EulerDifference::Wrapped.of(179.0, -179.0) - 2.0).abs() < 1e-12);
        assert!((EulerDifference::Wrapped.of(-10.0, 20.0) - 30.0).abs() < 1e-12);
    }

    #[test]
    fn success_rates_use_their_thresholds() {
        let g = rt(0.0, 0.0, 0.0, [0.0, 0.0, -0.5]);
        let verts = face();
        let mk = |yaw: f64, dz: f64| {
            sample_errors(
                &g,
                Ok(rt(yaw, 0.0, 0.0, [0.0, 0.0, -0.5 + dz])),
                &verts,
                None,
                EulerDifference::Official,
            )
        };
        // (4 deg, 4 cm): all three; (7 deg, 4 cm): 10deg5cm only; (4 deg, 8 cm): 5deg10cm only.
        let s = summarize(
            &[mk(4.0, 0.04), mk(7.0, 0.04), mk(4.0, 0.08), mk(20.0, 0.0)],
            EulerDifference::Official,
        );
        assert_eq!(s.success_5deg5cm_pct, 25.0);
        assert_eq!(s.success_10deg5cm_pct, 50.0);
        assert_eq!(s.success_5deg10cm_pct, 50.0);
        assert!((s.yaw_mae_deg - 35.0 / 4.0).abs() < 1e-9);
    }

    #[test]
    fn mask_scores_by_hand() {
        let p = [true, true, false, false];
        let g = [true, false, true, false];
        let s = mask_scores(&p, &g);
        assert_eq!((s.accuracy, s.iou, s.precision), (0.5, 1.0 / 3.0, 0.5));
    }

    #[test]
    fn median_of_even_and_odd() {
        assert_eq!(median([3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median([4.0, 1.0, 2.0, 3.0]), 2.5);
        assert!(median([]).is_nan());
    }
}
