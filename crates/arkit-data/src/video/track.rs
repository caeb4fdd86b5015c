//! `track`: faces matched across a video's frames into tracks with stable ids.
//!
//! Each frame either has the detector's boxes ([`Tracker::detected`]) or not
//! ([`Tracker::carried`], between detector runs with `--detect-every N`). A track's box
//! is predicted forward by its velocity (boxes per frame, smoothed); detections are
//! matched to the predictions greedily by intersection over union, best pair first, a
//! pair needing at least [`TrackerOptions::min_iou`]. A detection left over starts a new
//! track (ids count up from 0 and are never reused); a track with no detection is kept
//! for [`TrackerOptions::max_missed`] detector runs (not reported on them), then ends.
//! The same boxes in the same order give the same tracks.

/// Settings of a [`Tracker`].
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct TrackerOptions {
    /// The intersection over union a detection needs with a track's predicted box.
    pub min_iou: f64,
    /// Detector runs a track survives without its face.
    pub max_missed: u32,
}

impl Default for TrackerOptions {
    fn default() -> Self {
        TrackerOptions {
            min_iou: 0.3,
            max_missed: 2,
        }
    }
}

/// A face box of a frame with its track.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackedBox {
    /// The track's id.
    pub track: u64,
    /// `[x0, y0, x1, y1]`, pixels.
    pub bbox: [f64; 4],
    /// Whether the detector gave this box on this frame (false: carried forward).
    pub detected: bool,
    /// Which of the frame's detections it is (`None` when carried).
    pub detection: Option<usize>,
}

#[derive(Clone, Debug)]
struct Track {
    id: u64,
    bbox: [f64; 4],
    /// Box change per frame.
    velocity: [f64; 4],
    /// Frames since the box was last detected.
    since_seen: u32,
    /// Detector runs in a row without the face.
    missed: u32,
}

impl Track {
    fn predicted(&self, frames: u32) -> [f64; 4] {
        let k = frames as f64;
        std::array::from_fn(|i| self.bbox[i] + self.velocity[i] * k)
    }
}

/// Matches faces across frames (see the module docs).
#[derive(Clone, Debug, Default)]
pub struct Tracker {
    options: TrackerOptions,
    tracks: Vec<Track>,
    next_id: u64,
}

/// Intersection over union of two boxes `[x0, y0, x1, y1]` (0 for empty ones).
pub fn iou(a: &[f64; 4], b: &[f64; 4]) -> f64 {
    let w = (a[2].min(b[2]) - a[0].max(b[0])).max(0.0);
    let h = (a[3].min(b[3]) - a[1].max(b[1])).max(0.0);
    let inter = w * h;
    let area = |r: &[f64; 4]| (r[2] - r[0]).max(0.0) * (r[3] - r[1]).max(0.0);
    let union = area(a) + area(b) - inter;
    if union > 0.0 { inter / union } else { 0.0 }
}

impl Tracker {
    /// A tracker with no track yet.
    pub fn new(options: TrackerOptions) -> Self {
        Tracker {
            options,
            tracks: Vec::new(),
            next_id: 0,
        }
    }

    /// How many tracks are alive (reported or waiting for their face).
    pub fn live(&self) -> usize {
        self.tracks.len()
    }

    /// A frame on which the detector ran and found `detections`: the tracks of this
    /// frame, each matched or new, in the order of the detections.
    pub fn detected(&mut self, detections: &[[f64; 4]]) -> Vec<TrackedBox> {
        let mut pairs = Vec::new();
        for (ti, t) in self.tracks.iter().enumerate() {
            let predicted = t.predicted(t.since_seen + 1);
            for (di, d) in detections.iter().enumerate() {
                let o = iou(&predicted, d);
                if o >= self.options.min_iou {
                    pairs.push((o, ti, di));
                }
            }
        }
        // Best overlap first; ties by track then detection, so the result is stable.
        pairs.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
        let mut track_of: Vec<Option<usize>> = vec![None; detections.len()];
        let mut taken = vec![false; self.tracks.len()];
        for (_, ti, di) in pairs {
            if !taken[ti] && track_of[di].is_none() {
                taken[ti] = true;
                track_of[di] = Some(ti);
            }
        }
        for (ti, t) in self.tracks.iter_mut().enumerate() {
            if !taken[ti] {
                t.missed += 1;
                t.since_seen += 1;
            }
        }
        let mut out = Vec::with_capacity(detections.len());
        for (di, d) in detections.iter().enumerate() {
            let id = match track_of[di] {
                Some(ti) => {
                    let t = &mut self.tracks[ti];
                    let frames = (t.since_seen + 1) as f64;
                    for (i, v) in t.velocity.iter_mut().enumerate() {
                        *v = 0.5 * *v + 0.5 * (d[i] - t.bbox[i]) / frames;
                    }
                    t.bbox = *d;
                    t.since_seen = 0;
                    t.missed = 0;
                    t.id
                }
                None => {
                    let id = self.next_id;
                    self.next_id += 1;
                    self.tracks.push(Track {
                        id,
                        bbox: *d,
                        velocity: [0.0; 4],
                        since_seen: 0,
                        missed: 0,
                    });
                    id
                }
            };
            out.push(TrackedBox {
                track: id,
                bbox: *d,
                detected: true,
                detection: Some(di),
            });
        }
        let max_missed = self.options.max_missed;
        self.tracks.retain(|t| t.missed <= max_missed);
        out
    }

