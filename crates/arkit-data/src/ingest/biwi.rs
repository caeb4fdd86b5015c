//! The BIWI Kinect Head Pose database into the release's conventions (`convert
//! --format biwi`).
//!
//! Input, as distributed (`hpdb/`):
//!
//! ```text
//! hpdb/01/frame_00003_rgb.png   640x480 RGB image
//! hpdb/01/frame_00003_pose.txt  head rotation (3 lines of 3) and head centre (1 line, mm),
//!                               in the depth camera's frame: x_depth = R p + t
//! hpdb/01/rgb.cal               RGB intrinsics K (3 lines), distortion (1 line), the
//!                               depth-to-RGB rotation (3 lines) and translation (1 line, mm)
//! hpdb/01.obj                   the sequence's neutral head mesh (mm, BIWI's axes)
//! ```
//!
//! Stage one ([`stage`]) writes each posed frame as a release sample (download layout,
//! `test` list) into a staging folder; stage two is `convert` itself, with the BIWI
//! head's topology ([`biwi_topology`]), so the samples table, its checks and every later
//! command work as for ARKitFace.
//!
//! **Pose** (the official `data/biwi_preprocess.py`'s rules, written as maps): the head
//! point `p` (mm) goes to the depth camera by the frame's `(R, t)`, to the RGB camera
//! by the calibration `(Rc, tc)`: `x_cv = Rc (R p + t) + tc` (OpenCV axes, mm). Metres
//! and OpenGL axes (`F = diag(1, -1, -1)` on the camera and on the head, as the
//! official code flips the mesh by `T = F`): `v = F p / 1000`, `R_gl = F Rc R F`,
//! `t_gl = F (Rc t + tc) / 1000`. The official code then moves the head's origin by
//! `c = (0, 0.01, -0.021)` m to where ARKit's canonical face has its origin, so that a
//! network trained on ARKitFace predicts the same point: `v' = v - c`, `t' = t_gl + R_gl
//! c`. Camera-space points are unchanged by the shift (so is ADD); the translation
//! columns are those of the shifted origin.
//!
//! **Image**: the official code pads or crops each image to the release's field of
//! view (64.84 degrees, centred on the principal point) and resizes it to 800x800; the
//! same is done here by resampling into the release camera
//! ([`crate::ingest::release_camera::resample_to_release`]), which also honours `fx != fy` and a
//! sub-pixel principal point. The lens distortion of `rgb.cal` is not modelled, so a
//! sequence whose distortion coefficients are not zero is refused.
//!
//! **Mesh**: `verts` of each sample is the sequence's own head mesh (`NN.obj`, in
//! metres as above), not ARKit's 1,220-vertex topology: the samples table's `verts`
//! column is a list of any length, and `eval`'s ADD is the mean over the subject's own
//! vertices. The 68 landmarks (for the crop box) are the BIWI-mesh vertices the official
//! code names ([`BIWI_LANDMARKS`]).

use crate::ingest::release_camera::{principal_point_check, resample_to_release};
use crate::mesh::topology::FaceTopology;
use arkit_core::NpzCompression;
use arkit_core::atomic_file;
use arkit_core::conventions::{Camera, Pose};
use arkit_core::release::{self, InfoAnnotation, ReleaseLayout, SampleKey, Split};
use arkit_core::{Error, Result};
use nalgebra::{Matrix3, Matrix4, Point3, Rotation3, Vector3};
use rayon::prelude::*;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// The 68 landmark vertices of the BIWI head mesh, in the iBUG order, as the official
/// `data/biwi_preprocess.py` lists them (facts about the BIWI mesh's numbering).
pub const BIWI_LANDMARKS: [u32; 68] = [
    938, 954, 935, 946, 6374, 6370, 6769, 6759, 6749, 2634, 2647, 2657, 2234, 2243, 3364, 3377,
    3357, 3375, 4805, 5007, 5001, 5000, 179, 3800, 864, 861, 870, 3486, 3728, 3718, 2836, 2816,
    4773, 6612, 2772, 2489, 3518, 4449, 4627, 4721, 4410, 4425, 4472, 562, 572, 478, 456, 325, 242,
    6798, 6638, 6631, 2508, 2512, 2517, 2685, 2736, 2885, 2893, 5278, 6847, 6817, 6565, 2438, 2866,
    2719, 2856, 5296,
];

