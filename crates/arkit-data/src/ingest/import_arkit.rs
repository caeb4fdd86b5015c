//! `import-arkit`: a user's own ARKit face captures into the release's layout.
//!
//! A capture is a folder of frames; each frame is a JSON file (ARKit's values as the
//! app read them) and an image (`ARFrame.capturedImage` saved as PNG or JPEG). The
//! JSON holds, with matrices as ARKit gives them (`simd` types: column-major, column
//! vectors; each inner array is one column, `columns.0` first):
//!
//! | key | ARKit source | shape |
//! |---|---|---|
//! | `face_anchor_transform` | `ARFaceAnchor.transform` (face to world) | 4 columns of 4 |
//! | `camera_transform` | `ARCamera.transform` (camera to world) | 4 columns of 4 |
//! | `camera_intrinsics` | `ARCamera.intrinsics` (pixels of the captured image) | 3 columns of 3 |
//! | `image_resolution` | `ARCamera.imageResolution` | `[width, height]` |
//! | `interface_orientation` | the app's `UIInterfaceOrientation` | `"portrait"`, `"portraitUpsideDown"`, `"landscapeLeft"`, `"landscapeRight"` |
//! | `vertices` | `ARFaceAnchor.geometry.vertices` (face frame, metres) | 1,220 of 3 |
//! | `image` (optional) | the image file's name, next to the JSON | string |
//!
//! **Pose.** With `A` the anchor's transform and `C` the camera's, both in column
//! form, the face in the camera frame is `C^-1 A` (column form). ARKit's camera frame
//! is OpenGL's (x right along the captured image's width, y up, looking down -z), the
//! release's too, so no axis flip is needed; the release stores the transpose (row
//! form): `R_t = (C'^-1 A)^T`, where `C' = C O` is the camera turned to the interface
//! orientation (`O` a rotation about the camera's z axis, below). In row form this is
//! `faceAnchortransform = R_t @ cameratransform` with `faceAnchortransform = A^T` and
//! `cameratransform = C'^T`, the release's own identity (and the official code's
//! `R_t = faceAnchortransform @ inv(cameratransform)`). A simd matrix's columns read as
//! rows give exactly the row form, so `A^T` is the JSON array as written.
//!
//! **Orientation.** ARKit's captured image is always in the sensor's orientation
//! (landscape, as the interface orientation `landscapeRight` shows it). For another
//! interface orientation the written image is the captured one turned as the user saw
//! it: `portrait` 90 degrees clockwise, `landscapeLeft` 180, `portraitUpsideDown` 90
//! counter-clockwise; the camera frame turns with it, `O = Rz(90)`, `Rz(180)`,
//! `Rz(-90)`. The geometry is right whichever way an app reports its orientation (image
//! and camera frame turn together); a wrong orientation only makes the face upright
//! at another roll.
//!
//! **Camera.** The release's commands and its official loader project with one camera,
//! the release's (`projection_matrix.txt`: focal length 1.57443701 in normalised units,
//! principal point at the image centre, square pixels), so a capture's image is
//! resampled into it: an `S x S` image whose pixel `(i, j)` shows the scene along the
//! same ray as the captured image does at `K` applied to that ray (bilinear, the
//! capture's intrinsics read in OpenCV's pixel convention, centres at integers). A
//! rotation-free change of intrinsics moves no 3D point, so `R_t` is unchanged by it.
//! Parts of the square the capture did not see are black (as the official BIWI
//! preprocessing pads). `S` defaults to the side that keeps the capture's focal length
//! in pixels, `round(2 fx / 1.57443701)`.
//!
//! **Checks**, each reported per frame with the file and the reason, the frame skipped,
//! nothing guessed: the JSON's size (limit [`MAX_CAPTURE_JSON_BYTES`]), keys, shapes and
//! finite values; 1,220 vertices; both transforms rigid (last row `(0, 0, 0, 1)`, an
//! orthonormal right-handed rotation); intrinsics with positive focal lengths and last
//! row `(0, 0, 1)`, and a principal point in the middle half of the stated resolution
//! (intrinsics of another resolution are refused); the image present, within
//! [`MAX_IMAGE_FILE_BYTES`](arkit_core::limits::MAX_IMAGE_FILE_BYTES), of the stated
//! resolution (read from its header, before decoding), within the decoded-size limits
//! of [`crate::picture::image_decode`], and decoding; the face in front of the camera; every vertex inside the
//! written image (so `convert`'s checks pass).

