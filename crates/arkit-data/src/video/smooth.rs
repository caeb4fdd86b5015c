//! `smooth`: the One-Euro filter (Casiez, Roussel and Vogel, CHI 2012) on a pose.
//!
//! A low-pass filter whose cutoff rises with speed: at rest it is `min_cutoff_hz` (slow,
//! so jitter is averaged away); moving, `min_cutoff_hz + beta x speed` (fast, so the
//! filtered pose keeps up). The translation is filtered as a 3-vector (speed in m/s).
//! The rotation is filtered on SO(3), never on Euler angles: each step moves the
//! filtered rotation toward the new one along the geodesic, by the filter's `alpha` of
//! the rotation vector `log(R_filtered^T R_new)` (speed in rad/s), so a turn across the
//! ±180 degree yaw seam is as smooth as any other.

use arkit_core::conventions::Pose;
use arkit_core::{Error, Result};
use nalgebra::{Rotation3, Vector3};

/// The One-Euro filter's parameters.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct OneEuroParams {
    /// The cutoff at rest, Hz (lower: smoother and laggier at rest).
    pub min_cutoff_hz: f64,
    /// How fast the cutoff rises with the rotation's speed, Hz per rad/s.
    pub beta_rotation: f64,
    /// How fast the cutoff rises with the translation's speed, Hz per m/s.
    pub beta_translation: f64,
    /// The cutoff of the speed's own low-pass, Hz (the paper uses 1 Hz).
    pub derivative_cutoff_hz: f64,
}

impl Default for OneEuroParams {
    /// The defaults measured on `synth --video`'s clip with models/tiny-synthetic
    /// (docs/video.md): the jitter at rest falls more than 5x and the lag on a
    /// 90 degree/s turn stays under 2 frames at 30 frames a second.
    fn default() -> Self {
        OneEuroParams {
            min_cutoff_hz: 0.3,
            beta_rotation: 1.0,
            beta_translation: 10.0,
            derivative_cutoff_hz: 0.5,
        }
    }
}

impl OneEuroParams {
    /// Refuses cutoffs that are not positive and betas that are negative or not finite.
    pub fn check(&self) -> Result<()> {
        let ok = self.min_cutoff_hz.is_finite()
            && self.min_cutoff_hz > 0.0
            && self.derivative_cutoff_hz.is_finite()
            && self.derivative_cutoff_hz > 0.0
            && self.beta_rotation.is_finite()
            && self.beta_rotation >= 0.0
            && self.beta_translation.is_finite()
            && self.beta_translation >= 0.0;
        if ok {
            Ok(())
        } else {
            Err(Error::invalid(
                "smoothing",
                format!(
                    "min cutoff {} Hz, derivative cutoff {} Hz, beta {} / {}: cutoffs must be > 0 and betas >= 0",
                    self.min_cutoff_hz,
                    self.derivative_cutoff_hz,
                    self.beta_rotation,
                    self.beta_translation
                ),
            ))
        }
    }
}

/// The low-pass weight of a new sample for `cutoff_hz` after `dt_s` seconds.
pub fn alpha(cutoff_hz: f64, dt_s: f64) -> f64 {
    let tau = 1.0 / (2.0 * std::f64::consts::PI * cutoff_hz);
    1.0 / (1.0 + tau / dt_s)
}

/// A One-Euro filter on a pose (see the module docs).
#[derive(Clone, Debug)]
pub struct PoseFilter {
    params: OneEuroParams,
    last: Option<FilterState>,
}

#[derive(Clone, Debug)]
struct FilterState {
    time_s: f64,
    rotation: Rotation3<f64>,
    translation: Vector3<f64>,
    /// The filtered angular velocity (rad/s) and velocity (m/s).
    angular_velocity: Vector3<f64>,
    velocity: Vector3<f64>,
}

impl PoseFilter {
    /// A filter that has seen nothing yet.
    pub fn new(params: OneEuroParams) -> Self {
        PoseFilter { params, last: None }
    }

