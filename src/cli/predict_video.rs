//! `arkit-tool predict --video`: head poses along a video, by face track, smoothed
//! (docs/video.md).

use arkit_core::conventions::{AngleConvention, Pose};
use arkit_core::{Error, Result};
use arkit_data::picture::{DEMO_SIDE, DemoSquare, DetectOptions, detect_faces};
use arkit_data::pose::{PhotoCamera, RansacParams};
use arkit_data::video::{
    FrameRow, Mp4Encoder, OneEuroParams, PoseFilter, RowPose, RowWriter, Tracker, TrackerOptions,
    VideoSource,
};
use serde_json::json;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// What `predict --video` was asked.
pub struct VideoRequest<'a> {
    pub video: &'a Path,
    pub model: &'a Path,
    pub resources: Option<&'a Path>,
    pub boxes_file: Option<&'a Path>,
    pub fps: f64,
    pub detect_every: u32,
    pub tracker: TrackerOptions,
    pub smooth: Option<OneEuroParams>,
    pub min_face_px: u32,
    pub detector_score: f64,
    pub focal_px: Option<f64>,
    pub fov_deg: Option<f64>,
    pub angles: AngleConvention,
    pub draw: Option<&'a Path>,
    pub mesh: Option<&'a Path>,
    pub mesh_every: u32,
    pub output: Option<&'a Path>,
    pub seed: u64,
    pub ransac: RansacParams,
    pub strict: bool,
    pub json: bool,
}

/// Face boxes by frame from a `--boxes` JSON-lines file: `{"frame": N, "boxes":
/// [[x0, y0, x1, y1], ...]}` a line (what `synth --video` writes beside its clip).
fn read_frame_boxes(path: &Path) -> Result<HashMap<u64, Vec<[f64; 4]>>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let mut out = HashMap::new();
    for (n, line) in text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
    {
        let bad = |why: &str| {
            Error::format(
                path,
                format!(
                    "line {}: {why}; with --video a boxes file has a JSON object a line, {{\"frame\": N, \"boxes\": [[x0, y0, x1, y1], ...]}}",
                    n + 1
                ),
            )
        };
        let v: serde_json::Value =
            serde_json::from_str(line).map_err(|e| bad(&format!("not JSON ({e})")))?;
        let frame = v["frame"].as_u64().ok_or_else(|| bad("no frame number"))?;
        let boxes = v["boxes"]
            .as_array()
            .ok_or_else(|| bad("no list of boxes"))?
            .iter()
            .map(|b| {
                b.as_array()
                    .and_then(|a| a.iter().map(|x| x.as_f64()).collect::<Option<Vec<f64>>>())
                    .and_then(|a| <[f64; 4]>::try_from(a).ok())
                    .ok_or_else(|| bad(&format!("{b} is not [x0, y0, x1, y1]")))
            })
            .collect::<Result<Vec<[f64; 4]>>>()?;
        if out.insert(frame, boxes).is_some() {
            return Err(bad(&format!("frame {frame} is listed twice")));
        }
    }
    Ok(out)
}

/// A box clipped to a `w x h` frame, or `None` when too little of it is left.
fn clip_box(b: [f64; 4], w: u32, h: u32) -> Option<[f64; 4]> {
    let c = [
        b[0].clamp(0.0, w as f64),
        b[1].clamp(0.0, h as f64),
        b[2].clamp(0.0, w as f64),
        b[3].clamp(0.0, h as f64),
    ];
    (c[2] - c[0] >= 8.0 && c[3] - c[1] >= 8.0).then_some(c)
}

/// A colour per track, for `--draw`.
fn track_colour(track: u64) -> image::Rgb<u8> {
    const COLOURS: [[u8; 3]; 6] = [
        [255, 200, 0],
        [0, 200, 255],
        [255, 80, 200],
        [120, 255, 80],
        [255, 120, 40],
        [160, 120, 255],
    ];
    image::Rgb(COLOURS[(track % COLOURS.len() as u64) as usize])
}

/// Where `--draw` frames go: an MP4, or a folder of JPEGs (published when complete).
enum DrawTarget {
    Mp4(Box<Mp4Encoder>),
    Folder {
        tmp: arkit_core::atomic_file::TemporaryDir,
        path: PathBuf,
    },
}

impl DrawTarget {
    fn create(path: &Path, fps: f64) -> Result<Self> {
        let is_mp4 = path
            .extension()
            .is_some_and(|x| x.eq_ignore_ascii_case("mp4"));
        if is_mp4 {
            return Ok(DrawTarget::Mp4(Box::new(Mp4Encoder::create(path, fps)?)));
        }
        if path.extension().is_some() {
            return Err(Error::invalid(
                "--draw",
                format!(
                    "{}: with --video, --draw writes an .mp4 or a folder of frames (a path with no extension)",
                    path.display()
                ),
            ));
        }
        let tmp = arkit_core::atomic_file::TemporaryDir::create(path)?;
        Ok(DrawTarget::Folder {
            tmp,
            path: path.to_path_buf(),
        })
    }