/// The shift (metres, release axes) from the BIWI head's origin to ARKit's canonical
/// face origin, as the official preprocessing applies it.
pub const HEAD_ORIGIN_SHIFT_M: [f64; 3] = [0.0, 0.01, -0.021];

/// Largest file of the database read as text (`.obj`, `.cal`, `_pose.txt`): 64 MiB,
/// checked on the length before reading (a BIWI head mesh is about 1 MB).
pub(crate) const MAX_TEXT_FILE_BYTES: u64 = 64 << 20;

/// How the topology of a BIWI dataset is named in its manifest (`topology`).
pub(crate) const TOPOLOGY_PREFIX: &str = "BIWI head mesh";

/// Most vertices of a head mesh: 1,000,000 (BIWI's have 6,918).
pub(crate) const MAX_MESH_VERTICES: usize = 1_000_000;

/// The camera of a sequence, from `rgb.cal`.
#[derive(Clone, Debug, PartialEq)]
pub struct Calibration {
    /// RGB intrinsics (OpenCV pixel convention).
    pub k: Matrix3<f64>,
    /// Distortion coefficients as listed.
    pub distortion: Vec<f64>,
    /// Depth-to-RGB rotation.
    pub rotation: Matrix3<f64>,
    /// Depth-to-RGB translation, mm.
    pub translation_mm: Vector3<f64>,
    /// The image size the intrinsics are for (`width height`, the file's last line), if
    /// the file gives it (BIWI's do: `640 480`).
    pub image_size: Option<(u32, u32)>,
}

fn read_text(path: &Path) -> Result<String> {
    let len = std::fs::metadata(path)
        .map_err(|e| Error::io(path, e))?
        .len();
    if len > MAX_TEXT_FILE_BYTES {
        return Err(Error::format(
            path,
            format!("{len} bytes, more than the {MAX_TEXT_FILE_BYTES} this file may have"),
        ));
    }
    std::fs::read_to_string(path).map_err(|e| Error::io(path, e))
}

/// The non-empty lines of `text`, each as numbers; `path` names the file in errors.
fn number_lines(text: &str, path: &Path) -> Result<Vec<Vec<f64>>> {
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(n, l)| {
            l.split_whitespace()
                .map(|s| match s.parse::<f64>() {
                    Ok(v) if v.is_finite() => Ok(v),
                    _ => Err(Error::format(
                        path,
                        format!("line {}: '{s}' is not a finite number", n + 1),
                    )),
                })
                .collect()
        })
        .collect()
}

fn rows3(lines: &[Vec<f64>], path: &Path, what: &str) -> Result<Matrix3<f64>> {
    if lines.len() != 3 || lines.iter().any(|l| l.len() != 3) {
        return Err(Error::format(
            path,
            format!("the {what} must be 3 lines of 3 numbers"),
        ));
    }
    Ok(Matrix3::from_fn(|r, c| lines[r][c]))
}

fn check_rotation(r: &Matrix3<f64>, path: &Path, what: &str) -> Result<()> {
    let dev = (r.transpose() * r - Matrix3::identity()).abs().max();
    if dev > arkit_core::conventions::ORTHONORMAL_TOLERANCE || r.determinant() <= 0.0 {
        return Err(Error::format(
            path,
            format!(
                "the {what} is not a rotation (max |R^T R - I| = {dev:.2e}, determinant {:.4})",
                r.determinant()
            ),
        ));
    }
    Ok(())
}