use crate::ingest::release_camera::resample_to_release;
use crate::ingest::systematic::Check;
use arkit_core::NpzCompression;
use arkit_core::atomic_file;
use arkit_core::conventions::ORTHONORMAL_TOLERANCE;
use arkit_core::conventions::{Camera, Pose};
use arkit_core::limits::{MAX_CAPTURE_JSON_BYTES, MAX_IMAGE_SIDE};
use arkit_core::release::{
    self, ARKIT_VERTEX_COUNT, InfoAnnotation, ReleaseLayout, SampleKey, Split,
};
use arkit_core::{Error, Result};
use image::RgbImage;
use nalgebra::{Matrix3, Matrix4, Point3};
use rayon::prelude::*;
use serde::Serialize;
use serde_json::Value;
use std::path::{Path, PathBuf};

/// The app's interface orientation when the frame was captured.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "camelCase")]
pub enum InterfaceOrientation {
    /// The sensor's own orientation: the image as captured.
    LandscapeRight,
    /// The captured image turned 90 degrees clockwise.
    Portrait,
    /// Turned 180 degrees.
    LandscapeLeft,
    /// Turned 90 degrees counter-clockwise.
    PortraitUpsideDown,
}

impl InterfaceOrientation {
    /// Parses ARKit's name (`UIInterfaceOrientation` case names).
    pub fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "landscapeRight" => InterfaceOrientation::LandscapeRight,
            "portrait" => InterfaceOrientation::Portrait,
            "landscapeLeft" => InterfaceOrientation::LandscapeLeft,
            "portraitUpsideDown" => InterfaceOrientation::PortraitUpsideDown,
            _ => return None,
        })
    }

    /// The name ARKit's enum uses.
    pub fn name(self) -> &'static str {
        match self {
            InterfaceOrientation::LandscapeRight => "landscapeRight",
            InterfaceOrientation::Portrait => "portrait",
            InterfaceOrientation::LandscapeLeft => "landscapeLeft",
            InterfaceOrientation::PortraitUpsideDown => "portraitUpsideDown",
        }
    }

    /// `O`: the written image's camera axes in the sensor camera's frame (a rotation
    /// about z by 0, 90, 180 or -90 degrees); `d_sensor = O d_written`.
    pub fn rotation(self) -> Matrix3<f64> {
        // Exact integers, not trigonometry: 90-degree turns stay exact.
        let (c, s) = match self {
            InterfaceOrientation::LandscapeRight => (1.0, 0.0),
            InterfaceOrientation::Portrait => (0.0, 1.0),
            InterfaceOrientation::LandscapeLeft => (-1.0, 0.0),
            InterfaceOrientation::PortraitUpsideDown => (0.0, -1.0),
        };
        Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
    }
}

/// One frame's JSON, parsed and checked. Matrices are in column form (`p' = M p`).
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct CaptureFrame {
    /// `ARFaceAnchor.transform`: face frame to world.
    pub face_anchor_transform: Matrix4<f64>,
    /// `ARCamera.transform`: sensor camera frame to world.
    pub camera_transform: Matrix4<f64>,
    /// `ARCamera.intrinsics` `K`, OpenCV pixel convention, of the captured image.
    pub intrinsics: Matrix3<f64>,
    /// `ARCamera.imageResolution` (width, height) of the captured image.
    pub image_resolution: (u32, u32),
    /// The interface orientation.
    pub orientation: InterfaceOrientation,
    /// The anchor's vertices in the face frame, metres.
    pub vertices: Vec<Point3<f64>>,
    /// The image file named by the JSON's `image` key, if any.
    pub image: Option<String>,
}

fn number(v: &Value, what: &str) -> std::result::Result<f64, String> {
    let x = v
        .as_f64()
        .ok_or_else(|| format!("{what} is not a number (found {v})"))?;
    if !x.is_finite() {
        return Err(format!("{what} is not finite"));
    }
    Ok(x)
}

fn array<'a>(v: &'a Value, len: usize, what: &str) -> std::result::Result<&'a [Value], String> {
    let a = v
        .as_array()
        .ok_or_else(|| format!("{what} is not an array"))?;
    if a.len() != len {
        return Err(format!("{what} has {} entries, expected {len}", a.len()));
    }
    Ok(a)
}