    fn push(&mut self, index: u64, image: &image::RgbImage) -> Result<()> {
        match self {
            DrawTarget::Mp4(m) => m.push(image),
            DrawTarget::Folder { tmp, path } => {
                let bytes = arkit_data::picture::jpeg_bytes(image, 90)?;
                let file = tmp.path().join(format!("frame-{index:06}.jpg"));
                std::fs::write(&file, bytes)
                    .map_err(|e| Error::io(path.join(file.file_name().expect("named")), e))
            }
        }
    }

    fn finish(self) -> Result<()> {
        match self {
            DrawTarget::Mp4(m) => m.finish(),
            DrawTarget::Folder { tmp, path } => arkit_core::atomic_file::publish_dir(tmp, &path),
        }
    }
}

/// A track's span, for the summary.
#[derive(Default)]
struct TrackSpan {
    first: u64,
    last: u64,
    frames: u64,
    posed: u64,
}

/// Runs `predict --video`.
pub fn run(r: VideoRequest<'_>) -> Result<ExitCode> {
    if r.focal_px.is_some() && r.fov_deg.is_some() {
        return Err(Error::invalid(
            "--focal-px/--fov-deg",
            "give the camera once: a focal length in pixels or a horizontal field of view",
        ));
    }
    if r.detect_every == 0 {
        return Err(Error::invalid("--detect-every", "must be at least 1"));
    }
    if let Some(p) = &r.smooth {
        p.check()?;
    }
    let boxes = r.boxes_file.map(read_frame_boxes).transpose()?;
    let mut source = VideoSource::open(r.video, r.fps)?;
    if let (Some(table), Some(path)) = (&boxes, r.boxes_file)
        && let Some(f) = table.keys().filter(|&&f| f >= source.frame_count()).min()
    {
        return Err(Error::format(
            path,
            format!(
                "has boxes for frame {f}, but {} has {} frames (0 to {})",
                r.video.display(),
                source.frame_count(),
                source.frame_count().saturating_sub(1)
            ),
        ));
    }
    let topology = super::setup::load_topology(r.resources)?;
    let model = arkit_perspnet::load(r.model, &topology)?;
    model.net.perspnet("predict --video")?;
    if let Some(dir) = r.mesh {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    let names = r.angles.order();
    let mut rows = r.output.map(|p| RowWriter::create(p, names)).transpose()?;
    let mut draw = r
        .draw
        .map(|p| DrawTarget::create(p, source.fps()))
        .transpose()?;
    let mut meshes = 0u64;
    let detect = DetectOptions {
        min_face_px: r.min_face_px,
        score_threshold: r.detector_score,
    };
    let mut tracker = Tracker::new(r.tracker);
    let mut filters: HashMap<u64, PoseFilter> = HashMap::new();
    let mut spans: BTreeMap<u64, TrackSpan> = BTreeMap::new();
    let bar = super::console::progress_bar(source.frame_count(), "predict", "frames");
    let started = std::time::Instant::now();
    let (mut frames, mut faces, mut posed) = (0u64, 0u64, 0u64);
    let mut stdout_rows = Vec::new();
    while let Some(frame) = source.next_frame()? {
        bar.inc(1);
        frames += 1;
        let (w, h) = frame.image.dimensions();
        let tracked = if frame.index % r.detect_every as u64 == 0 {
            let found: Vec<[f64; 4]> = match &boxes {
                Some(table) => table.get(&frame.index).cloned().unwrap_or_default(),
                None => detect_faces(&frame.image, &detect)?
                    .iter()
                    .map(|f| f.bbox)
                    .collect(),
            };
            let found: Vec<[f64; 4]> = found
                .into_iter()
                .filter_map(|b| clip_box(b, w, h))
                .collect();
            tracker.detected(&found)
        } else {
            tracker.carried()
        };
        let tracked: Vec<_> = tracked
            .into_iter()
            .filter_map(|t| clip_box(t.bbox, w, h).map(|b| (t, b)))
            .collect();
        let camera = match (r.focal_px, r.fov_deg) {
            (Some(f), _) => PhotoCamera::FocalPx(f),
            (None, Some(fov)) => PhotoCamera::from_horizontal_fov(fov, w)?,
            (None, None) => PhotoCamera::Demo,
        };
        let square = DemoSquare::of(w, h, DEMO_SIDE);
        let boxes_now: Vec<[f64; 4]> = tracked.iter().map(|(_, b)| *b).collect();
        let predicted = arkit_perspnet::predict_photo(
            &model,
            &frame.image,
            &boxes_now,
            &camera,
            r.seed ^ (frame.index << 32),
            &r.ransac,
        )?;
        let mut drawn = draw.as_ref().map(|_| frame.image.clone());
        for ((t, bbox), face) in tracked.iter().zip(&predicted) {
            faces += 1;
            let span = spans.entry(t.track).or_insert(TrackSpan {
                first: frame.index,
                ..TrackSpan::default()
            });
            span.last = frame.index;
            span.frames += 1;
            let pose = face.pose.as_ref().map(|fp| {
                let raw = fp.pose;
                let smoothed = match &r.smooth {
                    Some(p) => filters
                        .entry(t.track)
                        .or_insert_with(|| PoseFilter::new(*p))
                        .filter(frame.time_s, &raw),
                    None => raw,
                };
                (raw, smoothed, fp.inliers, fp.points)
            });
            if let Some(img) = drawn.as_mut() {
                if let Some((_, smoothed, _, _)) = &pose {
                    draw_mesh(
                        img,
                        &topology,
                        &face.prediction.verts,
                        smoothed,
                        &camera,
                        &square,
                    )?;
                }
                arkit_data::picture::draw_box(img, *bbox, 2, track_colour(t.track));
            }
            if let (Some(dir), Some((_, smoothed, _, _))) = (r.mesh, &pose)
                && frame.index % r.mesh_every as u64 == 0
            {
                let at = MeshFrame {
                    video: r.video,
                    frame: frame.index,
                    time_s: frame.time_s,
                    track: t.track,
                    smoothed: r.smooth.is_some(),
                };
                write_mesh(
                    dir,
                    &at,
                    &topology,
                    &face.prediction.verts,
                    smoothed,
                    &camera,
                    &square,
                )?;
                meshes += 1;
            }
            let row = FrameRow {
                frame: frame.index,
                time_s: frame.time_s,
                track: t.track,
                detected: t.detected,
                bbox: *bbox,
                pose: pose.map(|(raw, smoothed, inliers, points)| {
                    posed += 1;
                    span.posed += 1;
                    row_pose(&raw, &smoothed, r.angles, inliers, points)
                }),
            };
            match rows.as_mut() {
                Some(w) => w.push(&row)?,
                None => stdout_rows.push(arkit_data::video::json_row(&row, &names)),
            }
        }
        if let (Some(d), Some(img)) = (draw.as_mut(), drawn) {
            d.push(frame.index, &img)?;
        }
    }
    bar.finish_and_clear();
    let seconds = started.elapsed().as_secs_f64();
    if let Some(w) = rows {
        w.finish()?;
    }
    if let Some(d) = draw {
        d.finish()?;
    }
    let summary = json!({
        "video": r.video.display().to_string(),
        "source": source.describe(),
        "frames": frames,
        "faces": faces,
        "posed": posed,
        "frames_per_second": if seconds > 0.0 { frames as f64 / seconds } else { 0.0 },
        "max_frames_held": source.max_frames_held(),
        "skipped": source.skipped().iter().map(|(what, why)| json!({"frame": what, "error": why})).collect::<Vec<_>>(),
        "peak_rss_mb": peak_rss_mb(),
        "detect_every": r.detect_every,
        "smoothing": r.smooth,
        "meshes": r.mesh.map(|d| json!({"folder": d.display().to_string(), "faces": meshes})),
        "tracks": spans.iter().map(|(id, s)| json!({
            "track": id, "first_frame": s.first, "last_frame": s.last,
            "frames": s.frames, "posed": s.posed,
        })).collect::<Vec<_>>(),
    });
    if r.output.is_none() {
        for row in &stdout_rows {
            println!("{row}");
        }
    } else if r.json {
        println!("{}", serde_json::to_string_pretty(&summary).expect("json"));
    } else {
        println!(
            "{} frames ({}): {} faces in {} tracks, {} posed, {:.1} frames/s -> {}",
            frames,
            source.describe(),
            faces,
            spans.len(),
            posed,
            summary["frames_per_second"].as_f64().unwrap_or(0.0),
            r.output
                .map(|p| p.display().to_string())
                .unwrap_or_default()
        );
    }
    for (what, why) in source.skipped() {
        eprintln!("predict: skipped {what}: {why}");
    }
    if frames == 0 {
        eprintln!("predict: {}: no frame could be read", r.video.display());
        return Ok(ExitCode::FAILURE);
    }
    Ok(if r.strict && !source.skipped().is_empty() {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    })
}

/// The process's peak resident memory, MB (Linux's VmHWM; `None` elsewhere).
fn peak_rss_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

fn row_pose(
    raw: &Pose,
    smoothed: &Pose,
    angles: AngleConvention,
    inliers: usize,
    points: usize,
) -> RowPose {
    let t = smoothed.translation_m();
    let (rvec, tvec) = smoothed.to_opencv_rvec();
    RowPose {
        r_t: smoothed.to_release_rt(),
        angles: angles.angles(smoothed),
        translation_m: [t.x, t.y, t.z],
        rvec: [rvec.x, rvec.y, rvec.z],
        tvec_m: [tvec.x, tvec.y, tvec.z],
        raw_angles: angles.angles(raw),
        inliers,
        points,
    }
}

/// Where a `--mesh` file's face is in the video.
struct MeshFrame<'a> {
    video: &'a Path,
    frame: u64,
    time_s: f64,
    track: u64,
    smoothed: bool,
}

