//! Systematic refusals: when one check skips most samples, the input is in another
//! convention, not full of bad samples.
//!
//! `convert`, `convert --format biwi` and `import-arkit` skip a bad sample with its
//! reason and go on. But a check that a *convention* can break (the release storing
//! `points2d` in another pixel convention, `R_t` transposed, an app writing its matrices
//! row-major, frames resized from the calibration's size) fails on every sample, and
//! skipping them one by one would end, hours later, in an empty dataset. So each such
//! check is named ([`Check`]), and the rule is:
//!
//! **Of the first [`SYSTEMATIC_WINDOW`] samples (1,000, in list order), if more than
//! half were skipped by the same check, the run stops** with an error that names the
//! check, how many samples it skipped, the first one and its reason, and what to do: turn
//! the check off when that is safe (`--skip-check points2d`), otherwise fix the input's
//! convention, or pass `--allow-systematic-skips` to skip them one by one as before.
//! Inputs with fewer samples than the window are never stopped (their skips are
//! reported as usual). Samples skipped for other reasons (a missing or corrupt file)
//! count towards the window but for no check.

use std::collections::BTreeMap;

/// The number of samples (the first, in list order) the rule looks at: 1,000.
pub const SYSTEMATIC_WINDOW: usize = 1000;

/// A per-sample check that a convention can break.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Check {
    /// `convert`: the annotation's `points2d` are not `verts` at `R_t` projected into
    /// the image. Can be turned off (`--skip-check points2d`): the pose and image are
    /// still checked against each other by the landmarks.
    Points2d,
    /// `convert`: `R_t` is not a rigid transform in the release's row-vector form.
    Pose,
    /// `convert`: the mesh at `R_t` does not project into the image (behind the camera,
    /// landmarks outside the image, or collapsed).
    Projection,
    /// `convert --format biwi`: a frame's size is not the one its `rgb.cal` is for.
    FrameSize,
    /// `import-arkit`: the image's size is not the frame's `image_resolution`.
    ImageResolution,
    /// `import-arkit`: a transform is not rigid (row-major matrices, scaled).
    Transforms,
    /// `import-arkit`: the intrinsics are not a pinhole `K` of the stated resolution.
    Intrinsics,
    /// `import-arkit`: the face is not wholly in the written image.
    InView,
}

impl Check {
    /// The check's name, as `--skip-check` takes it and errors print it.
    pub fn name(self) -> &'static str {
        match self {
            Check::Points2d => "points2d",
            Check::Pose => "pose",
            Check::Projection => "projection",
            Check::FrameSize => "frame-size",
            Check::ImageResolution => "image-resolution",
            Check::Transforms => "transforms",
            Check::Intrinsics => "intrinsics",
            Check::InView => "in-view",
        }
    }

    /// What to do when this check skips most samples.
    pub(crate) fn advice(self) -> &'static str {
        match self {
            Check::Points2d => {
                "if your release stores points2d in another convention, pass --skip-check points2d (the pose and image are still checked against each other by the 68 landmarks)"
            }
            Check::Pose => {
                "R_t must be the release's row-vector form ([[R^T, 0], [t, 1]]); a transposed (column-vector) R_t fails this way: convert the annotations, or check that this is the ARKitFace release"
            }
            Check::Projection => {
                "the mesh at R_t must project into the image with the release's camera: check --resources (projection_matrix.txt), that R_t is in the release's row-vector form and verts in metres"
            }
            Check::FrameSize => {
                "convert the frames at the size rgb.cal's intrinsics are for (BIWI's originals are 640x480), or give rgb.cal the intrinsics and size of the resized frames"
            }
            Check::ImageResolution => {
                "save ARFrame.capturedImage as captured (not resized or turned to the interface orientation), or write the image's own size as image_resolution"
            }
            Check::Transforms => {
                "write ARKit's simd matrices as 4 columns of 4 numbers (column-major, each inner array one column)"
            }
            Check::Intrinsics => {
                "write ARCamera.intrinsics as 3 columns of 3 numbers, for the image_resolution of the saved image"
            }
            Check::InView => {
                "check interface_orientation and the transforms' convention (the face must be in front of the camera), or pass a larger --size"
            }
        }
    }
}

