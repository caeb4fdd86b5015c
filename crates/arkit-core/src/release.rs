//! The release's files: layout, `_info.npz` annotations and list CSVs.
//!
//! Download layout (what users unpack):
//!
//! ```text
//! ARKitFace_image_{train,test}/image/<subject_id>/<facial_action>/<img_id>_ar.jpg
//! ARKitFace_info_{train,test}/info/<subject_id>/<facial_action>/<img_id>_info.npz
//! ARKitFace_list/list/ARKitFace_{train,test}.csv
//! ```
//!
//! Ids are strings everywhere (`225579`, `09_LeftToRight_Frown`, `1616212233525`):
//! leading zeros are kept.

use crate::conventions::{EulerAngles, Pose};
use crate::error::{Error, Result};
use crate::npy::{self, NpyArray, Npz, NpzCompression};
use nalgebra::Point3;
use std::fmt;
use std::path::{Path, PathBuf};

/// The key of one sample: `(subject_id, facial_action, img_id)`, all strings.
#[derive(
    Clone, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize,
)]
pub struct SampleKey {
    /// Subject id, e.g. `225579`.
    pub subject_id: String,
    /// Facial action folder, e.g. `09_LeftToRight_Frown`.
    pub facial_action: String,
    /// Image id, e.g. `1616212233525`.
    pub img_id: String,
}

impl fmt::Display for SampleKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}/{}/{}",
            self.subject_id, self.facial_action, self.img_id
        )
    }
}

/// The release's two splits.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum Split {
    /// The frames a model trains on (`train`).
    Train,
    /// The frames it is evaluated on (`test`).
    Test,
}

impl Split {
    /// `"train"` or `"test"`.
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Test => "test",
        }
    }
}

/// Paths of the download layout under a root folder.
#[derive(Clone, Debug)]
pub struct ReleaseLayout {
    /// The folder that holds `ARKitFace_image_train/` and the others.
    pub root: PathBuf,
}

impl ReleaseLayout {
    /// The layout under `root`.
    pub fn new(root: impl Into<PathBuf>) -> Self {
        ReleaseLayout { root: root.into() }
    }

    /// `ARKitFace_image_{split}/image/<subject>/<action>/<img_id>_ar.jpg`, relative.
    pub fn image_relative(split: Split, key: &SampleKey) -> PathBuf {
        PathBuf::from(format!("ARKitFace_image_{}", split.name()))
            .join("image")
            .join(&key.subject_id)
            .join(&key.facial_action)
            .join(format!("{}_ar.jpg", key.img_id))
    }

    /// `ARKitFace_info_{split}/info/<subject>/<action>/<img_id>_info.npz`, relative.
    pub fn info_relative(split: Split, key: &SampleKey) -> PathBuf {
        PathBuf::from(format!("ARKitFace_info_{}", split.name()))
            .join("info")
            .join(&key.subject_id)
            .join(&key.facial_action)
            .join(format!("{}_info.npz", key.img_id))
    }

    /// Absolute image path.
    pub fn image_path(&self, split: Split, key: &SampleKey) -> PathBuf {
        self.root.join(Self::image_relative(split, key))
    }

    /// Absolute annotation path.
    pub fn info_path(&self, split: Split, key: &SampleKey) -> PathBuf {
        self.root.join(Self::info_relative(split, key))
    }

    /// `ARKitFace_list/list/ARKitFace_{split}.csv`.
    pub fn list_path(&self, split: Split) -> PathBuf {
        self.root
            .join("ARKitFace_list")
            .join("list")
            .join(format!("ARKitFace_{}.csv", split.name()))
    }
}

/// The content of one `_info.npz`.
///
/// `verts` and `R_t` are required; the other keys are optional in the release and read
/// when present. Every array is checked for shape and finite values, and `R_t` with
/// [`Pose::check_release_rt`].
#[derive(Clone, Debug, PartialEq)]
pub struct InfoAnnotation {
    /// `verts`: the face in the canonical frame, metres (1220 x 3).
    pub verts: Vec<Point3<f32>>,
    /// `R_t`: row-vector pose, row-major.
    pub rt: [f64; 16],
    /// `verts_gt`, when present (used by the official augmentation).
    pub verts_gt: Option<Vec<Point3<f32>>>,
    /// `faceAnchortransform` (4x4, row-major), when present.
    pub face_anchor_transform: Option<[f64; 16]>,
    /// `cameratransform` (4x4, row-major), when present.
    pub camera_transform: Option<[f64; 16]>,
    /// `projectionMatrix` (4x4, row-vector form, row-major), when present.
    pub projection_matrix: Option<[f64; 16]>,
    /// `euler_angles` as stored: `[pitch, yaw, roll]` in degrees, when present.
    pub euler_angles_pyr: Option<[f64; 3]>,
    /// `translation` (metres, `R_t[3, :3]`), when present.
    pub translation: Option<[f64; 3]>,
    /// `points2d`: projected vertices in image pixels (1220 x 2), when present.
    pub points2d: Option<Vec<[f64; 2]>>,
}