impl Calibration {
    /// Parses `rgb.cal`: K (3 lines), distortion (1 line), rotation (3 lines),
    /// translation (1 line), then optionally the image size the intrinsics are for (1
    /// line: width and height); blank lines between them are allowed.
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let lines = number_lines(text, path)?;
        if lines.len() < 8 {
            return Err(Error::format(
                path,
                format!(
                    "expected K (3 lines), distortion (1), rotation (3) and translation (1), found {} lines of numbers",
                    lines.len()
                ),
            ));
        }
        let k = rows3(&lines[0..3], path, "intrinsics K")?;
        if k[(0, 0)] <= 0.0
            || k[(1, 1)] <= 0.0
            || k[(1, 0)] != 0.0
            || [k[(2, 0)], k[(2, 1)], k[(2, 2)]] != [0.0, 0.0, 1.0]
        {
            return Err(Error::format(
                path,
                "the intrinsics K are not a pinhole matrix (positive fx, fy; last row 0 0 1)",
            ));
        }
        let rotation = rows3(&lines[4..7], path, "depth-to-RGB rotation")?;
        check_rotation(&rotation, path, "depth-to-RGB rotation")?;
        if lines[7].len() != 3 {
            return Err(Error::format(
                path,
                "the depth-to-RGB translation must be one line of 3 numbers",
            ));
        }
        if lines.len() > 9 {
            return Err(Error::format(
                path,
                format!(
                    "{} lines of numbers, at most 9 expected (K, distortion, rotation, translation, image size)",
                    lines.len()
                ),
            ));
        }
        let image_size = match lines.get(8) {
            None => None,
            Some(l) => {
                let side = |v: f64| {
                    (v.fract() == 0.0
                        && (1.0..=arkit_core::limits::MAX_IMAGE_SIDE as f64).contains(&v))
                    .then_some(v as u32)
                };
                match l.as_slice() {
                    &[w, h] if side(w).is_some() && side(h).is_some() => Some((w as u32, h as u32)),
                    _ => {
                        return Err(Error::format(
                            path,
                            format!(
                                "the image size (last line) must be a width and a height in pixels, found {l:?}"
                            ),
                        ));
                    }
                }
            }
        };
        Ok(Calibration {
            k,
            distortion: lines[3].clone(),
            rotation,
            translation_mm: Vector3::new(lines[7][0], lines[7][1], lines[7][2]),
            image_size,
        })
    }

    /// Reads `rgb.cal`.
    pub fn read(path: &Path) -> Result<Self> {
        Self::parse(&read_text(path)?, path)
    }

    /// Checks that a frame of `width x height` pixels is one these intrinsics are for:
    /// the calibration's image size when it gives one, and in any case the principal
    /// point within the middle half of the image (a frame resized by 2 puts it on the
    /// border). A resized or cropped frame no longer matches its intrinsics, so its
    /// image would not match its pose; the reason says so.
    pub fn check_frame_size(&self, width: u32, height: u32) -> std::result::Result<(), String> {
        if let Some((w, h)) = self.image_size
            && (w, h) != (width, height)
        {
            return Err(format!(
                "the image is {width}x{height} but rgb.cal's intrinsics are for {w}x{h}: a resized or cropped frame does not match its calibration, so its image would not match its pose"
            ));
        }
        principal_point_check(&self.k, width, height).map_err(|m| format!("{m} (rgb.cal)"))
    }
}

/// A frame's head pose in the depth camera: `x_depth = rotation p + translation_mm`.
#[derive(Clone, Debug, PartialEq)]
pub struct FramePose {
    /// Head rotation.
    pub rotation: Matrix3<f64>,
    /// Head centre, mm.
    pub translation_mm: Vector3<f64>,
}

impl FramePose {
    /// Parses `frame_NNNNN_pose.txt`: 3 lines of the rotation, 1 of the centre.
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let lines = number_lines(text, path)?;
        if lines.len() != 4 || lines[3].len() != 3 {
            return Err(Error::format(
                path,
                "expected the head rotation (3 lines of 3 numbers) and centre (1 line of 3)",
            ));
        }
        let rotation = rows3(&lines[0..3], path, "head rotation")?;
        check_rotation(&rotation, path, "head rotation")?;
        Ok(FramePose {
            rotation,
            translation_mm: Vector3::new(lines[3][0], lines[3][1], lines[3][2]),
        })
    }
}