/// A square matrix given as `n` columns of `n` numbers (simd's column-major layout).
fn columns<const N: usize>(v: &Value, key: &str) -> std::result::Result<[[f64; N]; N], String> {
    let cols = array(v, N, &format!("'{key}' ({N} columns of {N})"))?;
    let mut out = [[0.0; N]; N];
    for (c, col) in cols.iter().enumerate() {
        let entries = array(col, N, &format!("'{key}' column {c}"))?;
        for (r, e) in entries.iter().enumerate() {
            out[c][r] = number(e, &format!("'{key}' column {c} row {r}"))?;
        }
    }
    Ok(out)
}

fn matrix4_from_columns(c: [[f64; 4]; 4]) -> Matrix4<f64> {
    Matrix4::from_fn(|r, k| c[k][r])
}

/// Checks that `m` (column form) is rigid: last row `(0, 0, 0, 1)`, rotation
/// orthonormal within [`ORTHONORMAL_TOLERANCE`], determinant positive.
fn check_rigid(m: &Matrix4<f64>, key: &str) -> std::result::Result<(), String> {
    let last = [m[(3, 0)], m[(3, 1)], m[(3, 2)], m[(3, 3)]];
    if last[0].abs() + last[1].abs() + last[2].abs() + (last[3] - 1.0).abs() > 1e-6 {
        return Err(format!(
            "'{key}' is not a rigid transform: its last row is {last:?}, not (0, 0, 0, 1) (is it written row-major? ARKit's matrices are columns)"
        ));
    }
    let r = m.fixed_view::<3, 3>(0, 0).into_owned();
    let dev = (r.transpose() * r - Matrix3::identity()).abs().max();
    if dev > ORTHONORMAL_TOLERANCE {
        return Err(format!(
            "'{key}' is not a rigid transform: its rotation is not orthonormal (max |R^T R - I| = {dev:.2e}; scaled or sheared)"
        ));
    }
    if r.determinant() <= 0.0 {
        return Err(format!(
            "'{key}' is not a rigid transform: its rotation is a reflection"
        ));
    }
    Ok(())
}

