//! `arkit-tool predict --image`: the poses of the faces in photos, as the official
//! `demo.py` finds them (docs/photos.md).

use arkit_core::conventions::{AngleConvention, AngleUnit};
use arkit_core::{Error, Result};
use arkit_data::picture::read_photo_upright;
use arkit_data::picture::{DEMO_SIDE, DemoSquare};
use arkit_data::picture::{DetectOptions, detect_faces};
use arkit_data::pose::PhotoCamera;
use arkit_data::pose::RansacParams;
use serde_json::{Value, json};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// What `predict --image` was asked.
pub struct ImageRequest<'a> {
    pub images: &'a [PathBuf],
    pub model: &'a Path,
    pub resources: Option<&'a Path>,
    pub boxes: &'a [String],
    pub boxes_file: Option<&'a Path>,
    pub min_face_px: u32,
    pub detector_score: f64,
    pub focal_px: Option<f64>,
    pub fov_deg: Option<f64>,
    pub angles: AngleConvention,
    pub vertices: bool,
    pub draw: Option<&'a Path>,
    pub dump_crops: Option<&'a Path>,
    pub mesh: Option<&'a Path>,
    pub output: Option<&'a Path>,
    pub seed: u64,
    pub ransac: RansacParams,
    pub strict: bool,
    pub json: bool,
}

/// One photo of a run: its path as found, whether it was named on the command line (not
/// found in a folder), and its name in output folders (see [`output_names`]).
struct PhotoFile {
    path: PathBuf,
    named: bool,
    /// The path relative to the deepest folder holding every photo of the run, with
    /// its extension (`face.jpg`, or `trip1/face.jpg` for photos of two folders).
    relative: PathBuf,
}

impl PhotoFile {
    /// The output name: `relative` without its extension.
    fn stem(&self) -> PathBuf {
        self.relative.with_extension("")
    }
}

/// The image files of `--image` arguments: files as given, folders' images (`.jpg`,
/// `.jpeg`, `.png`, `.webp`, any case) sorted by name, not recursing.
fn photo_files(images: &[PathBuf]) -> Result<Vec<PhotoFile>> {
    let mut out = Vec::new();
    for p in images {
        let meta = std::fs::metadata(p).map_err(|e| Error::io(p, e))?;
        if meta.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(p)
                .map_err(|e| Error::io(p, e))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|f| {
                    f.is_file()
                        && f.extension().is_some_and(|x| {
                            let x = x.to_string_lossy().to_ascii_lowercase();
                            matches!(x.as_str(), "jpg" | "jpeg" | "png" | "webp")
                        })
                })
                .collect();
            found.sort();
            if found.is_empty() {
                return Err(Error::invalid(
                    "--image",
                    format!(
                        "{}: a folder with no .jpg, .jpeg, .png or .webp file",
                        p.display()
                    ),
                ));
            }
            out.extend(found.into_iter().map(|path| (path, false)));
        } else {
            out.push((p.clone(), true));
        }
    }
    let relative = output_names(out.iter().map(|(p, _)| p.as_path()))?;
    Ok(out
        .into_iter()
        .zip(relative)
        .map(|((path, named), relative)| PhotoFile {
            path,
            named,
            relative,
        })
        .collect())
}

/// Each photo's path relative to the deepest folder that holds them all (their folders
/// resolved, symbolic links followed): the file name when they share one folder,
/// `trip1/face.jpg` and `trip2/face.jpg` for photos of two folders.
fn output_names<'a>(paths: impl Iterator<Item = &'a Path>) -> Result<Vec<PathBuf>> {
    let mut full = Vec::new();
    for p in paths {
        let parent = p.parent().filter(|d| !d.as_os_str().is_empty());
        let dir = parent.unwrap_or(Path::new("."));
        let dir = std::fs::canonicalize(dir).map_err(|e| Error::io(dir, e))?;
        let name = p
            .file_name()
            .ok_or_else(|| Error::invalid("--image", format!("{}: not a file", p.display())))?;
        full.push(dir.join(name));
    }
    let Some(first) = full.first() else {
        return Ok(Vec::new());
    };
    let mut common: PathBuf = first.parent().expect("a file in a folder").to_path_buf();
    for f in &full[1..] {
        while !f.starts_with(&common) {
            if !common.pop() {
                break;
            }
        }
    }
    Ok(full
        .iter()
        .map(|f| f.strip_prefix(&common).unwrap_or(f).to_path_buf())
        .collect())
}