/// Counts the skips of the first [`SYSTEMATIC_WINDOW`] (or `window`) samples by check,
/// in list order, and gives the verdict of the rule (module docs).
#[derive(Clone, Debug)]
pub(crate) struct SkipTally {
    window: usize,
    seen: usize,
    counts: BTreeMap<Check, (usize, String)>,
}

impl SkipTally {
    /// A tally over the first `window` samples (0: never stops).
    pub fn new(window: usize) -> Self {
        SkipTally {
            window,
            seen: 0,
            counts: BTreeMap::new(),
        }
    }

    /// How many more samples the window takes (0 once it is full).
    pub fn remaining(&self) -> usize {
        self.window - self.seen
    }

    /// Records the next sample (in list order): `None` if converted or skipped for no
    /// named check, else the check and a description (`file: reason`) of the skip. Past
    /// the window, nothing is recorded.
    pub fn record(&mut self, skip: Option<(Check, String)>) {
        if self.seen == self.window {
            return;
        }
        self.seen += 1;
        if let Some((check, example)) = skip {
            self.counts.entry(check).or_insert((0, example)).0 += 1;
        }
    }

    /// The rule's verdict once the window is full: the check that skipped more than
    /// half of it, with the message to stop with.
    pub(crate) fn verdict(&self, what: &str) -> Option<(Check, String)> {
        if self.window == 0 || self.seen < self.window {
            return None;
        }
        let (check, (n, example)) = self
            .counts
            .iter()
            .max_by_key(|(_, (n, _))| *n)
            .map(|(c, v)| (*c, v))?;
        (2 * n > self.window).then(|| {
            (
                check,
                format!(
                    "stopped: the '{}' check skipped {n} of the first {} {what}, so the input is likely in another convention rather than full of bad samples (first: {example}). What to do: {}. (A rerun with other options is another conversion: give it a new --output or pass --overwrite.) To skip them one by one instead, pass --allow-systematic-skips",
                    check.name(),
                    self.window,
                    check.advice()
                ),
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn more_than_half_of_a_full_window_for_one_check_stops() {
        let mut t = SkipTally::new(10);
        for i in 0..10 {
            assert_eq!(t.verdict("samples"), None, "window not full at {i}");
            let skip = match i % 10 {
                0..=5 => Some((Check::Points2d, format!("a/{i}.jpg: off"))),
                6 => Some((Check::Pose, "b: x".into())),
                _ => None,
            };
            t.record(skip);
        }
        assert_eq!(t.remaining(), 0);
        let (c, msg) = t.verdict("samples").unwrap();
        assert_eq!(c, Check::Points2d);
        assert!(
            msg.contains("'points2d' check skipped 6 of the first 10 samples")
                && msg.contains("first: a/0.jpg: off")
                && msg.contains("--skip-check points2d"),
            "{msg}"
        );
        // Past the window nothing changes the verdict.
        for _ in 0..100 {
            t.record(Some((Check::Pose, "b".into())));
        }
        assert_eq!(t.verdict("samples").unwrap().0, Check::Points2d);
    }

    #[test]
    fn half_or_split_between_checks_does_not_stop() {
        let mut t = SkipTally::new(10);
        for i in 0..10 {
            t.record((i < 5).then(|| (Check::Points2d, "x".into())));
        }
        assert_eq!(t.verdict("samples"), None);
        let mut t = SkipTally::new(10);
        for i in 0..10 {
            let c = if i % 2 == 0 {
                Check::Pose
            } else {
                Check::Projection
            };
            t.record((i < 8).then(|| (c, "x".into())));
        }
        assert_eq!(t.verdict("samples"), None, "4 and 4 of 10");
        // A window never filled (fewer samples than the window) never stops, nor does 0.
        let mut t = SkipTally::new(10);
        for _ in 0..9 {
            t.record(Some((Check::Pose, "x".into())));
        }
        assert_eq!(t.verdict("samples"), None);
        let mut t = SkipTally::new(0);
        t.record(Some((Check::Pose, "x".into())));
        assert_eq!(t.verdict("samples"), None);
    }
}