fn flip() -> Matrix3<f64> {
    Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0))
}

/// The release pose of a frame (module docs): the head, origin shifted to ARKit's, in
/// the RGB camera's OpenGL frame, metres.
pub fn release_pose(frame: &FramePose, cal: &Calibration) -> Pose {
    let f = flip();
    let r_gl = f * cal.rotation * frame.rotation * f;
    let t_gl = f * (cal.rotation * frame.translation_mm + cal.translation_mm) / 1000.0;
    let c = Vector3::from(HEAD_ORIGIN_SHIFT_M);
    Pose::new(Rotation3::from_matrix(&r_gl), t_gl + r_gl * c)
}

/// A BIWI head mesh (`NN.obj`): vertices in mm and BIWI's axes, triangles 0-based.
#[derive(Clone, Debug, PartialEq)]
pub struct HeadMesh {
    /// Vertices as in the file.
    pub vertices: Vec<Point3<f64>>,
    /// Triangles (faces with more corners are split into fans).
    pub triangles: Vec<[u32; 3]>,
}

impl HeadMesh {
    /// Reads the `v` and `f` lines of an OBJ.
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let mut vertices = Vec::new();
        let mut faces: Vec<(usize, Vec<i64>)> = Vec::new();
        for (n, line) in text.lines().enumerate() {
            let mut it = line.split_whitespace();
            match it.next() {
                Some("v") => {
                    let c: Vec<f64> = it
                        .take(3)
                        .map(|s| s.parse::<f64>().ok().filter(|v| v.is_finite()))
                        .collect::<Option<_>>()
                        .filter(|c: &Vec<f64>| c.len() == 3)
                        .ok_or_else(|| {
                            Error::format(
                                path,
                                format!("line {}: a vertex needs 3 finite numbers", n + 1),
                            )
                        })?;
                    if vertices.len() == MAX_MESH_VERTICES {
                        return Err(Error::format(
                            path,
                            format!("more than {MAX_MESH_VERTICES} vertices"),
                        ));
                    }
                    vertices.push(Point3::new(c[0], c[1], c[2]));
                }
                Some("f") => {
                    let idx: Vec<i64> = it
                        .map(|s| s.split('/').next().unwrap_or("").parse::<i64>().ok())
                        .collect::<Option<_>>()
                        .filter(|v: &Vec<i64>| v.len() >= 3)
                        .ok_or_else(|| {
                            Error::format(
                                path,
                                format!("line {}: a face needs 3 or more vertex numbers", n + 1),
                            )
                        })?;
                    faces.push((n + 1, idx));
                }
                _ => {}
            }
        }
        if vertices.is_empty() {
            return Err(Error::format(path, "no vertices ('v' lines)"));
        }
        let nv = vertices.len() as i64;
        let mut triangles = Vec::new();
        for (line, idx) in faces {
            let resolved: Vec<u32> = idx
                .iter()
                .map(|&i| {
                    let z = if i < 0 { nv + i } else { i - 1 };
                    if (0..nv).contains(&z) {
                        Ok(z as u32)
                    } else {
                        Err(Error::format(
                            path,
                            format!("line {line}: vertex {i} does not exist ({nv} vertices)"),
                        ))
                    }
                })
                .collect::<Result<_>>()?;
            for k in 1..resolved.len() - 1 {
                triangles.push([resolved[0], resolved[k], resolved[k + 1]]);
            }
        }
        Ok(HeadMesh {
            vertices,
            triangles,
        })
    }

    /// Reads an OBJ file.
    pub fn read(path: &Path) -> Result<Self> {
        Self::parse(&read_text(path)?, path)
    }

    /// The vertices in the release's head frame (module docs): `F p / 1000 - c`.
    pub(crate) fn release_vertices(&self) -> Vec<Point3<f32>> {
        let f = flip();
        let c = Vector3::from(HEAD_ORIGIN_SHIFT_M);
        self.vertices
            .iter()
            .map(|p| Point3::from(f * p.coords / 1000.0 - c).cast())
            .collect()
    }
}