/// Refuses a run whose photos would write the same output file (`face.jpg` and
/// `face.png` of one folder, or a photo given twice): the two photos and the option.
fn check_unique_outputs(photos: &[PhotoFile], options: &str) -> Result<()> {
    let mut seen: HashMap<PathBuf, &Path> = HashMap::new();
    for p in photos {
        if let Some(other) = seen.insert(p.stem(), &p.path) {
            return Err(Error::invalid(
                options,
                format!(
                    "{} and {} would write the same files ({}.*): rename one, or run them separately",
                    other.display(),
                    p.path.display(),
                    p.stem().display()
                ),
            ));
        }
    }
    Ok(())
}

/// One `--box "x0 y0 x1 y1"` (spaces or commas).
fn parse_box(s: &str) -> Result<[f64; 4]> {
    let v: Vec<f64> = s
        .split(|c: char| c == ',' || c.is_whitespace())
        .filter(|t| !t.is_empty())
        .map(|t| t.parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| {
            Error::invalid("--box", format!("'{s}': expected four numbers x0 y0 x1 y1"))
        })?;
    <[f64; 4]>::try_from(v)
        .map_err(|_| Error::invalid("--box", format!("'{s}': expected four numbers x0 y0 x1 y1")))
}

/// Face boxes by photo, from a `--boxes` file: JSON (`[[x0, y0, x1, y1], ...]` for a
/// single photo, or `{"PHOTO": [[...], ...], ...}`) or CSV with the header
/// `image,x0,y0,x1,y1`. Photos are named as given on the command line or by file name.
fn read_boxes_file(path: &Path) -> Result<HashMap<String, Vec<[f64; 4]>>> {
    const MAX_BYTES: u64 = 64 << 20;
    let meta = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    if meta.len() > MAX_BYTES {
        return Err(Error::format(
            path,
            format!("{} bytes: a boxes file may hold 64 MiB", meta.len()),
        ));
    }
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let is_json = path
        .extension()
        .is_some_and(|x| x.eq_ignore_ascii_case("json"));
    let mut out: HashMap<String, Vec<[f64; 4]>> = HashMap::new();
    if is_json {
        let v: Value = serde_json::from_str(&text)
            .map_err(|e| Error::format(path, format!("not JSON: {e}")))?;
        let list = |v: &Value, what: &str| -> Result<Vec<[f64; 4]>> {
            let items = v.as_array().ok_or_else(|| {
                Error::format(path, format!("{what}: expected a list of [x0, y0, x1, y1]"))
            })?;
            items
                .iter()
                .map(|b| {
                    let nums: Option<Vec<f64>> = b
                        .as_array()
                        .map(|a| a.iter().map(|x| x.as_f64()).collect::<Option<Vec<f64>>>())
                        .unwrap_or(None);
                    nums.and_then(|n| <[f64; 4]>::try_from(n).ok())
                        .ok_or_else(|| {
                            Error::format(path, format!("{what}: {b} is not [x0, y0, x1, y1]"))
                        })
                })
                .collect()
        };
        match &v {
            Value::Array(_) => {
                out.insert(String::new(), list(&v, "the boxes")?);
            }
            Value::Object(m) => {
                for (k, b) in m {
                    out.insert(k.clone(), list(b, k)?);
                }
            }
            _ => {
                return Err(Error::format(
                    path,
                    "expected a list of boxes or an object of photo -> boxes",
                ));
            }
        }
    } else {
        let mut lines = text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty());
        let header = lines.next().map(|(_, l)| l.trim().to_ascii_lowercase());
        if header.as_deref().map(|h| h.replace(' ', "")) != Some("image,x0,y0,x1,y1".into()) {
            return Err(Error::format(
                path,
                "a CSV of boxes starts with the header image,x0,y0,x1,y1 (or use a .json file)",
            ));
        }
        for (n, line) in lines {
            let cells: Vec<&str> = line.split(',').map(str::trim).collect();
            let parsed = (cells.len() == 5)
                .then(|| {
                    cells[1..]
                        .iter()
                        .map(|c| c.parse::<f64>().ok())
                        .collect::<Option<Vec<f64>>>()
                })
                .flatten()
                .and_then(|v| <[f64; 4]>::try_from(v).ok());
            let Some(b) = parsed else {
                return Err(Error::format(
                    path,
                    format!("line {}: expected image,x0,y0,x1,y1, got '{line}'", n + 1),
                ));
            };
            out.entry(cells[0].to_string()).or_default().push(b);
        }
    }
    Ok(out)
}