    /// Filters the pose observed at `time_s` (seconds, increasing): the first pose is
    /// returned as it is; a time not after the last one restarts the filter there.
    pub fn filter(&mut self, time_s: f64, pose: &Pose) -> Pose {
        let (r, t) = (pose.rotation(), pose.translation_m());
        let p = self.params;
        let Some(s) = self.last.as_mut().filter(|s| time_s > s.time_s) else {
            self.last = Some(FilterState {
                time_s,
                rotation: r,
                translation: t,
                angular_velocity: Vector3::zeros(),
                velocity: Vector3::zeros(),
            });
            return *pose;
        };
        let dt = time_s - s.time_s;
        let a_d = alpha(p.derivative_cutoff_hz, dt);
        // Rotation: the step from the filtered rotation to the new one, in its frame.
        let step = (s.rotation.inverse() * r).scaled_axis();
        s.angular_velocity += a_d * (step / dt - s.angular_velocity);
        let a_r = alpha(
            p.min_cutoff_hz + p.beta_rotation * s.angular_velocity.norm(),
            dt,
        );
        s.rotation *= Rotation3::from_scaled_axis(a_r * step);
        // Translation.
        let dx = t - s.translation;
        s.velocity += a_d * (dx / dt - s.velocity);
        let a_t = alpha(p.min_cutoff_hz + p.beta_translation * s.velocity.norm(), dt);
        s.translation += a_t * dx;
        s.time_s = time_s;
        Pose::new(s.rotation, s.translation)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use arkit_core::conventions::EulerAngles;

    fn pose(yaw: f64, pitch: f64, roll: f64, z: f64) -> Pose {
        Pose::from_euler(
            EulerAngles::new(yaw, pitch, roll),
            Vector3::new(0.01, -0.02, z),
        )
    }

    #[test]
    fn alpha_matches_the_papers_formula() {
        // tau = 1 / (2 pi fc); alpha = 1 / (1 + tau / dt): fc = 1/(2 pi) Hz, dt = 1 s.
        assert!((alpha(1.0 / (2.0 * std::f64::consts::PI), 1.0) - 0.5).abs() < 1e-12);
        assert!(alpha(1.0, 1.0 / 30.0) < alpha(5.0, 1.0 / 30.0));
    }

    #[test]
    fn a_constant_pose_stays_constant() {
        let mut f = PoseFilter::new(OneEuroParams::default());
        let p = pose(20.0, -10.0, 5.0, -0.5);
        for i in 0..100 {
            let q = f.filter(i as f64 / 30.0, &p);
            assert!(q.rotation_angle_to_deg(&p) < 1e-9, "frame {i}");
            assert!((q.translation_m() - p.translation_m()).norm() < 1e-12);
        }
    }

    #[test]
    fn a_turn_across_the_yaw_seam_has_no_jump() {
        // Yaw from 170 to 208 (= -152) degrees at 60 degrees a second: the filtered
        // rotation moves by about the input's 2 degree step each frame (a little more
        // while it catches up), never by ~340 degrees.
        let mut f = PoseFilter::new(OneEuroParams::default());
        let mut prev: Option<Pose> = None;
        let mut last_in = pose(170.0, 0.0, 0.0, -0.5);
        for i in 0..20 {
            let yaw = 170.0 + 2.0 * i as f64;
            let yaw = if yaw > 180.0 { yaw - 360.0 } else { yaw };
            let input = pose(yaw, 0.0, 0.0, -0.5);
            let out = f.filter(i as f64 / 30.0, &input);
            if let Some(prev) = prev {
                let step = out.rotation_angle_to_deg(&prev);
                assert!(step <= 3.0, "frame {i}: a step of {step} degrees");
            }
            // The filtered pose trails the input, never by more than a few frames.
            assert!(out.rotation_angle_to_deg(&input) < 15.0, "frame {i}");
            prev = Some(out);
            last_in = input;
        }
        // It ends on the far side of the seam, a few degrees behind the input's -152
        // (averaged Euler angles would be near 0 there).
        let end = prev.unwrap();
        assert!(end.rotation_angle_to_deg(&last_in) < 15.0);
        let yaw = end.euler().yaw_deg;
        assert!((-170.0..=-152.0).contains(&yaw), "yaw {yaw}");
    }

    #[test]
    fn jitter_at_rest_falls_and_a_step_is_followed() {
        // Alternating +-1 degree yaw around 10 degrees: the filtered steps are much
        // smaller; then a step to 40 degrees is reached.
        let mut f = PoseFilter::new(OneEuroParams::default());
        let mut out = Vec::new();
        for i in 0..90 {
            let yaw = 10.0 + if i % 2 == 0 { 1.0 } else { -1.0 };
            out.push(f.filter(i as f64 / 30.0, &pose(yaw, 0.0, 0.0, -0.5)));
        }
        let steps: Vec<f64> = out[30..]
            .windows(2)
            .map(|w| w[1].rotation_angle_to_deg(&w[0]))
            .collect();
        let mean = steps.iter().sum::<f64>() / steps.len() as f64;
        assert!(
            mean < 2.0 / 5.0,
            "mean filtered step {mean} vs 2 degrees raw"
        );
        let target = pose(40.0, 0.0, 0.0, -0.5);
        let mut last = out[89];
        for i in 90..150 {
            last = f.filter(i as f64 / 30.0, &target);
        }
        assert!(last.rotation_angle_to_deg(&target) < 0.5);
    }

    #[test]
    fn bad_parameters_are_refused() {
        let mut p = OneEuroParams::default();
        assert!(p.check().is_ok());
        p.min_cutoff_hz = 0.0;
        assert!(p.check().is_err());
        p = OneEuroParams {
            beta_rotation: -1.0,
            ..OneEuroParams::default()
        };
        assert!(p.check().is_err());
    }
}