/// The file stem of a face's `--mesh` files: `frame-NNNNNN-track-K` (the frame index
/// as `--draw`'s frames number it).
fn mesh_stem(frame: u64, track: u64) -> String {
    format!("frame-{frame:06}-track-{track}")
}

/// The pinhole, in the frame's own pixels, equivalent to `camera` on a frame whose
/// demo square is `square`: `[fx, fy, cx, cy]` (OpenCV's frame: x right, y down, z
/// forward). The demo's camera lives in the 800-px square; the square's pixel `u` is
/// the frame's `u / scale - pad`, a map linear in `u`, so the pinhole scales with it.
fn frame_pinhole(camera: &PhotoCamera, square: &DemoSquare) -> [f64; 4] {
    let k = camera.intrinsics(square);
    match camera {
        PhotoCamera::Demo => {
            let s = square.scale();
            [
                k.fx / s,
                k.fy / s,
                k.cx / s - square.pad_left as f64,
                k.cy / s - square.pad_top as f64,
            ]
        }
        PhotoCamera::FocalPx(_) => [k.fx, k.fy, k.cx, k.cy],
    }
}

/// Writes one face's mesh at `pose` (its predicted canonical vertices `verts` posed in
/// camera space) as `DIR/frame-NNNNNN-track-K.obj`, `.ply` and `.landmarks.json`
/// (camera-space points, the frame's pixels, the frame's pinhole), each atomically.
fn write_mesh(
    dir: &Path,
    at: &MeshFrame<'_>,
    topology: &arkit_data::mesh::FaceTopology,
    verts: &[f32],
    pose: &Pose,
    camera: &PhotoCamera,
    square: &DemoSquare,
) -> Result<()> {
    let canonical: Vec<nalgebra::Point3<f64>> = verts
        .chunks_exact(3)
        .map(|p| nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64))
        .collect();
    let mesh = arkit_data::mesh::FaceMesh::new(
        topology,
        canonical.iter().map(|p| pose.to_camera(p)).collect(),
    )?;
    let (r_cv, t_cv) = pose.to_opencv();
    let pixels: Vec<Option<(f64, f64)>> = topology
        .landmarks
        .iter()
        .map(|&i| camera.project_to_photo(square, &(r_cv * canonical[i as usize] + t_cv)))
        .collect();
    let stem = mesh_stem(at.frame, at.track);
    mesh.write_obj(&dir.join(format!("{stem}.obj")))?;
    mesh.write_ply(&dir.join(format!("{stem}.ply")))?;
    let [fx, fy, cx, cy] = frame_pinhole(camera, square);
    let mut about = serde_json::Map::new();
    about.insert("video".into(), json!(at.video.display().to_string()));
    about.insert("frame_index".into(), json!(at.frame));
    about.insert("time_s".into(), json!(at.time_s));
    about.insert("track".into(), json!(at.track));
    about.insert(
        "pose".into(),
        json!(if at.smoothed { "smoothed" } else { "raw" }),
    );
    about.insert(
        "pixels_in".into(),
        json!("the frame's pixels (x right, y down), as the rows' boxes"),
    );
    about.insert(
        "camera".into(),
        json!({"fx": fx, "fy": fy, "cx": cx, "cy": cy,
               "width": square.width, "height": square.height,
               "axes": "OpenCV's: x right, y down, z forward (the points' (x, -y, -z))"}),
    );
    mesh.write_landmarks(&dir.join(format!("{stem}.landmarks.json")), &pixels, about)
}

fn draw_mesh(
    img: &mut image::RgbImage,
    topology: &arkit_data::mesh::FaceTopology,
    verts: &[f32],
    pose: &Pose,
    camera: &PhotoCamera,
    square: &DemoSquare,
) -> Result<()> {
    let (r_cv, t_cv) = pose.to_opencv();
    let projected: Vec<Option<(f64, f64)>> = verts
        .chunks_exact(3)
        .map(|p| {
            let p = nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            camera.project_to_photo(square, &(r_cv * p + t_cv))
        })
        .collect();
    arkit_data::picture::draw_projected_mesh(
        img,
        topology,
        &projected,
        &arkit_data::picture::MeshStyle::ANNOTATION,
    )
}