/// The names a `--boxes` key may give a photo: its path as given, its path relative to
/// the run's common folder, its file name.
fn box_keys(photo: &PhotoFile) -> [String; 3] {
    [
        photo.path.display().to_string(),
        photo.relative.display().to_string(),
        photo
            .path
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default(),
    ]
}

/// The boxes a `--boxes` file gives `photo` (by the path as given, its path under the
/// common folder, or its file name).
fn boxes_for<'a>(
    table: &'a HashMap<String, Vec<[f64; 4]>>,
    photo: &PhotoFile,
    single: bool,
) -> Option<&'a Vec<[f64; 4]>> {
    if let Some(b) = table.get("").filter(|_| single) {
        return Some(b);
    }
    box_keys(photo).iter().find_map(|k| table.get(k))
}

/// Checks that every key of a `--boxes` file names exactly one given photo (and that a
/// bare list of boxes is given with one photo): boxes meant for a photo that is not
/// there, or for two, are a mistake worth stopping for.
fn check_box_keys(
    file: &Path,
    table: &HashMap<String, Vec<[f64; 4]>>,
    photos: &[PhotoFile],
) -> Result<()> {
    if table.contains_key("") && photos.len() != 1 {
        return Err(Error::format(
            file,
            format!(
                "a bare list of boxes is for one photo, and {} were given: key the boxes by photo ({{\"PHOTO\": [[x0, y0, x1, y1], ...]}})",
                photos.len()
            ),
        ));
    }
    let keys: Vec<[String; 3]> = photos.iter().map(box_keys).collect();
    let mut unmatched: Vec<&str> = Vec::new();
    for key in table.keys().filter(|k| !k.is_empty()) {
        let matching: Vec<&PhotoFile> = photos
            .iter()
            .zip(&keys)
            .filter(|(_, names)| names.contains(key))
            .map(|(p, _)| p)
            .collect();
        match matching.len() {
            0 => unmatched.push(key),
            1 => {}
            _ => {
                return Err(Error::format(
                    file,
                    format!(
                        "'{key}' names {} photos ({}): key their boxes by path",
                        matching.len(),
                        matching
                            .iter()
                            .map(|p| p.path.display().to_string())
                            .collect::<Vec<_>>()
                            .join(", ")
                    ),
                ));
            }
        }
    }
    if !unmatched.is_empty() {
        unmatched.sort();
        return Err(Error::format(
            file,
            format!(
                "boxes for photos that were not given: {} (a key is a photo's path as given, its path under the folder given, or its file name)",
                unmatched.join(", ")
            ),
        ));
    }
    Ok(())
}

fn rt_rows(rt: &[f64; 16]) -> Value {
    json!([
        [rt[0], rt[1], rt[2], rt[3]],
        [rt[4], rt[5], rt[6], rt[7]],
        [rt[8], rt[9], rt[10], rt[11]],
        [rt[12], rt[13], rt[14], rt[15]]
    ])
}