/// The topology of the BIWI head (its vertex count, triangles and [`BIWI_LANDMARKS`]);
/// no UVs (BIWI samples are for evaluation, not for `render`).
pub fn biwi_topology(mesh: &HeadMesh) -> Result<FaceTopology> {
    if let Some(&i) = BIWI_LANDMARKS
        .iter()
        .find(|&&i| i as usize >= mesh.vertices.len())
    {
        return Err(Error::invalid(
            "BIWI mesh",
            format!(
                "landmark vertex {i} does not exist in a mesh of {} vertices (not a BIWI head mesh?)",
                mesh.vertices.len()
            ),
        ));
    }
    Ok(FaceTopology {
        source: format!("{TOPOLOGY_PREFIX} ({} vertices)", mesh.vertices.len()),
        vertex_count: mesh.vertices.len(),
        triangles: mesh.triangles.clone(),
        uv: Vec::new(),
        landmarks: BIWI_LANDMARKS.to_vec(),
        template: None,
        uv_extension: Vec::new(),
    })
}

/// The number of `frame_*_rgb.png` files in the sequence folders of `input` (for a
/// progress bar; 0 when the folder cannot be read).
pub fn count_frames(input: &Path) -> usize {
    let Ok(rd) = std::fs::read_dir(input) else {
        return 0;
    };
    rd.flatten()
        .filter(|e| e.path().is_dir())
        .filter_map(|e| std::fs::read_dir(e.path()).ok())
        .flat_map(|d| d.flatten())
        .filter(|f| {
            let n = f.file_name().to_string_lossy().into_owned();
            n.starts_with("frame_") && n.ends_with("_rgb.png")
        })
        .count()
}

/// A problem found while staging: the file and what is wrong.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct StageProblem {
    /// The file, relative to the input.
    pub file: String,
    /// What is wrong.
    pub reason: String,
}

/// What [`stage`] did.
#[derive(Clone, Debug, Serialize)]
pub struct StageSummary {
    /// The `hpdb` folder.
    pub input: PathBuf,
    /// The release-layout staging folder.
    pub staging: PathBuf,
    /// Sequence folders found.
    pub sequences: usize,
    /// Frames (images) found.
    pub frames_found: usize,
    /// Frames written.
    pub staged: usize,
    /// Images without a pose file: listed, not guessed.
    pub without_pose: Vec<String>,
    /// Frames, sequences or files that could not be used, with the reason.
    pub problems: Vec<StageProblem>,
    /// The head meshes' vertex count.
    pub vertex_count: usize,
}

struct Frame {
    sequence: String,
    number: String,
    image: PathBuf,
    pose: PathBuf,
}

fn rel(root: &Path, p: &Path) -> String {
    p.strip_prefix(root)
        .unwrap_or(p)
        .components()
        .map(|c| c.as_os_str().to_string_lossy())
        .collect::<Vec<_>>()
        .join("/")
}

/// Writes each posed frame of `input` (an `hpdb` folder) as a release sample into
/// `staging` (download layout, `test` list; subject id = the sequence folder, facial
/// action `biwi`, img id = the frame number), images resampled into the release camera
/// at `side x side`. Returns the summary and the BIWI topology to convert with.
pub fn stage(
    input: &Path,
    staging: &Path,
    side: u32,
    progress: &(dyn Fn() + Sync),
) -> Result<(StageSummary, FaceTopology)> {
    stage_with(
        input,
        staging,
        side,
        crate::ingest::systematic::SYSTEMATIC_WINDOW,
        progress,
    )
}

