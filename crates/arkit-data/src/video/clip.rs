//! `clip`: the synthetic clips `synth --video` draws (their known poses) and the
//! figures `predict --video`'s smoothing is measured with on them.
//!
//! - [`ClipKind::Turn`]: one head at rest, a yaw turn at a constant speed (90 degrees a
//!   second by default), and rest again: the measuring clip of docs/video.md.
//! - [`ClipKind::Cross`]: two heads at different distances moving across the picture
//!   in opposite directions, passing each other half-way: the clip whose track ids
//!   must not swap.
//!
//! [`rest_jitter_deg`] is the spread of the frame-to-frame rotation change over frames
//! at rest: the change `log(R_i^T R_i+1)` as a rotation vector (degrees, signed, so
//! yaw, pitch and roll's changes in the head's frame), the standard deviation of each
//! of its three components, combined as their root mean square; [`lag_frames`] is
//! the delay (frames, fractional) that best aligns a yaw series with another over a
//! window: the shift `s` minimising the mean squared difference between `a(t)` and
//! `b(t - s)` (linear interpolation).

use arkit_core::conventions::{EulerAngles, Pose};
use nalgebra::Vector3;

/// Which clip (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ClipKind {
    /// Rest, a yaw turn, rest.
    Turn,
    /// Two heads that cross.
    Cross,
}

/// The timing of a clip.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClipPlan {
    /// Which clip.
    pub kind: ClipKind,
    /// Frames a second.
    pub fps: f64,
    /// Seconds at rest before and after the turn.
    pub rest_s: f64,
    /// The turn's speed, degrees a second.
    pub turn_deg_s: f64,
    /// The yaw at the start; the turn goes to its opposite (so it lasts
    /// `2 |start_yaw_deg| / turn_deg_s` seconds).
    pub start_yaw_deg: f64,
}

impl ClipPlan {
    /// The measuring clip: 30 fps, 1 s at yaw -30, a 90 degree/s turn to +30, 1 s.
    pub fn turn(fps: f64) -> Self {
        ClipPlan {
            kind: ClipKind::Turn,
            fps,
            rest_s: 1.0,
            turn_deg_s: 90.0,
            start_yaw_deg: -30.0,
        }
    }

    /// The crossing clip at `fps`, 3 seconds.
    pub fn cross(fps: f64) -> Self {
        ClipPlan {
            kind: ClipKind::Cross,
            fps,
            rest_s: 1.5,
            turn_deg_s: 0.0,
            start_yaw_deg: 0.0,
        }
    }

    /// The turn's first and last frames (`Turn`), the frames whose yaw changes.
    pub fn turn_frames(&self) -> (usize, usize) {
        let turn_s = 2.0 * self.start_yaw_deg.abs() / self.turn_deg_s.max(1e-9);
        let first = (self.rest_s * self.fps).round() as usize;
        (first, first + (turn_s * self.fps).round() as usize)
    }

    /// The number of frames.
    pub fn frames(&self) -> usize {
        match self.kind {
            ClipKind::Turn => self.turn_frames().1 + (self.rest_s * self.fps).round() as usize + 1,
            ClipKind::Cross => (2.0 * self.rest_s * self.fps).round() as usize,
        }
    }

    /// The faces of frame `i`: `(subject, pose)` in the release's camera frame, for a
    /// camera whose focal length is `focal_px` on a `width x height` picture (the
    /// heads are placed in pixels, then at a distance).
    pub fn faces(&self, i: usize, focal_px: f64, width: u32, height: u32) -> Vec<(usize, Pose)> {
        let (w, h) = (width as f64, height as f64);
        // A head (about 0.16 m) filling `fill` of the picture's height, centred at (u, v).
        let place = |u: f64, v: f64, fill: f64| {
            let z = focal_px * 0.16 / (fill * h);
            Vector3::new(
                (u - w / 2.0) * z / focal_px,
                -(v - h / 2.0) * z / focal_px,
                -z,
            )
        };
        match self.kind {
            ClipKind::Turn => {
                let (first, last) = self.turn_frames();
                let per_frame = -(self.turn_deg_s / self.fps * self.start_yaw_deg.signum());
                let yaw = self.start_yaw_deg + per_frame * (i.clamp(first, last) - first) as f64;
                let t = place(w / 2.0, h / 2.0, 0.45);
                vec![(0, Pose::from_euler(EulerAngles::new(yaw, 5.0, 0.0), t))]
            }
            ClipKind::Cross => {
                let s = i as f64 / (self.frames().max(2) - 1) as f64;
                // The nearer head (larger) goes right, the farther left; drawn far first.
                let far = place(w * (0.8 - 0.6 * s), h * 0.45, 0.32);
                let near = place(w * (0.2 + 0.6 * s), h * 0.55, 0.42);
                vec![
                    (1, Pose::from_euler(EulerAngles::new(20.0, 0.0, 0.0), far)),
                    (0, Pose::from_euler(EulerAngles::new(-20.0, 5.0, 0.0), near)),
                ]
            }
        }
    }
}