/// A photo's boxes, their detector scores (`None` for a given box), and where they came
/// from (`--box`, `--boxes` or `detector`).
type PhotoBoxes = (Vec<[f64; 4]>, Vec<Option<f64>>, &'static str);

/// What every photo of a run shares.
struct Run<'a> {
    r: &'a ImageRequest<'a>,
    model: arkit_perspnet::TrainedModel,
    topology: arkit_data::mesh::FaceTopology,
    detect: DetectOptions,
    given: Vec<[f64; 4]>,
    table: Option<HashMap<String, Vec<[f64; 4]>>>,
    single: bool,
    names: [&'static str; 3],
}

/// One photo's part of the report: its JSON entry, its CSV rows, and whether it was
/// skipped.
struct PhotoOutcome {
    entry: Value,
    rows: Vec<Vec<String>>,
    skipped: bool,
    /// Skipped, and named on the command line: the run exits 1.
    refused: bool,
    faces: usize,
    posed: usize,
}

impl PhotoOutcome {
    fn skipped(photo: &PhotoFile, e: &Error) -> Self {
        let path = &photo.path;
        if photo.named {
            eprintln!("predict: refused {}: {e}", path.display());
        } else {
            eprintln!("predict: skipped {}: {e}", path.display());
        }
        PhotoOutcome {
            entry: json!({"path": path.display().to_string(), "error": e.to_string()}),
            rows: Vec::new(),
            skipped: true,
            refused: photo.named,
            faces: 0,
            posed: 0,
        }
    }
}

/// Runs `predict --image`.
pub fn run(r: ImageRequest<'_>) -> Result<ExitCode> {
    if r.focal_px.is_some() && r.fov_deg.is_some() {
        return Err(Error::invalid(
            "--focal-px/--fov-deg",
            "give the photo's camera once: a focal length in pixels or a horizontal field of view",
        ));
    }
    let photos = photo_files(r.images)?;
    let single = photos.len() == 1;
    if !r.boxes.is_empty() && !single {
        return Err(Error::invalid(
            "--box",
            format!(
                "boxes on the command line are for one photo; {} photos were given: use --boxes FILE",
                photos.len()
            ),
        ));
    }
    let given: Vec<[f64; 4]> = r
        .boxes
        .iter()
        .map(|s| parse_box(s))
        .collect::<Result<_>>()?;
    let table = r.boxes_file.map(read_boxes_file).transpose()?;
    if let (Some(file), Some(table)) = (r.boxes_file, &table) {
        check_box_keys(file, table, &photos)?;
    }
    let writes: Vec<&str> = [
        (r.draw.is_some() && !single, "--draw"),
        (r.dump_crops.is_some(), "--dump-crops"),
        (r.mesh.is_some(), "--mesh"),
    ]
    .iter()
    .filter(|(given, _)| *given)
    .map(|(_, flag)| *flag)
    .collect();
    if !writes.is_empty() {
        check_unique_outputs(&photos, &writes.join("/"))?;
    }
    if let Some(f) = r.focal_px {
        PhotoCamera::FocalPx(f).check()?;
    }
    if let Some(fov) = r.fov_deg {
        PhotoCamera::from_horizontal_fov(fov, 1)?;
    }
    let topology = super::setup::load_topology(r.resources)?;
    let model = arkit_perspnet::load(r.model, &topology)?;
    model.net.perspnet("predict --image")?;
    for dir in [r.dump_crops, r.draw.filter(|_| !single), r.mesh]
        .into_iter()
        .flatten()
    {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    let run = Run {
        r: &r,
        model,
        topology,
        detect: DetectOptions {
            min_face_px: r.min_face_px,
            score_threshold: r.detector_score,
        },
        given,
        table,
        single,
        names: r.angles.order(),
    };
    let bar = super::console::progress_bar(photos.len() as u64, "predict", "photos");
    let (mut entries, mut rows) = (Vec::new(), Vec::new());
    let (mut skipped, mut faces, mut posed) = (0usize, 0usize, 0usize);
    let mut refused = false;
    for (pi, photo) in photos.iter().enumerate() {
        bar.inc(1);
        let outcome = run.photo(pi, photo)?;
        skipped += outcome.skipped as usize;
        refused |= outcome.refused;
        faces += outcome.faces;
        posed += outcome.posed;
        entries.push(outcome.entry);
        rows.extend(outcome.rows);
    }
    bar.finish_and_clear();
    let unit = match r.angles.unit() {
        AngleUnit::Degrees => "deg",
        AngleUnit::Radians => "rad",
    };
    let report = json!({
        "model": r.model.display().to_string(),
        "angles": {"convention": r.angles.name(), "order": run.names, "unit": unit},
        "frame": "R_t: the release's (row vectors, OpenGL camera: x right, y up, looking down -z), metres; rvec/tvec_m: OpenCV's (x right, y down, looking down +z)",
        "photos": entries,
        "summary": {"photos": photos.len(), "skipped": skipped, "faces": faces, "posed": posed},
    });
    match r.output {
        Some(p) if p.extension().is_some_and(|x| x.eq_ignore_ascii_case("csv")) => {
            arkit_core::atomic_file::write_bytes(p, csv_text(&run.names, &rows).as_bytes())?;
        }
        Some(p) => {
            let text = serde_json::to_string_pretty(&report).expect("json");
            arkit_core::atomic_file::write_bytes(p, text.as_bytes())?;
        }
        None => {}
    }
    if r.json || r.output.is_none() {
        println!("{}", serde_json::to_string_pretty(&report).expect("json"));
    } else {
        println!(
            "{} photos ({} skipped): {} faces, {} posed -> {}",
            photos.len(),
            skipped,
            faces,
            posed,
            r.output
                .map(|p| p.display().to_string())
                .unwrap_or_default()
        );
    }
    // A photo named on the command line that could not be posed fails the run; one
    // found in a folder does only under --strict.
    Ok(if refused || (r.strict && skipped > 0) {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    })
}

/// The CSV table of the faces: a header, then one row per face.
fn csv_text(names: &[&str; 3], rows: &[Vec<String>]) -> String {
    let mut text = format!(
        "image,face,boxes_from,x0,y0,x1,y1,status,{},{},{},tx_m,ty_m,tz_m,inliers,distinct_points",
        names[0], names[1], names[2]
    );
    for i in 0..16 {
        text.push_str(&format!(",r_t_{}{}", i / 4, i % 4));
    }
    text.push('\n');
    for row in rows {
        let cells: Vec<String> = row
            .iter()
            .map(|c| {
                if c.contains([',', '"', '\n']) {
                    format!("\"{}\"", c.replace('"', "\"\""))
                } else {
                    c.clone()
                }
            })
            .collect();
        text.push_str(&cells.join(","));
        text.push('\n');
    }
    text
}

impl Run<'_> {
    /// The boxes of a photo: `--box`, its `--boxes` entry, or the detector's (with
    /// their scores), and where they came from.
    fn boxes(&self, photo: &image::RgbImage, file: &PhotoFile) -> Result<PhotoBoxes> {
        if !self.given.is_empty() {
            return Ok((self.given.clone(), vec![None; self.given.len()], "--box"));
        }
        if let Some(b) = self
            .table
            .as_ref()
            .and_then(|t| boxes_for(t, file, self.single))
        {
            return Ok((b.clone(), vec![None; b.len()], "--boxes"));
        }
        let found = detect_faces(photo, &self.detect)?;
        Ok((
            found.iter().map(|f| f.bbox).collect(),
            found.iter().map(|f| Some(f.score)).collect(),
            "detector",
        ))
    }

    /// Predicts one photo (the `pi`-th): an unreadable photo, or a bad box from a
    /// `--boxes` file, skips it; a bad `--box` or a model error stops the run.
    fn photo(&self, pi: usize, file: &PhotoFile) -> Result<PhotoOutcome> {
        let r = self.r;
        let path = file.path.as_path();
        // Upright first (its EXIF orientation applied): boxes, outputs and drawings are
        // in the pixels people see.
        let (photo, orientation) = match read_photo_upright(path) {
            Ok(p) => p,
            Err(e) => return Ok(PhotoOutcome::skipped(file, &e)),
        };
        let (w, h) = photo.dimensions();
        let camera = match (r.focal_px, r.fov_deg) {
            (Some(f), _) => PhotoCamera::FocalPx(f),
            (None, Some(fov)) => PhotoCamera::from_horizontal_fov(fov, w)?,
            (None, None) => PhotoCamera::Demo,
        };
        let square = DemoSquare::of(w, h, DEMO_SIDE);
        let (boxes, scores, source) = self.boxes(&photo, file)?;
        // A box given on the command line that does not fit the photo is a mistake in
        // the command; one in a --boxes file skips its photo only.
        if let Some(e) = boxes
            .iter()
            .find_map(|b| arkit_data::pose::check_box(*b, w, h).err())
        {
            if source == "--box" {
                return Err(e);
            }
            return Ok(PhotoOutcome::skipped(file, &e));
        }
        let faces = arkit_perspnet::predict_photo(
            &self.model,
            &photo,
            &boxes,
            &camera,
            r.seed ^ ((pi as u64) << 32),
            &r.ransac,
        )?;
        if faces.is_empty() {
            eprintln!(
                "predict: {}: no face found (the detector finds roughly frontal faces of at least {} px; give boxes with --box or --boxes)",
                path.display(),
                r.min_face_px
            );
        }
        let stem = file.stem().display().to_string();
        let mut drawn = r.draw.map(|_| photo.clone());
        let (mut entries, mut rows, mut posed) = (Vec::new(), Vec::new(), 0);
        for (fi, face) in faces.iter().enumerate() {
            let mut row = vec![
                path.display().to_string(),
                fi.to_string(),
                source.to_string(),
            ];
            row.extend(face.bbox.iter().map(|x| x.to_string()));
            let mut entry = json!({
                "face": fi,
                "box": face.bbox,
                "detector_score": scores[fi],
                "points": face.prediction.pixels.len(),
            });
            if let Some(dir) = r.dump_crops {
                let file = dir.join(format!("{stem}-face{fi}.png"));
                let mut png = Vec::new();
                face.crop_image
                    .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
                    .map_err(|e| Error::invalid("crop", e.to_string()))?;
                arkit_core::atomic_file::write_bytes(&file, &png)?;
                entry["crop"] = json!(file.display().to_string());
            }
            posed += face.pose.is_some() as usize;
            self.pose_fields(face, &camera, &square, &mut entry, &mut row, drawn.as_mut())?;
            if let (Some(dir), Some(fp)) = (r.mesh, &face.pose) {
                let files = self.write_mesh(
                    dir,
                    &format!("{stem}-face{fi}"),
                    path,
                    fi,
                    face,
                    fp,
                    &camera,
                    &square,
                )?;
                entry["mesh"] = files;
            }
            if let Some(img) = drawn.as_mut() {
                arkit_data::picture::draw_box(img, face.bbox, 2, image::Rgb([255, 200, 0]));
            }
            rows.push(row);
            entries.push(entry);
        }
        if let (Some(target), Some(img)) = (r.draw, drawn) {
            let file = if self.single {
                target.to_path_buf()
            } else {
                target.join(format!("{stem}.jpg"))
            };
            let bytes = arkit_data::picture::jpeg_bytes(&img, 90)?;
            arkit_core::atomic_file::write_bytes(&file, &bytes)?;
        }
        let k = camera.intrinsics(&square);
        let pixels = match camera {
            PhotoCamera::Demo => "the demo's 800-px square",
            PhotoCamera::FocalPx(_) => "the photo's",
        };
        Ok(PhotoOutcome {
            entry: json!({
                "path": path.display().to_string(),
                "width": w,
                "height": h,
                "exif_orientation": orientation,
                "boxes_from": source,
                "camera": {"fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy, "pixels": pixels},
                "faces": entries,
            }),
            rows,
            skipped: false,
            refused: false,
            faces: faces.len(),
            posed,
        })
    }

    /// A face's pose into its JSON entry and CSV row (empty cells when PnP failed), and
    /// its mesh onto the drawing.
    fn pose_fields(
        &self,
        face: &arkit_perspnet::PhotoFace,
        camera: &PhotoCamera,
        square: &DemoSquare,
        entry: &mut Value,
        row: &mut Vec<String>,
        drawn: Option<&mut image::RgbImage>,
    ) -> Result<()> {
        let Some(fp) = &face.pose else {
            entry["status"] = json!("pnp failed");
            row.push("pnp failed".into());
            row.extend(std::iter::repeat_n(String::new(), 3 + 3 + 2 + 16));
            return Ok(());
        };
        let names = self.names;
        let rt = fp.pose.to_release_rt();
        let a = self.r.angles.angles(&fp.pose);
        let t = fp.pose.translation_m();
        let (rvec, tvec) = fp.pose.to_opencv_rvec();
        entry["status"] = json!("ok");
        entry["R_t"] = rt_rows(&rt);
        entry["angles"] = json!({names[0]: a[0], names[1]: a[1], names[2]: a[2]});
        entry["translation_m"] = json!([t.x, t.y, t.z]);
        entry["rvec"] = json!([rvec.x, rvec.y, rvec.z]);
        entry["tvec_m"] = json!([tvec.x, tvec.y, tvec.z]);
        entry["inliers"] = json!(fp.inliers);
        entry["distinct_points"] = json!(fp.points);
        let canonical: Vec<nalgebra::Point3<f64>> = face
            .prediction
            .verts
            .chunks_exact(3)
            .map(|p| nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64))
            .collect();
        if self.r.vertices {
            let cam: Vec<[f64; 3]> = canonical
                .iter()
                .map(|p| {
                    let q = fp.pose.to_camera(p);
                    [q.x, q.y, q.z]
                })
                .collect();
            entry["vertices_m"] = json!(cam);
        }
        if let Some(img) = drawn {
            let (r_cv, t_cv) = fp.pose.to_opencv();
            let projected: Vec<Option<(f64, f64)>> = canonical
                .iter()
                .map(|p| camera.project_to_photo(square, &(r_cv * p + t_cv)))
                .collect();
            arkit_data::picture::draw_projected_mesh(
                img,
                &self.topology,
                &projected,
                &arkit_data::picture::MeshStyle::ANNOTATION,
            )?;
        }
        row.push("ok".to_string());
        row.extend(a.iter().map(|x| x.to_string()));
        row.extend([t.x, t.y, t.z].iter().map(|x| x.to_string()));
        row.extend([fp.inliers.to_string(), fp.points.to_string()]);
        row.extend(rt.iter().map(|x| x.to_string()));
        Ok(())
    }

    /// Writes a posed face's mesh (`NAME.obj`, `NAME.ply`) and landmarks
    /// (`NAME.landmarks.json`: camera-space points and photo pixels) into `dir`;
    /// returns the files' paths for the report.
    #[allow(clippy::too_many_arguments)]
    fn write_mesh(
        &self,
        dir: &Path,
        name: &str,
        photo: &Path,
        fi: usize,
        face: &arkit_perspnet::PhotoFace,
        fp: &arkit_data::pose::FacePose,
        camera: &PhotoCamera,
        square: &DemoSquare,
    ) -> Result<Value> {
        let canonical: Vec<nalgebra::Point3<f64>> = face
            .prediction
            .verts
            .chunks_exact(3)
            .map(|p| nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64))
            .collect();
        let mesh = arkit_data::mesh::FaceMesh::new(
            &self.topology,
            canonical.iter().map(|p| fp.pose.to_camera(p)).collect(),
        )?;
        let (r_cv, t_cv) = fp.pose.to_opencv();
        let pixels: Vec<Option<(f64, f64)>> = self
            .topology
            .landmarks
            .iter()
            .map(|&i| camera.project_to_photo(square, &(r_cv * canonical[i as usize] + t_cv)))
            .collect();
        let (obj, ply, marks) = (
            dir.join(format!("{name}.obj")),
            dir.join(format!("{name}.ply")),
            dir.join(format!("{name}.landmarks.json")),
        );
        mesh.write_obj(&obj)?;
        mesh.write_ply(&ply)?;
        let mut about = serde_json::Map::new();
        about.insert("photo".into(), json!(photo.display().to_string()));
        about.insert("face".into(), json!(fi));
        about.insert(
            "pixels_in".into(),
            json!("the upright photo's pixels (x right, y down), as --box takes them"),
        );
        mesh.write_landmarks(&marks, &pixels, about)?;
        Ok(json!({
            "obj": obj.display().to_string(),
            "ply": ply.display().to_string(),
            "landmarks": marks.display().to_string(),
        }))
    }
}