/// [`stage`] with the systematic rule's window (0: never stop; see
/// [`crate::ingest::SYSTEMATIC_WINDOW`]): when the frame-size check refuses more than half of the
/// first `window` posed frames, staging stops with the reason and what to do.
pub fn stage_with(
    input: &Path,
    staging: &Path,
    side: u32,
    window: usize,
    progress: &(dyn Fn() + Sync),
) -> Result<(StageSummary, FaceTopology)> {
    if !input.is_dir() {
        return Err(Error::format(input, "BIWI folder does not exist"));
    }
    let (seqs, mut problems) = sequence_folders(input)?;
    let mut found = read_sequences(input, &seqs, &mut problems)?;
    let topology = common_topology(input, &mut found, &mut problems)?;
    let n = topology.vertex_count;
    let Found {
        frames_found,
        without_pose,
        frames,
        sequences,
    } = found;
    let verts: std::collections::BTreeMap<&String, Vec<Point3<f32>>> = sequences
        .iter()
        .map(|(s, (_, m))| (s, m.release_vertices()))
        .collect();
    let target = StageTarget {
        input,
        layout: ReleaseLayout::new(staging),
        camera: Camera::release(side, side),
        side,
        fatal: std::sync::Mutex::new(None),
    };
    let stop_if_fatal = || match target.fatal.lock().expect("fatal lock").take() {
        Some(e) => Err(e),
        None => Ok(()),
    };
    let stage_frames =
        |frames: &[Frame]| -> Vec<std::result::Result<SampleKey, (bool, StageProblem)>> {
            frames
                .par_iter()
                .map(|f| {
                    let r = stage_frame(&target, f, &sequences[&f.sequence].0, &verts[&f.sequence]);
                    progress();
                    r
                })
                .collect()
        };
    // The first frames (the systematic rule's window) first, then the rule, then the rest.
    let mut tally = crate::ingest::systematic::SkipTally::new(window);
    let first = tally.remaining().min(frames.len());
    let mut results = stage_frames(&frames[..first]);
    stop_if_fatal()?;
    for r in &results {
        tally.record(match r {
            Err((true, p)) => Some((
                crate::ingest::systematic::Check::FrameSize,
                format!("{}: {}", p.file, p.reason),
            )),
            _ => None,
        });
    }
    if let Some((_, message)) = tally.verdict("posed frames") {
        return Err(Error::format(input, message));
    }
    results.extend(stage_frames(&frames[first..]));
    stop_if_fatal()?;
    let mut keys = Vec::new();
    for r in results {
        match r {
            Ok(k) => keys.push(k),
            Err((_, p)) => problems.push(p),
        }
    }
    release::write_list(&target.layout.list_path(Split::Test), &keys)?;
    Ok((
        StageSummary {
            input: input.to_path_buf(),
            staging: staging.to_path_buf(),
            sequences: seqs.len(),
            frames_found,
            staged: keys.len(),
            without_pose,
            problems,
            vertex_count: n,
        },
        topology,
    ))
}

/// The sequence folders of `input` (the entries named by digits that are folders), sorted,
/// and a problem for each one that cannot be read (a broken or looping symbolic link, no
/// permission); an error when there is no readable one.
fn sequence_folders(input: &Path) -> Result<(Vec<PathBuf>, Vec<StageProblem>)> {
    let mut problems = Vec::new();
    let mut seqs: Vec<PathBuf> = Vec::new();
    for e in std::fs::read_dir(input).map_err(|e| Error::io(input, e))? {
        let p = e.map_err(|e| Error::io(input, e))?.path();
        let digits = p.file_name().is_some_and(|n| {
            let n = n.to_string_lossy();
            !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit())
        });
        if !digits {
            continue;
        }
        match std::fs::metadata(&p).and_then(|m| {
            if m.is_dir() {
                std::fs::read_dir(&p).map(|_| true)
            } else {
                Ok(false)
            }
        }) {
            Ok(true) => seqs.push(p),
            Ok(false) => {}
            Err(e) => problems.push(StageProblem {
                file: rel(input, &p),
                reason: format!(
                    "this sequence folder cannot be read ({e}): a broken or looping symbolic link? Its frames are not converted"
                ),
            }),
        }
    }
    seqs.sort();
    problems.sort_by(|a, b| a.file.cmp(&b.file));
    if seqs.is_empty() {
        let unreadable: Vec<String> = problems
            .iter()
            .map(|p| format!("{}: {}", p.file, p.reason))
            .collect();
        return Err(Error::format(
            input,
            if unreadable.is_empty() {
                "no sequence folders (01/, 02/, ...): is this BIWI's hpdb folder?".to_string()
            } else {
                format!("no readable sequence folder: {}", unreadable.join("; "))
            },
        ));
    }
    Ok((seqs, problems))
}