/// Number of vertices an ARKit face has; `_info.npz` files must match it.
pub const ARKIT_VERTEX_COUNT: usize = 1220;

fn points3(values: Vec<f64>) -> Vec<Point3<f32>> {
    values
        .chunks(3)
        .map(|c| Point3::new(c[0] as f32, c[1] as f32, c[2] as f32))
        .collect()
}

fn mat16(values: Vec<f64>) -> [f64; 16] {
    let mut m = [0.0; 16];
    m.copy_from_slice(&values);
    m
}

impl InfoAnnotation {
    /// The pose of `R_t` (already validated by [`read_info`]).
    pub fn pose(&self) -> Result<Pose> {
        Pose::from_release_rt(&self.rt)
    }

    /// Parses an `_info.npz` archive; `path` names it in errors.
    pub(crate) fn from_npz(npz: &Npz, path: &Path) -> Result<Self> {
        Self::from_npz_with_vertex_count(npz, path, ARKIT_VERTEX_COUNT)
    }

    /// As [`InfoAnnotation::from_npz`] for a mesh of `vertex_count` vertices (another
    /// head mesh than ARKit's, such as BIWI's, converted into the release's layout).
    pub(crate) fn from_npz_with_vertex_count(
        npz: &Npz,
        path: &Path,
        vertex_count: usize,
    ) -> Result<Self> {
        let verts = points3(npz.require_finite_f64("verts", &[vertex_count, 3])?);
        let rt = mat16(npz.require_finite_f64("R_t", &[4, 4])?);
        Pose::check_release_rt(&rt).map_err(|e| e.in_file(path))?;
        let optional = |key: &str, shape: &[usize]| -> Result<Option<Vec<f64>>> {
            if npz.get(key).is_some() {
                npz.require_finite_f64(key, shape).map(Some)
            } else {
                Ok(None)
            }
        };
        Ok(InfoAnnotation {
            verts,
            rt,
            verts_gt: optional("verts_gt", &[vertex_count, 3])?.map(points3),
            face_anchor_transform: optional("faceAnchortransform", &[4, 4])?.map(mat16),
            camera_transform: optional("cameratransform", &[4, 4])?.map(mat16),
            projection_matrix: optional("projectionMatrix", &[4, 4])?.map(mat16),
            euler_angles_pyr: optional("euler_angles", &[3])?.map(|v| [v[0], v[1], v[2]]),
            translation: optional("translation", &[3])?.map(|v| [v[0], v[1], v[2]]),
            points2d: optional("points2d", &[vertex_count, 2])?
                .map(|v| v.chunks(2).map(|c| [c[0], c[1]]).collect()),
        })
    }

    /// The annotation of a face `verts` at `pose`, with every optional key filled
    /// consistently: `verts_gt = verts`, `faceAnchortransform = R_t @ cameratransform`
    /// for the given camera transform, `projectionMatrix`, `euler_angles`
    /// (`[pitch, yaw, roll]`), `translation`, and `points2d` (the projected vertices).
    pub fn complete(
        verts: Vec<Point3<f32>>,
        pose: &Pose,
        camera: &crate::conventions::Camera,
        camera_transform: nalgebra::Matrix4<f64>,
    ) -> Self {
        let rt_m = pose.release_matrix();
        let anchor = rt_m * camera_transform;
        let to16 = |m: &nalgebra::Matrix4<f64>| {
            let mut o = [0.0; 16];
            for r in 0..4 {
                for c in 0..4 {
                    o[r * 4 + c] = m[(r, c)];
                }
            }
            o
        };
        let pts: Vec<Point3<f64>> = verts.iter().map(|p| p.cast::<f64>()).collect();
        let projected = camera.project_all(pose, &pts);
        let e: EulerAngles = pose.euler();
        let t = pose.translation_m();
        InfoAnnotation {
            verts_gt: Some(verts.clone()),
            verts,
            rt: pose.to_release_rt(),
            face_anchor_transform: Some(to16(&anchor)),
            camera_transform: Some(to16(&camera_transform)),
            projection_matrix: Some(to16(&camera.projection)),
            euler_angles_pyr: Some(e.to_release_order()),
            translation: Some([t.x, t.y, t.z]),
            points2d: Some(projected.iter().map(|p| [p.u, p.v]).collect()),
        }
    }