/// The spread of the frame-to-frame rotation change, degrees, over the consecutive
/// pairs of `poses` (see the module docs; `NaN` with fewer than three poses).
pub fn rest_jitter_deg(poses: &[Pose]) -> f64 {
    let steps: Vec<nalgebra::Vector3<f64>> = poses
        .windows(2)
        .map(|w| {
            (w[0].rotation().inverse() * w[1].rotation()).scaled_axis() * 180.0
                / std::f64::consts::PI
        })
        .collect();
    let var: f64 = (0..3)
        .map(|k| std_dev(&steps.iter().map(|v| v[k]).collect::<Vec<f64>>()).powi(2))
        .sum();
    (var / 3.0).sqrt()
}

/// The standard deviation of `x` (population), `NaN` with fewer than two values.
pub fn std_dev(x: &[f64]) -> f64 {
    if x.len() < 2 {
        return f64::NAN;
    }
    let mean = x.iter().sum::<f64>() / x.len() as f64;
    (x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / x.len() as f64).sqrt()
}

/// The delay of series `a` behind `b` in frames over `window` (indices into both): the
/// shift in `[-max_shift, max_shift]` (steps of 0.05 frame) minimising the mean squared
/// difference of `a(t)` and `b(t - s)`.
pub fn lag_frames(a: &[f64], b: &[f64], window: std::ops::Range<usize>, max_shift: f64) -> f64 {
    let at = |t: f64| {
        let t = t.clamp(0.0, (b.len() - 1) as f64);
        let i = t.floor() as usize;
        let j = (i + 1).min(b.len() - 1);
        b[i] + (b[j] - b[i]) * (t - i as f64)
    };
    let steps = (max_shift / 0.05).round() as i64;
    let mut best = (f64::INFINITY, 0.0);
    for k in -steps..=steps {
        let s = k as f64 * 0.05;
        let err: f64 = window
            .clone()
            .map(|t| (a[t] - at(t as f64 - s)).powi(2))
            .sum();
        if err < best.0 - 1e-12 {
            best = (err, s);
        }
    }
    best.1
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_turn_clip_rests_turns_at_its_speed_and_rests() {
        let plan = ClipPlan::turn(30.0);
        let (first, last) = plan.turn_frames();
        assert_eq!((first, last), (30, 50));
        assert_eq!(plan.frames(), 81);
        let yaw = |i| plan.faces(i, 500.0, 640, 480)[0].1.euler().yaw_deg;
        assert!((yaw(0) + 30.0).abs() < 1e-9 && (yaw(first) + 30.0).abs() < 1e-9);
        assert!((yaw(last) - 30.0).abs() < 1e-9 && (yaw(80) - 30.0).abs() < 1e-9);
        // 90 degrees a second at 30 fps: 3 degrees a frame.
        assert!((yaw(first + 1) - yaw(first) - 3.0).abs() < 1e-9);
    }

    #[test]
    fn lag_of_a_shifted_ramp_is_its_shift() {
        let b: Vec<f64> = (0..60)
            .map(|i| (i as f64 - 20.0).clamp(0.0, 20.0) * 3.0)
            .collect();
        let a: Vec<f64> = (0..60)
            .map(|i| (i as f64 - 21.5).clamp(0.0, 20.0) * 3.0)
            .collect();
        assert!((lag_frames(&a, &b, 15..50, 10.0) - 1.5).abs() < 1e-9);
        assert!(lag_frames(&b, &b, 15..50, 10.0).abs() < 1e-9);
    }

    #[test]
    fn jitter_by_hand() {
        // Yaw steps of 1 and 3 degrees in turn: std 1 about one axis, 0 about the
        // others: sqrt(1 / 3).
        let mut yaw = 0.0;
        let poses: Vec<Pose> = (0..11)
            .map(|i| {
                yaw += if i % 2 == 0 { 1.0 } else { 3.0 };
                Pose::from_euler(
                    EulerAngles::new(yaw, 0.0, 0.0),
                    Vector3::new(0.0, 0.0, -0.5),
                )
            })
            .collect();
        assert!((rest_jitter_deg(&poses) - (1.0f64 / 3.0).sqrt()).abs() < 1e-9);
        assert!(rest_jitter_deg(&poses[..2]).is_nan());
    }
}