impl CaptureFrame {
    /// Parses and checks a frame's JSON text; the error is the reason (the caller
    /// names the file).
    pub fn parse(text: &str) -> std::result::Result<Self, String> {
        let v: Value = serde_json::from_str(text).map_err(|e| format!("not valid JSON: {e}"))?;
        let obj = v
            .as_object()
            .ok_or("the JSON is not an object of ARKit values")?;
        let get = |key: &str| obj.get(key).ok_or_else(|| format!("missing key '{key}'"));
        let face = matrix4_from_columns(columns::<4>(
            get("face_anchor_transform")?,
            "face_anchor_transform",
        )?);
        check_rigid(&face, "face_anchor_transform")?;
        let camera =
            matrix4_from_columns(columns::<4>(get("camera_transform")?, "camera_transform")?);
        check_rigid(&camera, "camera_transform")?;
        let k = columns::<3>(get("camera_intrinsics")?, "camera_intrinsics")?;
        let intrinsics = Matrix3::from_fn(|r, c| k[c][r]);
        if intrinsics[(0, 0)] <= 0.0 || intrinsics[(1, 1)] <= 0.0 {
            return Err(format!(
                "'camera_intrinsics' focal lengths must be positive, found fx = {} and fy = {}",
                intrinsics[(0, 0)],
                intrinsics[(1, 1)]
            ));
        }
        let bottom = [intrinsics[(2, 0)], intrinsics[(2, 1)], intrinsics[(2, 2)]];
        if bottom != [0.0, 0.0, 1.0] || intrinsics[(1, 0)] != 0.0 {
            return Err(format!(
                "'camera_intrinsics' is not a pinhole K: its last row is {bottom:?} (expected (0, 0, 1)) and K[1][0] = {} (expected 0); is it written row-major?",
                intrinsics[(1, 0)]
            ));
        }
        let res = array(
            get("image_resolution")?,
            2,
            "'image_resolution' ([width, height])",
        )?;
        let side = |v: &Value, what: &str| -> std::result::Result<u32, String> {
            let x = v
                .as_u64()
                .ok_or_else(|| format!("'image_resolution' {what} is not a whole number"))?;
            if x == 0 || x > MAX_IMAGE_SIDE as u64 {
                return Err(format!(
                    "'image_resolution' {what} {x} is outside 1..={MAX_IMAGE_SIDE}"
                ));
            }
            Ok(x as u32)
        };
        let image_resolution = (side(&res[0], "width")?, side(&res[1], "height")?);
        crate::ingest::release_camera::principal_point_check(
            &intrinsics,
            image_resolution.0,
            image_resolution.1,
        )
        .map_err(|m| format!("'camera_intrinsics' and 'image_resolution' disagree: {m}"))?;
        let o = get("interface_orientation")?;
        let orientation = o
            .as_str()
            .and_then(InterfaceOrientation::parse)
            .ok_or_else(|| {
                format!(
                    "'interface_orientation' {o} is not one of \"portrait\", \"portraitUpsideDown\", \"landscapeLeft\", \"landscapeRight\""
                )
            })?;
        let verts = get("vertices")?
            .as_array()
            .ok_or("'vertices' is not an array")?;
        if verts.len() != ARKIT_VERTEX_COUNT {
            return Err(format!(
                "'vertices' has {} vertices, an ARKit face anchor has {ARKIT_VERTEX_COUNT}",
                verts.len()
            ));
        }
        let vertices = verts
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let c = array(p, 3, &format!("'vertices' entry {i}"))?;
                Ok(Point3::new(
                    number(&c[0], &format!("'vertices' entry {i} x"))?,
                    number(&c[1], &format!("'vertices' entry {i} y"))?,
                    number(&c[2], &format!("'vertices' entry {i} z"))?,
                ))
            })
            .collect::<std::result::Result<Vec<_>, String>>()?;
        let image = match obj.get("image") {
            None => None,
            Some(Value::String(s)) => {
                if s.contains(['/', '\\']) || s == "." || s == ".." || s.is_empty() {
                    return Err(format!(
                        "'image' \"{s}\" must be a file name next to the JSON"
                    ));
                }
                Some(s.clone())
            }
            Some(other) => return Err(format!("'image' {other} is not a file name")),
        };
        Ok(CaptureFrame {
            face_anchor_transform: face,
            camera_transform: camera,
            intrinsics,
            image_resolution,
            orientation,
            vertices,
            image,
        })
    }

    /// The camera of the written image in the world, column form: `C' = C O`.
    pub(crate) fn written_camera_transform(&self) -> Matrix4<f64> {
        let mut o = Matrix4::identity();
        o.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&self.orientation.rotation());
        self.camera_transform * o
    }

    /// The release's row-form `R_t` of this frame: `(C'^-1 A)^T` (module docs). The
    /// camera's inverse is the rigid inverse `[R^T, -R^T t]`.
    pub fn release_rt(&self) -> Matrix4<f64> {
        let c = self.written_camera_transform();
        let r = c.fixed_view::<3, 3>(0, 0).transpose();
        let t = -(r * c.fixed_view::<3, 1>(0, 3));
        let mut inv = Matrix4::identity();
        inv.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        inv.fixed_view_mut::<3, 1>(0, 3).copy_from(&t);
        (inv * self.face_anchor_transform).transpose()
    }

    /// The written image's side: `size` if given, else the side that keeps the
    /// capture's focal length in pixels (`round(2 max(fx, fy) / f_ndc)`).
    pub(crate) fn written_side(&self, size: Option<u32>) -> u32 {
        size.unwrap_or_else(|| {
            let f = self.intrinsics[(0, 0)].max(self.intrinsics[(1, 1)]);
            (2.0 * f / Camera::RELEASE_FOCAL_NDC).round() as u32
        })
    }
}

/// A frame found in the capture folder.
#[derive(Clone, Debug)]
pub struct FoundFrame {
    /// The JSON file, relative to the capture folder.
    pub json: PathBuf,
    /// The sample key it becomes.
    pub key: SampleKey,
}

/// A frame that was skipped, with the file at fault and why.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct FrameProblem {
    /// The file at fault, relative to the capture folder.
    pub file: String,
    /// What is wrong.
    pub reason: String,
    /// The check a convention can break that refused the frame, if one did (for the
    /// systematic rule, [`crate::ingest::SYSTEMATIC_WINDOW`]).
    #[serde(skip)]
    pub check: Option<Check>,
}

/// What to import.
#[derive(Clone, Debug)]
pub struct ImportOptions {
    /// The capture folder.
    pub input: PathBuf,
    /// The release-layout output folder.
    pub output: PathBuf,
    /// The subject id (default: the capture folder's name).
    pub subject: Option<String>,
    /// The split whose list names the frames.
    pub split: Split,
    /// The written images' side (default: keep the capture's focal length).
    pub size: Option<u32>,
    /// JPEG quality of the written images, 1..=100.
    pub jpeg_quality: u8,
    /// Replace a release layout already in the output folder.
    pub overwrite: bool,
    /// The systematic rule's window ([`crate::ingest::systematic::SYSTEMATIC_WINDOW`]; 0: never
    /// stop, `--allow-systematic-skips`).
    pub systematic_window: usize,
}