    /// The arrays of this annotation, in the order written, with the dtypes the release
    /// uses (float32 for vertices and 2D points, float64 for matrices and angles).
    pub fn to_arrays(&self) -> Vec<(&'static str, NpyArray)> {
        let v32 = |v: &[Point3<f32>]| {
            NpyArray::from_f32(
                vec![v.len(), 3],
                v.iter().flat_map(|p| [p.x, p.y, p.z]).collect(),
            )
            .expect("shape")
        };
        let m44 = |m: &[f64; 16]| NpyArray::from_f64(vec![4, 4], m.to_vec()).expect("shape");
        let mut out = vec![("verts", v32(&self.verts)), ("R_t", m44(&self.rt))];
        if let Some(v) = &self.verts_gt {
            out.push(("verts_gt", v32(v)));
        }
        if let Some(m) = &self.face_anchor_transform {
            out.push(("faceAnchortransform", m44(m)));
        }
        if let Some(m) = &self.camera_transform {
            out.push(("cameratransform", m44(m)));
        }
        if let Some(m) = &self.projection_matrix {
            out.push(("projectionMatrix", m44(m)));
        }
        if let Some(e) = &self.euler_angles_pyr {
            out.push((
                "euler_angles",
                NpyArray::from_f64(vec![3], e.to_vec()).expect("shape"),
            ));
        }
        if let Some(t) = &self.translation {
            out.push((
                "translation",
                NpyArray::from_f64(vec![3], t.to_vec()).expect("shape"),
            ));
        }
        if let Some(p) = &self.points2d {
            out.push((
                "points2d",
                NpyArray::from_f32(
                    vec![p.len(), 2],
                    p.iter().flat_map(|q| [q[0] as f32, q[1] as f32]).collect(),
                )
                .expect("shape"),
            ));
        }
        out
    }

    /// The bytes of this annotation as an `.npz` archive (deterministic).
    pub fn to_npz_bytes(&self, compression: NpzCompression) -> Result<Vec<u8>> {
        let arrays = self.to_arrays();
        let members: Vec<(&str, &NpyArray)> = arrays.iter().map(|(k, a)| (*k, a)).collect();
        let mut cursor = std::io::Cursor::new(Vec::new());
        npy::write_npz(&mut cursor, &members, compression)?;
        Ok(cursor.into_inner())
    }
}

/// Reads and validates one `_info.npz`.
pub fn read_info(path: &Path) -> Result<InfoAnnotation> {
    let npz = npy::read_npz(path)?;
    InfoAnnotation::from_npz(&npz, path)
}

/// Reads and validates one `_info.npz` whose mesh has `vertex_count` vertices.
pub fn read_info_with_vertex_count(path: &Path, vertex_count: usize) -> Result<InfoAnnotation> {
    let npz = npy::read_npz(path)?;
    InfoAnnotation::from_npz_with_vertex_count(&npz, path, vertex_count)
}

/// Writes one `_info.npz` atomically (as numpy's `savez_compressed` or `savez`).
pub fn write_info(path: &Path, info: &InfoAnnotation, compression: NpzCompression) -> Result<()> {
    let bytes = info.to_npz_bytes(compression)?;
    crate::atomic_file::write_bytes(path, &bytes)
}

/// One row of a list CSV.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ListRow {
    /// The sample's key.
    pub key: SampleKey,
    /// The line number in the file (1-based, the header is line 1), for reports.
    pub line: usize,
}

/// Reads a list CSV: a header naming at least `subject_id`, `facial_action` and
/// `img_id` (in any order, other columns ignored; a leading unnamed index column as
/// pandas writes it is fine), then one row per sample. Ids are kept as strings.
pub fn read_list(path: &Path) -> Result<Vec<ListRow>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse_list(&text, path)
}