/// The frames found in the sequence folders and the sequences that can be used.
struct Found {
    /// Frames (images) found.
    frames_found: usize,
    /// Images without a pose file.
    without_pose: Vec<String>,
    /// The posed frames of the sequences that can be used.
    frames: Vec<Frame>,
    /// Per usable sequence: its calibration and head mesh.
    sequences: std::collections::BTreeMap<String, (Calibration, HeadMesh)>,
}

/// Lists each sequence's frames and reads its calibration and mesh; a sequence that lacks
/// either is reported in `problems` (with its posed frames' count) and left out.
fn read_sequences(
    input: &Path,
    seqs: &[PathBuf],
    problems: &mut Vec<StageProblem>,
) -> Result<Found> {
    let mut found = Found {
        frames_found: 0,
        without_pose: Vec::new(),
        frames: Vec::new(),
        sequences: Default::default(),
    };
    for seq in seqs {
        let name = seq.file_name().unwrap().to_string_lossy().into_owned();
        let seq_frames = sequence_frames(input, seq, &name, &mut found)?;
        match load_sequence(input, seq, &name) {
            Ok(x) => {
                found.sequences.insert(name.clone(), x);
                found.frames.extend(seq_frames);
            }
            Err(e) => {
                let file = e
                    .path()
                    .map(|p| rel(input, p))
                    .unwrap_or_else(|| rel(input, seq));
                problems.push(StageProblem {
                    file,
                    reason: format!(
                        "{}; the sequence's {} posed frames are skipped",
                        e.reason(),
                        seq_frames.len()
                    ),
                });
            }
        }
    }
    Ok(found)
}

/// The posed frames (`frame_N_rgb.png` with a `frame_N_pose.txt`) of the sequence folder
/// `seq`, in file-name order; counts every frame in `found` and lists the unposed ones.
fn sequence_frames(input: &Path, seq: &Path, name: &str, found: &mut Found) -> Result<Vec<Frame>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(seq)
        .map_err(|e| Error::io(seq, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    files.sort();
    let mut seq_frames = Vec::new();
    for f in &files {
        let fname = f.file_name().unwrap().to_string_lossy().into_owned();
        let Some(number) = fname
            .strip_prefix("frame_")
            .and_then(|n| n.strip_suffix("_rgb.png"))
        else {
            continue;
        };
        found.frames_found += 1;
        let pose = seq.join(format!("frame_{number}_pose.txt"));
        if !pose.is_file() {
            found.without_pose.push(rel(input, f));
            continue;
        }
        seq_frames.push(Frame {
            sequence: name.to_string(),
            number: number.to_string(),
            image: f.clone(),
            pose,
        });
    }
    Ok(seq_frames)
}

/// The sequence's calibration (`rgb.cal`, which must have no distortion) and its head
/// mesh (`NN.obj` beside the sequence folders).
fn load_sequence(input: &Path, seq: &Path, name: &str) -> Result<(Calibration, HeadMesh)> {
    let cal_path = seq.join("rgb.cal");
    let mesh_path = input.join(format!("{name}.obj"));
    Calibration::read(&cal_path)
        .and_then(|cal| {
            if cal.distortion.iter().any(|&d| d != 0.0) {
                return Err(Error::format(
                    &cal_path,
                    format!(
                        "distortion coefficients {:?} are not zero; this conversion models a pinhole camera",
                        cal.distortion
                    ),
                ));
            }
            Ok(cal)
        })
        .and_then(|cal| Ok((cal, HeadMesh::read(&mesh_path)?)))
}

/// The topology of the first usable sequence's head mesh; the sequences whose mesh has
/// another vertex count are reported in `problems` and dropped with their frames.
fn common_topology(
    input: &Path,
    found: &mut Found,
    problems: &mut Vec<StageProblem>,
) -> Result<FaceTopology> {
    let sequences = &mut found.sequences;
    let Some((_, (_, first_mesh))) = sequences.iter().next() else {
        return Err(Error::format(
            input,
            format!(
                "no sequence could be read: {}",
                problems
                    .iter()
                    .map(|p| format!("{}: {}", p.file, p.reason))
                    .collect::<Vec<_>>()
                    .join("; ")
            ),
        ));
    };
    let topology = biwi_topology(first_mesh)?;
    let n = topology.vertex_count;
    let bad_meshes: Vec<String> = sequences
        .iter()
        .filter(|(_, (_, m))| m.vertices.len() != n)
        .map(|(s, _)| s.clone())
        .collect();
    for s in &bad_meshes {
        problems.push(StageProblem {
            file: format!("{s}.obj"),
            reason: format!(
                "{} vertices where the other head meshes have {n}; the sequence is skipped",
                sequences[s].1.vertices.len()
            ),
        });
        sequences.remove(s);
    }
    found.frames.retain(|f| sequences.contains_key(&f.sequence));
    Ok(topology)
}

/// Where and how the frames of a staging are written.
struct StageTarget<'a> {
    /// The `hpdb` folder (problems name files relative to it).
    input: &'a Path,
    /// The staging folder's release layout.
    layout: ReleaseLayout,
    /// The release camera at `side x side`.
    camera: Camera,
    /// The written images' side.
    side: u32,
    /// The first write error: it stops the staging.
    fatal: std::sync::Mutex<Option<Error>>,
}