/// What an import did.
#[derive(Clone, Debug, Serialize)]
pub struct ImportSummary {
    /// The capture folder.
    pub input: PathBuf,
    /// The output folder.
    pub output: PathBuf,
    /// The subject id written.
    pub subject_id: String,
    /// The split listed.
    pub split: String,
    /// Frame JSON files found.
    pub frames_found: usize,
    /// Frames written.
    pub imported: usize,
    /// Frames skipped, with the reasons.
    pub skipped: Vec<FrameProblem>,
}

fn plain_name(s: &str) -> bool {
    !s.is_empty() && s != "." && s != ".." && !s.contains(['/', '\\'])
}

fn relative_string(p: &Path) -> String {
    p.components()
        .map(|c| c.as_os_str().to_string_lossy())
        .collect::<Vec<_>>()
        .join("/")
}

/// Finds the frames of a capture: `*.json` in the folder (facial action `capture`) or
/// in its sub-folders, one level (the sub-folder's name is the facial action). The img
/// id is the JSON file's stem. Sorted, so the output does not depend on the directory
/// order.
pub fn find_frames(input: &Path, subject: &str) -> Result<Vec<FoundFrame>> {
    if !input.is_dir() {
        return Err(Error::format(input, "capture folder does not exist"));
    }
    let list = |dir: &Path| -> Result<Vec<PathBuf>> {
        let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(|e| Error::io(dir, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .collect();
        v.sort();
        Ok(v)
    };
    let mut frames = Vec::new();
    let mut push = |path: &Path, action: &str| {
        let stem = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        frames.push(FoundFrame {
            json: path.strip_prefix(input).unwrap_or(path).to_path_buf(),
            key: SampleKey {
                subject_id: subject.to_string(),
                facial_action: action.to_string(),
                img_id: stem,
            },
        });
    };
    let is_json = |p: &Path| p.is_file() && p.extension().is_some_and(|x| x == "json");
    for entry in list(input)? {
        if is_json(&entry) {
            push(&entry, "capture");
        } else if entry.is_dir() {
            let action = entry
                .file_name()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default();
            if action.starts_with('.') {
                continue;
            }
            for f in list(&entry)? {
                if is_json(&f) {
                    push(&f, &action);
                }
            }
        }
    }
    if frames.is_empty() {
        return Err(Error::format(
            input,
            "no frame JSON files (*.json) in the capture folder or its sub-folders",
        ));
    }
    Ok(frames)
}

/// The entries of a capture folder (and of its sub-folders, one level) that cannot be
/// read, so their frames cannot be found: a broken or looping symbolic link, a folder
/// without permission. Each is reported (`import_capture` lists them as skipped), not
/// passed over in silence.
fn unreadable_entries(input: &Path) -> Vec<FrameProblem> {
    let mut out = Vec::new();
    let scan = |dir: &Path, depth: usize, out: &mut Vec<FrameProblem>| -> Vec<PathBuf> {
        let mut subs = Vec::new();
        let Ok(rd) = std::fs::read_dir(dir) else {
            return subs;
        };
        for e in rd.flatten() {
            let p = e.path();
            let hidden = p
                .file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with('.'));
            let readable = std::fs::metadata(&p).and_then(|m| {
                if m.is_dir() {
                    std::fs::read_dir(&p).map(|_| true)
                } else {
                    Ok(false)
                }
            });
            match readable {
                Ok(true) if depth == 0 && !hidden => subs.push(p),
                Ok(_) => {}
                Err(e) if !hidden => out.push(FrameProblem {
                    file: relative_string(p.strip_prefix(input).unwrap_or(&p)),
                    reason: format!(
                        "cannot be read ({e}): a broken or looping symbolic link? No frame in it is imported"
                    ),
                    check: None,
                }),
                Err(_) => {}
            }
        }
        subs
    };
    for sub in scan(input, 0, &mut out) {
        scan(&sub, 1, &mut out);
    }
    out.sort_by(|a, b| a.file.cmp(&b.file));
    out
}

/// A frame made ready to write.
#[derive(Clone, Debug)]
pub(crate) struct ImportedFrame {
    /// The written image.
    pub image: RgbImage,
    /// Its annotation.
    pub info: InfoAnnotation,
}

/// Reads, checks and converts one frame (module docs). The error is the file at
/// fault and the reason.
fn import_frame(
    input: &Path,
    frame: &FoundFrame,
    size: Option<u32>,
) -> std::result::Result<ImportedFrame, FrameProblem> {
    let fail = frame_problem;
    let tagged = |check: Check| {
        move |p: FrameProblem| FrameProblem {
            check: Some(check),
            ..p
        }
    };
    let cf = read_frame_json(input, frame)?;
    let image_rel = frame_image(input, frame, &cf)?;
    let image_path = input.join(&image_rel);
    // The size from the image's header, against the frame's resolution, before any
    // pixel is decoded (and the decode bounded: crate::picture::image_decode).
    let captured = crate::picture::image_decode::read_rgb8_checked(&image_path, |h| {
        if (h.width, h.height) != cf.image_resolution {
            return Err(Error::format(
                &image_path,
                format!(
                    "the image is {}x{} but the frame's image_resolution is {}x{}: the intrinsics are for the captured size (was the image resized or rotated?)",
                    h.width, h.height, cf.image_resolution.0, cf.image_resolution.1
                ),
            ));
        }
        Ok(())
    })
    .map_err(|e| match e {
        Error::Io { source, .. } => fail(&image_rel, format!("cannot read the image: {source}")),
        e if e.reason().contains("but the frame's image_resolution is") => {
            tagged(Check::ImageResolution)(fail(&image_rel, e.reason()))
        }
        e => fail(&image_rel, e.reason()),
    })?;
    let side = cf.written_side(size);
    if !(arkit_core::limits::MIN_IMAGE_SIDE..=arkit_core::MAX_VIEWPORT).contains(&side) {
        return Err(fail(
            &frame.json,
            format!(
                "the written image would be {side}x{side} pixels, outside {}..={} (pass --size)",
                arkit_core::limits::MIN_IMAGE_SIDE,
                arkit_core::MAX_VIEWPORT
            ),
        ));
    }
    let rt = cf.release_rt();
    let mut rt16 = [0.0; 16];
    for r in 0..4 {
        for c in 0..4 {
            rt16[r * 4 + c] = rt[(r, c)];
        }
    }
    let pose = Pose::from_release_rt(&rt16).map_err(|e| {
        fail(
            &frame.json,
            format!("the face's pose in the camera: {}", e.reason()),
        )
    })?;
    let camera = Camera::release(side, side);
    camera
        .check_projectable(&pose, &cf.vertices)
        .map_err(|e| tagged(Check::InView)(fail(&frame.json, e.reason())))?;
    for (i, q) in camera.project_all(&pose, &cf.vertices).iter().enumerate() {
        if !(0.0..=side as f64).contains(&q.u) || !(0.0..=side as f64).contains(&q.v) {
            return Err(tagged(Check::InView)(fail(
                &frame.json,
                format!(
                    "vertex {i} projects to ({:.1}, {:.1}), outside the written {side}x{side} image: the face is not wholly in view",
                    q.u, q.v
                ),
            )));
        }
    }
    let image = resample_to_release(&captured, &cf.intrinsics, &cf.orientation.rotation(), side);
    let verts: Vec<Point3<f32>> = cf.vertices.iter().map(|p| p.cast()).collect();
    let written_camera = cf.written_camera_transform().transpose();
    let mut info = InfoAnnotation::complete(verts, &pose, &camera, written_camera);
    // R_t exactly as composed (not re-orthonormalised), and the anchor as ARKit gave
    // it, so faceAnchortransform = R_t @ cameratransform holds to rounding.
    info.rt = rt16;
    let a = cf.face_anchor_transform.transpose();
    info.face_anchor_transform = Some(std::array::from_fn(|i| a[(i / 4, i % 4)]));
    Ok(ImportedFrame { image, info })
}

/// A problem with `file` (relative to the capture folder), of no systematic check.
fn frame_problem(file: &Path, reason: String) -> FrameProblem {
    FrameProblem {
        file: relative_string(file),
        reason,
        check: None,
    }
}

/// The frame's JSON, size-checked and parsed; a reason that breaks a convention (row-major
/// matrices, intrinsics of another resolution) is tagged with its check.
fn read_frame_json(
    input: &Path,
    frame: &FoundFrame,
) -> std::result::Result<CaptureFrame, FrameProblem> {
    let fail = frame_problem;
    let json_path = input.join(&frame.json);
    let len = std::fs::metadata(&json_path)
        .map_err(|e| fail(&frame.json, e.to_string()))?
        .len();
    if len > MAX_CAPTURE_JSON_BYTES {
        return Err(fail(
            &frame.json,
            format!("{len} bytes, more than the {MAX_CAPTURE_JSON_BYTES} a frame JSON may have"),
        ));
    }
    let text = std::fs::read_to_string(&json_path).map_err(|e| fail(&frame.json, e.to_string()))?;
    CaptureFrame::parse(&text).map_err(|r| {
        // The checks of the JSON that a convention breaks (row-major matrices,
        // intrinsics of another resolution), by the key the reason starts with.
        let check = if r.contains("is not a rigid transform") {
            Some(Check::Transforms)
        } else if r.starts_with("'camera_intrinsics'") {
            Some(Check::Intrinsics)
        } else {
            None
        };
        FrameProblem {
            check,
            ..fail(&frame.json, r)
        }
    })
}

/// The frame's image, relative to the capture folder: named by the JSON, or the JSON's
/// stem with a PNG or JPEG extension (exactly one of them).
fn frame_image(
    input: &Path,
    frame: &FoundFrame,
    cf: &CaptureFrame,
) -> std::result::Result<PathBuf, FrameProblem> {
    let fail = frame_problem;
    let dir = frame.json.parent().unwrap_or(Path::new(""));
    Ok(match &cf.image {
        Some(name) => dir.join(name),
        None => {
            let stem = &frame.key.img_id;
            let found: Vec<PathBuf> = ["png", "jpg", "jpeg", "PNG", "JPG", "JPEG"]
                .iter()
                .map(|x| dir.join(format!("{stem}.{x}")))
                .filter(|p| input.join(p).is_file())
                .collect();
            match found.len() {
                1 => found[0].clone(),
                0 => {
                    return Err(fail(
                        &frame.json,
                        format!(
                            "no image for this frame: expected {stem}.png or {stem}.jpg next to it, or an 'image' key"
                        ),
                    ));
                }
                _ => {
                    return Err(fail(
                        &frame.json,
                        format!(
                            "several images could be this frame's ({}); name one with the 'image' key",
                            found
                                .iter()
                                .map(|p| relative_string(p))
                                .collect::<Vec<_>>()
                                .join(", ")
                        ),
                    ));
                }
            }
        }
    })
}

const LAYOUT_DIRS: [&str; 5] = [
    "ARKitFace_image_train",
    "ARKitFace_image_test",
    "ARKitFace_info_train",
    "ARKitFace_info_test",
    "ARKitFace_list",
];

/// Imports a capture folder (module docs), calling `progress` once per frame.
pub fn import_capture(
    options: &ImportOptions,
    progress: &(dyn Fn() + Sync),
) -> Result<ImportSummary> {
    let subject = import_subject(options)?;
    let frames = find_frames(&options.input, &subject)?;
    let _lock = atomic_file::FolderLock::acquire(&options.output, "import-arkit", "import-arkit")?;
    atomic_file::remove_stale_temporaries(&options.output, true)?;
    clear_release_layout(options)?;
    let layout = ReleaseLayout::new(&options.output);
    let first_of = first_of_keys(&frames);
    // A frame that cannot be written (a full disk, say) stops the import, naming the
    // file: it is not the frame's fault, and skipping it would leave a smaller release
    // that looks complete.
    let fatal: std::sync::Mutex<Option<Error>> = std::sync::Mutex::new(None);
    let stop_if_fatal = || match fatal.lock().expect("fatal lock").take() {
        Some(e) => Err(e),
        None => Ok(()),
    };
    let import =
        |range: std::ops::Range<usize>| -> Vec<std::result::Result<SampleKey, FrameProblem>> {
            frames[range.clone()]
                .par_iter()
                .zip(&first_of[range])
                .map(|(f, first)| {
                    let r = import_one(options, &layout, f, first.as_deref(), &fatal);
                    progress();
                    r
                })
                .collect()
        };
    // The first frames (the systematic rule's window) first, then the rule, then the rest.
    let mut tally = crate::ingest::systematic::SkipTally::new(options.systematic_window);
    let first = tally.remaining().min(frames.len());
    let mut results = import(0..first);
    stop_if_fatal()?;
    for r in &results {
        tally.record(
            r.as_ref()
                .err()
                .and_then(|p| p.check.map(|c| (c, format!("{}: {}", p.file, p.reason)))),
        );
    }
    if let Some((_, message)) = tally.verdict("frames") {
        // Nothing of a stopped import stays: the layout folders are this run's (any
        // earlier ones were refused or, with --overwrite, removed above).
        for d in LAYOUT_DIRS {
            let p = options.output.join(d);
            if p.exists() {
                std::fs::remove_dir_all(&p).map_err(|e| Error::io(&p, e))?;
            }
        }
        return Err(Error::format(&options.input, message));
    }
    results.extend(import(first..frames.len()));
    stop_if_fatal()?;
    let mut keys = Vec::new();
    let mut skipped = unreadable_entries(&options.input);
    for r in results {
        match r {
            Ok(k) => keys.push(k),
            Err(p) => skipped.push(p),
        }
    }
    release::write_list(&layout.list_path(options.split), &keys)?;
    Ok(ImportSummary {
        input: options.input.clone(),
        output: options.output.clone(),
        subject_id: subject,
        split: options.split.name().to_string(),
        frames_found: frames.len(),
        imported: keys.len(),
        skipped,
    })
}

/// Checks the JPEG quality; the subject id (`--subject`, or the capture folder's name),
/// which must be a plain name.
fn import_subject(options: &ImportOptions) -> Result<String> {
    if !(1..=100).contains(&options.jpeg_quality) {
        return Err(Error::invalid("--jpeg-quality", "must be in 1..=100"));
    }
    let subject = match &options.subject {
        Some(s) => s.clone(),
        None => std::fs::canonicalize(&options.input)
            .map_err(|e| Error::io(&options.input, e))?
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
    };
    if !plain_name(&subject) {
        return Err(Error::invalid(
            "--subject",
            format!("'{subject}' is not a plain name (no slashes)"),
        ));
    }
    Ok(subject)
}

/// Refuses an output that already holds a release layout, or with `--overwrite` removes
/// its layout folders.
fn clear_release_layout(options: &ImportOptions) -> Result<()> {
    let existing: Vec<&str> = LAYOUT_DIRS
        .iter()
        .copied()
        .filter(|d| options.output.join(d).exists())
        .collect();
    if !existing.is_empty() {
        if !options.overwrite {
            return Err(Error::format(
                &options.output,
                format!(
                    "already holds a release layout ({}); pass --overwrite to replace it",
                    existing.join(", ")
                ),
            ));
        }
        for d in existing {
            let p = options.output.join(d);
            std::fs::remove_dir_all(&p).map_err(|e| Error::io(&p, e))?;
        }
    }
    Ok(())
}

/// Per frame, the JSON of the earlier frame with the same key, if any (a `capture/`
/// sub-folder beside frames in the root): the first is imported, the other reported,
/// never written over it.
fn first_of_keys(frames: &[FoundFrame]) -> Vec<Option<PathBuf>> {
    let mut seen = std::collections::HashMap::new();
    frames
        .iter()
        .map(|f| match seen.get(&f.key) {
            Some(first) => Some(PathBuf::clone(first)),
            None => {
                seen.insert(f.key.clone(), f.json.clone());
                None
            }
        })
        .collect()
}

/// Imports frame `f` (refused when `first`, an earlier frame, has its key) and writes its
/// image and info; a write error is also kept in `fatal`, which stops the import.
fn import_one(
    options: &ImportOptions,
    layout: &ReleaseLayout,
    f: &FoundFrame,
    first: Option<&Path>,
    fatal: &std::sync::Mutex<Option<Error>>,
) -> std::result::Result<SampleKey, FrameProblem> {
    if let Some(first) = first {
        return Err(FrameProblem {
            check: None,
            file: relative_string(&f.json),
            reason: format!(
                "the same sample key ({}) as {}, imported first",
                f.key,
                relative_string(first)
            ),
        });
    }
    let done = import_frame(&options.input, f, options.size)?;
    let write_fail = |e: Error| {
        let problem = FrameProblem {
            check: None,
            file: relative_string(&f.json),
            reason: format!("could not write the output: {e}"),
        };
        fatal.lock().expect("fatal lock").get_or_insert(e);
        problem
    };
    let jpeg = crate::picture::encode::jpeg_bytes(&done.image, options.jpeg_quality)
        .map_err(write_fail)?;
    atomic_file::write_bytes(&layout.image_path(options.split, &f.key), &jpeg)
        .map_err(write_fail)?;
    release::write_info(
        &layout.info_path(options.split, &f.key),
        &done.info,
        NpzCompression::Deflated,
    )
    .map_err(write_fail)?;
    Ok(f.key.clone())
}