/// Parses list CSV text; `path` names it in errors. See [`read_list`].
///
/// A leading UTF-8 byte-order mark (as Excel writes "CSV UTF-8") is skipped.
pub(crate) fn parse_list(text: &str, path: &Path) -> Result<Vec<ListRow>> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut lines = text.lines().enumerate();
    let header = loop {
        match lines.next() {
            Some((_, l)) if l.trim().is_empty() => continue,
            Some((_, l)) => break split_csv_line(l),
            None => return Err(Error::format(path, "empty list file (no header)")),
        }
    };
    let col = |name: &str| -> Result<usize> {
        header.iter().position(|h| h.trim() == name).ok_or_else(|| {
            Error::format(
                path,
                format!(
                    "header has no '{name}' column (found: {})",
                    header.join(", ")
                ),
            )
        })
    };
    let (cs, ca, ci) = (col("subject_id")?, col("facial_action")?, col("img_id")?);
    let mut rows = Vec::new();
    for (n, line) in lines {
        if line.trim().is_empty() {
            continue;
        }
        let fields = split_csv_line(line);
        let get = |c: usize, name: &str| -> Result<String> {
            let v = fields
                .get(c)
                .map(|s| s.trim().to_string())
                .filter(|s| !s.is_empty())
                .ok_or_else(|| Error::format(path, format!("line {}: missing {name}", n + 1)))?;
            if v.contains('/') || v.contains('\\') || v == "." || v == ".." {
                return Err(Error::format(
                    path,
                    format!("line {}: {name} '{v}' is not a plain name", n + 1),
                ));
            }
            Ok(v)
        };
        rows.push(ListRow {
            key: SampleKey {
                subject_id: get(cs, "subject_id")?,
                facial_action: get(ca, "facial_action")?,
                img_id: get(ci, "img_id")?,
            },
            line: n + 1,
        });
    }
    Ok(rows)
}

/// Splits one CSV line, honouring double-quoted fields (`""` inside quotes is a quote).
fn split_csv_line(line: &str) -> Vec<String> {
    let mut fields = Vec::new();
    let mut cur = String::new();
    let mut quoted = false;
    let mut chars = line.trim_end_matches('\r').chars().peekable();
    while let Some(c) = chars.next() {
        match (c, quoted) {
            ('"', true) if chars.peek() == Some(&'"') => {
                cur.push('"');
                chars.next();
            }
            ('"', _) => quoted = !quoted,
            (',', false) => fields.push(std::mem::take(&mut cur)),
            _ => cur.push(c),
        }
    }
    fields.push(cur);
    fields
}

/// The text of a list CSV for `keys` (header `subject_id,facial_action,img_id`). A field
/// with a comma, a double quote or a line break is quoted as RFC 4180 says (inner
/// quotes doubled), so `parse_list` (and pandas) read back the same ids.
pub fn list_csv_text(keys: &[SampleKey]) -> String {
    fn field(v: &str) -> std::borrow::Cow<'_, str> {
        if v.contains([',', '"', '\n', '\r']) {
            format!("\"{}\"", v.replace('"', "\"\"")).into()
        } else {
            v.into()
        }
    }
    let mut s = String::from("subject_id,facial_action,img_id\n");
    for k in keys {
        s.push_str(&format!(
            "{},{},{}\n",
            field(&k.subject_id),
            field(&k.facial_action),
            field(&k.img_id)
        ));
    }
    s
}

/// Writes the list CSVs of a release rooted at `root` together: `lists` (split name,
/// keys) become `root/ARKitFace_list/list/ARKitFace_{split}.csv`, replacing the whole
/// `ARKitFace_list/` folder at once (`atomic_file::publish_dir`), so a reader never sees
/// one list of this run beside one of another (or a train list without its test list).
pub fn write_lists(root: &Path, lists: &[(&str, &[SampleKey])]) -> Result<()> {
    let dir = root.join("ARKitFace_list");
    let tmp = crate::atomic_file::TemporaryDir::create(&dir)?;
    for (split, keys) in lists {
        write_list(
            &tmp.path()
                .join("list")
                .join(format!("ARKitFace_{split}.csv")),
            keys,
        )?;
    }
    crate::atomic_file::publish_dir(tmp, &dir)
}