    /// A frame on which the detector did not run: the tracks seen at the last run,
    /// their boxes moved on by their velocity.
    pub fn carried(&mut self) -> Vec<TrackedBox> {
        let mut out = Vec::new();
        for t in &mut self.tracks {
            let seen_last_run = t.missed == 0;
            t.since_seen += 1;
            if seen_last_run {
                out.push(TrackedBox {
                    track: t.id,
                    bbox: t.predicted(t.since_seen),
                    detected: false,
                    detection: None,
                });
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square(x: f64, y: f64, side: f64) -> [f64; 4] {
        [x, y, x + side, y + side]
    }

    #[test]
    fn iou_by_hand() {
        let a = [0.0, 0.0, 10.0, 10.0];
        assert_eq!(iou(&a, &a), 1.0);
        // Half overlapping: 50 / 150.
        assert!((iou(&a, &[5.0, 0.0, 15.0, 10.0]) - 1.0 / 3.0).abs() < 1e-12);
        assert_eq!(iou(&a, &[20.0, 20.0, 30.0, 30.0]), 0.0);
    }

    #[test]
    fn a_moving_face_keeps_its_id_through_two_missed_frames() {
        let mut t = Tracker::new(TrackerOptions::default());
        let mut ids = Vec::new();
        for f in 0..30 {
            let b = square(100.0 + 4.0 * f as f64, 50.0, 80.0);
            let found = if f == 10 || f == 11 { vec![] } else { vec![b] };
            for tb in t.detected(&found) {
                ids.push(tb.track);
            }
        }
        assert_eq!(ids.len(), 28);
        assert!(ids.iter().all(|&i| i == 0), "{ids:?}");
    }

    #[test]
    fn a_track_ends_after_max_missed_and_a_new_face_gets_a_new_id() {
        let mut t = Tracker::new(TrackerOptions::default());
        let b = square(100.0, 100.0, 60.0);
        assert_eq!(t.detected(&[b])[0].track, 0);
        for _ in 0..3 {
            assert!(t.detected(&[]).is_empty());
        }
        assert_eq!(t.live(), 0);
        assert_eq!(t.detected(&[b])[0].track, 1);
    }

    #[test]
    fn two_faces_that_cross_keep_their_ids() {
        // One face moves right, the other left, on nearly the same row; they pass
        // through each other around frame 20.
        let mut t = Tracker::new(TrackerOptions::default());
        for f in 0..40 {
            let a = square(50.0 + 10.0 * f as f64, 100.0, 90.0);
            let b = square(450.0 - 10.0 * f as f64, 110.0, 80.0);
            // Listed in screen order (left first), so the list order swaps too.
            let mut found = [(0u64, a), (1u64, b)];
            found.sort_by(|x, y| x.1[0].total_cmp(&y.1[0]));
            let boxes: Vec<[f64; 4]> = found.iter().map(|x| x.1).collect();
            let got = t.detected(&boxes);
            for (k, tb) in got.iter().enumerate() {
                assert_eq!(tb.track, found[k].0, "frame {f}");
            }
        }
    }

    #[test]
    fn carried_boxes_follow_the_velocity() {
        let mut t = Tracker::new(TrackerOptions::default());
        t.detected(&[square(0.0, 0.0, 50.0)]);
        t.detected(&[square(6.0, 0.0, 50.0)]);
        // Velocity: half of 6 px a frame (smoothed from rest).
        let c = t.carried();
        assert_eq!(c.len(), 1);
        assert!(!c[0].detected);
        assert!((c[0].bbox[0] - 9.0).abs() < 1e-12, "{:?}", c[0].bbox);
        // The next run matches it to the same track.
        assert_eq!(t.detected(&[square(18.0, 0.0, 50.0)])[0].track, 0);
    }
}