/// Reads, checks, resamples and writes one frame (image and info) of a sequence with
/// calibration `cal` and release-frame head vertices `verts`. The error is the problem
/// and whether the frame-size check refused it; a write error is also kept in
/// `target.fatal` (a frame that cannot be written, a full disk say, stops the staging,
/// naming the file: skipping it would leave a smaller release that looks complete).
fn stage_frame(
    target: &StageTarget<'_>,
    f: &Frame,
    cal: &Calibration,
    verts: &[Point3<f32>],
) -> std::result::Result<SampleKey, (bool, StageProblem)> {
    let mut size_refused = false;
    let r = (|| {
        let key = SampleKey {
            subject_id: f.sequence.clone(),
            facial_action: "biwi".into(),
            img_id: f.number.clone(),
        };
        let problem = |p: &Path, reason: String| StageProblem {
            file: rel(target.input, p),
            reason,
        };
        let text = read_text(&f.pose).map_err(|e| problem(&f.pose, e.reason()))?;
        let fp = FramePose::parse(&text, &f.pose).map_err(|e| problem(&f.pose, e.reason()))?;
        let pose = release_pose(&fp, cal);
        pose.check()
            .map_err(|e| problem(&f.pose, format!("the pose: {}", e.reason())))?;
        // The frame's size from its header, against the calibration's, before
        // any pixel is decoded (the decode itself is bounded too).
        let img = crate::picture::image_decode::read_rgb8_checked(&f.image, |h| {
            cal.check_frame_size(h.width, h.height).map_err(|m| {
                size_refused = true;
                Error::format(&f.image, m)
            })
        })
        .map_err(|e| problem(&f.image, e.reason()))?;
        let written = resample_to_release(&img, &cal.k, &Matrix3::identity(), target.side);
        let info =
            InfoAnnotation::complete(verts.to_vec(), &pose, &target.camera, Matrix4::identity());
        let write = |e: Error| {
            let p = problem(&f.image, format!("could not write: {e}"));
            target.fatal.lock().expect("fatal lock").get_or_insert(e);
            p
        };
        let layout = &target.layout;
        let jpeg = crate::picture::encode::jpeg_bytes(&written, 95).map_err(write)?;
        atomic_file::write_bytes(&layout.image_path(Split::Test, &key), &jpeg).map_err(write)?;
        release::write_info(
            &layout.info_path(Split::Test, &key),
            &info,
            NpzCompression::Deflated,
        )
        .map_err(write)?;
        Ok(key)
    })();
    r.map_err(|p| (size_refused, p))
}