/// Writes a list CSV atomically.
pub fn write_list(path: &Path, keys: &[SampleKey]) -> Result<()> {
    crate::atomic_file::write_bytes(path, list_csv_text(keys).as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::conventions::Camera;
    use nalgebra::{Matrix4, Vector3};

    fn key(s: &str, a: &str, i: &str) -> SampleKey {
        SampleKey {
            subject_id: s.into(),
            facial_action: a.into(),
            img_id: i.into(),
        }
    }

    #[test]
    fn layout_paths() {
        let l = ReleaseLayout::new("/data");
        let k = key("000123", "09_LeftToRight_Frown", "1616212233525");
        assert_eq!(
            l.image_path(Split::Train, &k),
            PathBuf::from(
                "/data/ARKitFace_image_train/image/000123/09_LeftToRight_Frown/1616212233525_ar.jpg"
            )
        );
        assert_eq!(
            l.info_path(Split::Test, &k),
            PathBuf::from(
                "/data/ARKitFace_info_test/info/000123/09_LeftToRight_Frown/1616212233525_info.npz"
            )
        );
        assert_eq!(
            l.list_path(Split::Test),
            PathBuf::from("/data/ARKitFace_list/list/ARKitFace_test.csv")
        );
    }

    #[test]
    fn list_keeps_leading_zeros_and_reads_pandas_index() {
        let text = ",subject_id,facial_action,img_id,extra\n0,000123,01_Neutral,0001616,x\n1,\"42\",\"a,b\",7\n";
        let rows = parse_list(text, Path::new("l.csv")).unwrap();
        assert_eq!(rows[0].key, key("000123", "01_Neutral", "0001616"));
        assert_eq!(rows[1].key, key("42", "a,b", "7"));
        assert_eq!(rows[1].line, 3);
        // Round trip of our own writer.
        let keys: Vec<_> = rows
            .iter()
            .map(|r| r.key.clone())
            .filter(|k| !k.facial_action.contains(','))
            .collect();
        let back = parse_list(&list_csv_text(&keys), Path::new("x")).unwrap();
        assert_eq!(back.into_iter().map(|r| r.key).collect::<Vec<_>>(), keys);
    }

    #[test]
    fn list_with_a_utf8_bom_reads_like_without() {
        let plain = "subject_id,facial_action,img_id\r\n000123,01_Neutral,0001616\r\n";
        let with_bom = format!("\u{feff}{plain}");
        let rows = parse_list(&with_bom, Path::new("bom.csv")).unwrap();
        assert_eq!(rows, parse_list(plain, Path::new("bom.csv")).unwrap());
        assert_eq!(rows[0].key, key("000123", "01_Neutral", "0001616"));
        assert_eq!(rows[0].line, 2);
        // Only a leading mark is skipped: one inside a name is kept, so it does not match.
        let inner = "subject_id,\u{feff}facial_action,img_id\n1,a,2\n";
        assert!(parse_list(inner, Path::new("bom.csv")).is_err());
    }

    #[test]
    fn list_errors_name_file_and_line() {
        let err = parse_list("subject_id,img_id\n1,2\n", Path::new("a.csv"))
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with("a.csv:") && err.contains("facial_action"),
            "{err}"
        );
        let err = parse_list(
            "subject_id,facial_action,img_id\n1,,3\n",
            Path::new("a.csv"),
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("line 2") && err.contains("facial_action"),
            "{err}"
        );
        let err = parse_list(
            "subject_id,facial_action,img_id\n1,../x,3\n",
            Path::new("a.csv"),
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("not a plain name"), "{err}");
        assert!(parse_list("", Path::new("a.csv")).is_err());
    }

    fn sample_info() -> InfoAnnotation {
        let verts: Vec<Point3<f32>> = (0..ARKIT_VERTEX_COUNT)
            .map(|i| Point3::new(i as f32 * 1e-4, -0.01, 0.02))
            .collect();
        let pose = Pose::from_euler(
            EulerAngles::new(20.0, -10.0, 5.0),
            Vector3::new(0.01, 0.02, -0.5),
        );
        let cam_t = Matrix4::new_translation(&Vector3::new(0.1, 0.2, 0.3));
        InfoAnnotation::complete(verts, &pose, &Camera::release(640, 480), cam_t)
    }

    #[test]
    fn info_round_trip_and_consistency() {
        let dir = tempfile::tempdir().unwrap();
        let info = sample_info();
        for (i, c) in [NpzCompression::Stored, NpzCompression::Deflated]
            .into_iter()
            .enumerate()
        {
            let p = dir.path().join(format!("{i}_info.npz"));
            write_info(&p, &info, c).unwrap();
            let back = read_info(&p).unwrap();
            // f32 keys (points2d) lose precision; everything else is exact.
            assert_eq!(back.verts, info.verts);
            assert_eq!(back.rt, info.rt);
            assert_eq!(back.face_anchor_transform, info.face_anchor_transform);
            let p2 = back.points2d.as_ref().unwrap();
            assert!((p2[5][0] - info.points2d.as_ref().unwrap()[5][0]).abs() < 1e-3);
        }
        // R_t = faceAnchortransform @ inv(cameratransform), as the official code builds it.
        let a = Matrix4::from_row_slice(info.face_anchor_transform.as_ref().unwrap());
        let c = Matrix4::from_row_slice(info.camera_transform.as_ref().unwrap());
        let rt = a * c.try_inverse().unwrap();
        assert!((rt - Matrix4::from_row_slice(&info.rt)).abs().max() < 1e-12);
        let [p, y, r] = info.euler_angles_pyr.unwrap();
        assert!((p + 10.0).abs() < 1e-9 && (y - 20.0).abs() < 1e-9 && (r - 5.0).abs() < 1e-9);
        assert_eq!(info.translation.unwrap(), [0.01, 0.02, -0.5]);
    }

    #[test]
    fn broken_info_files_are_reported_with_their_reason() {
        let dir = tempfile::tempdir().unwrap();
        let info = sample_info();
        let write = |name: &str, members: Vec<(&str, NpyArray)>| {
            let p = dir.path().join(name);
            let refs: Vec<(&str, &NpyArray)> = members.iter().map(|(k, a)| (*k, a)).collect();
            let mut f = std::fs::File::create(&p).unwrap();
            npy::write_npz(&mut f, &refs, NpzCompression::Stored).unwrap();
            p
        };
        let arrays = info.to_arrays();
        let get = |k: &str| arrays.iter().find(|(n, _)| *n == k).unwrap().1.clone();
        // Missing key.
        let p = write("missing_info.npz", vec![("verts", get("verts"))]);
        let e = read_info(&p).unwrap_err().to_string();
        assert!(e.contains("missing_info.npz") && e.contains("R_t"), "{e}");
        // Wrong shape.
        let short = NpyArray::from_f32(vec![1219, 3], vec![0.0; 1219 * 3]).unwrap();
        let p = write(
            "short_info.npz",
            vec![("verts", short), ("R_t", get("R_t"))],
        );
        let e = read_info(&p).unwrap_err().to_string();
        assert!(e.contains("short_info.npz") && e.contains("1219"), "{e}");
        // NaN.
        let mut v = get("verts").to_f32_vec();
        v[10] = f32::NAN;
        let p = write(
            "nan_info.npz",
            vec![
                ("verts", NpyArray::from_f32(vec![1220, 3], v).unwrap()),
                ("R_t", get("R_t")),
            ],
        );
        let e = read_info(&p).unwrap_err().to_string();
        assert!(e.contains("nan_info.npz") && e.contains("verts"), "{e}");
        // Positive tz.
        let mut rt = info.rt;
        rt[14] = 0.5;
        let p = write(
            "tz_info.npz",
            vec![
                ("verts", get("verts")),
                ("R_t", NpyArray::from_f64(vec![4, 4], rt.to_vec()).unwrap()),
            ],
        );
        let e = read_info(&p).unwrap_err().to_string();
        assert!(e.contains("tz_info.npz") && e.contains("negative"), "{e}");
        // Truncated archive.
        let good = dir.path().join("good_info.npz");
        write_info(&good, &info, NpzCompression::Deflated).unwrap();
        let bytes = std::fs::read(&good).unwrap();
        let p = dir.path().join("truncated_info.npz");
        std::fs::write(&p, &bytes[..bytes.len() / 2]).unwrap();
        let e = read_info(&p).unwrap_err().to_string();
        assert!(e.contains("truncated_info.npz"), "{e}");
    }

    #[test]
    fn list_ids_with_commas_and_quotes_round_trip() {
        let keys = vec![
            SampleKey {
                subject_id: "12,5".into(),
                facial_action: "say \"hi\"".into(),
                img_id: "007".into(),
            },
            SampleKey {
                subject_id: "plain".into(),
                facial_action: "a".into(),
                img_id: "1".into(),
            },
        ];
        let text = list_csv_text(&keys);
        assert!(text.contains("\"12,5\",\"say \"\"hi\"\"\",007"), "{text}");
        let back: Vec<SampleKey> = parse_list(&text, Path::new("l.csv"))
            .unwrap()
            .into_iter()
            .map(|r| r.key)
            .collect();
        assert_eq!(back, keys);
    }
}
