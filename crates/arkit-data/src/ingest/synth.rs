//! The synthetic dataset generator behind `arkit-tool synth`.
//!
//! It writes a dataset in the release's download layout ([`arkit_core::release`]): for each
//! sample a JPEG of a shaded, textured face on a varied background and an `_info.npz`
//! whose `verts`, `R_t` and optional keys agree with each other and with the image
//! (the face in the image is the rasterized `verts` at `R_t` through the release camera),
//! plus the train and test list CSVs.
//!
//! Each subject has its own identity (shape coefficients, skin, brow and eye colours);
//! each image an expression, a pose drawn over the paper's ranges (yaw -78..77, pitch
//! -64..51, roll -90..63 degrees, distance 0.3..0.9 m) and a light. Every sample draws
//! from its own seeded stream ([`Rng::for_stream`]), so the output is byte-identical for
//! a seed whatever the number of threads.

use crate::mesh::synthetic_face::{EXPRESSION_DIMS, FaceShapeModel, IDENTITY_DIMS};
use crate::mesh::topology::{FaceTopology, HoleFill, LoopRole};
use crate::picture::encode::jpeg_bytes;
use arkit_core::NpzCompression;
use arkit_core::Rng;
use arkit_core::VisibilityBuffer;
use arkit_core::atomic_file;
use arkit_core::conventions::{Camera, EulerAngles, Pose};
use arkit_core::release::{self, InfoAnnotation, ReleaseLayout, SampleKey, Split};
use arkit_core::{Error, Result};
use image::{Rgb, RgbImage};
use nalgebra::{Point3, Vector3};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// The paper's pose ranges (degrees) and distances (metres).
pub mod ranges {
    /// Yaw range of ARKitFace, degrees.
    pub(crate) const YAW_DEG: (f64, f64) = (-78.0, 77.0);
    /// Pitch range, degrees.
    pub(crate) const PITCH_DEG: (f64, f64) = (-64.0, 51.0);
    /// Roll range, degrees.
    pub(crate) const ROLL_DEG: (f64, f64) = (-90.0, 63.0);
    /// Camera distance range, metres.
    pub(crate) const DISTANCE_M: (f64, f64) = (0.3, 0.9);
}

/// The facial actions the generator names its folders after, with the expression
/// (mouth open, smile, brows up, squint) each one shows.
pub(crate) const FACIAL_ACTIONS: [(&str, [f64; EXPRESSION_DIMS]); 6] = [
    ("01_Neutral", [0.0, 0.0, 0.0, 0.0]),
    ("02_Smile", [0.1, 1.0, 0.0, 0.3]),
    ("03_MouthOpen", [1.0, 0.0, 0.2, 0.0]),
    ("04_BrowsUp", [0.0, 0.0, 1.0, 0.0]),
    ("05_Squint", [0.0, 0.2, 0.0, 1.0]),
    ("09_LeftToRight_Frown", [0.2, 0.0, -0.6, 0.5]),
];

/// What to generate.
#[derive(Clone, Debug)]
pub struct SynthOptions {
    /// Number of subjects.
    pub subjects: usize,
    /// Images per subject.
    pub images_per_subject: usize,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// The seed; the same seed gives the same bytes.
    pub seed: u64,
    /// Fraction of subjects in the test split (at least one when there are two or more).
    pub test_fraction: f64,
    /// JPEG quality (1-100).
    pub jpeg_quality: u8,
}

impl Default for SynthOptions {
    fn default() -> Self {
        SynthOptions {
            subjects: 10,
            images_per_subject: 20,
            width: 800,
            height: 800,
            seed: 0,
            test_fraction: 0.2,
            jpeg_quality: 90,
        }
    }
}

impl SynthOptions {
    /// Checks the options.
    pub fn check(&self) -> Result<()> {
        if self.subjects == 0 || self.images_per_subject == 0 {
            return Err(Error::invalid(
                "synth options",
                "need at least one subject and one image per subject",
            ));
        }
        if self.width < 32 || self.height < 32 || self.width > 8192 || self.height > 8192 {
            return Err(Error::invalid(
                "--size",
                format!("{}x{} is outside 32..8192 pixels", self.width, self.height),
            ));
        }
        if !(0.0..=1.0).contains(&self.test_fraction) {
            return Err(Error::invalid("--test-fraction", "must be in [0, 1]"));
        }
        if !(1..=100).contains(&self.jpeg_quality) {
            return Err(Error::invalid("--jpeg-quality", "must be in 1..=100"));
        }
        Ok(())
    }
}

/// A face the generator can draw: its topology, neutral shape, hole fill, and where its
/// features are (from the neutral shape's landmarks).
#[derive(Clone, Debug)]
pub struct FaceSource {
    /// The topology.
    pub topology: FaceTopology,
    /// The shape model over the neutral face.
    pub shape: FaceShapeModel,
    /// Triangles closing the eyes and the mouth.
    pub hole_fill: HoleFill,
    features: Features,
}

#[derive(Clone, Debug)]
struct Features {
    eye_centres: [Point3<f32>; 2],
    eye_radius: f32,
    mouth_centre: Point3<f32>,
    mouth_half: (f32, f32),
    brows: Vec<Point3<f32>>,
    nose_tip: Point3<f32>,
}

impl FaceSource {
    /// The built-in synthetic face.
    pub fn builtin() -> Self {
        let face = crate::mesh::synthetic_face::builtin();
        Self::new(face.topology.clone()).expect("the built-in face has a template and 4 loops")
    }

    /// A face from a topology that has a template (for example the real one read with
    /// `--resources`, whose folder has `template_verts.npy`).
    pub fn new(topology: FaceTopology) -> Result<Self> {
        let neutral = topology.template.clone().ok_or_else(|| {
            Error::format(
                topology.source_path(),
                "no template face (template_verts.npy) to draw: synth needs one",
            )
        })?;
        let hole_fill = topology.hole_fill()?;
        let lm = |i: usize| neutral[topology.landmarks[i] as usize];
        let mean = |r: std::ops::Range<usize>| {
            let n = r.len() as f32;
            Point3::from(r.map(|i| lm(i).coords).sum::<Vector3<f32>>() / n)
        };
        let eye_centres = [mean(36..42), mean(42..48)];
        let eye_radius = 0.5 * (lm(39) - lm(36)).norm() * 0.42;
        let mouth_centre = mean(48..60);
        let mouth_half = (
            (lm(54).x - lm(48).x).abs() / 2.0 * 1.05,
            ((lm(51).y - lm(57).y).abs() / 2.0).max(0.006),
        );
        let features = Features {
            eye_centres,
            eye_radius,
            mouth_centre,
            mouth_half,
            brows: (17..27).map(lm).collect(),
            nose_tip: lm(30),
        };
        Ok(FaceSource {
            shape: FaceShapeModel::new(neutral),
            topology,
            hole_fill,
            features,
        })
    }
}

/// One planned sample.
#[derive(Clone, Debug)]
pub struct PlannedSample {
    /// Its key.
    pub key: SampleKey,
    /// Its split.
    pub split: Split,
    /// Subject number (0-based).
    pub subject: usize,
    /// Image number within the subject.
    pub image: usize,
}

/// Subject ids, splits and image ids of a run, in a fixed order.
pub fn plan(options: &SynthOptions) -> Vec<PlannedSample> {
    let mut rng = Rng::for_stream(options.seed, u64::MAX);
    let n_test = if options.subjects >= 2 {
        ((options.subjects as f64 * options.test_fraction).round() as usize)
            .clamp(1, options.subjects - 1)
    } else {
        0
    };
    // Subject ids with a leading zero, as strings: tools must not read them as numbers.
    let base = 10_000 + rng.below(80_000) as usize;
    let mut out = Vec::new();
    for s in 0..options.subjects {
        let subject_id = format!("0{:05}", base + 37 * s);
        let split = if s >= options.subjects - n_test {
            Split::Test
        } else {
            Split::Train
        };
        let t0 = 1_616_212_233_525u64 + rng.below(1_000_000_000);
        for i in 0..options.images_per_subject {
            let action = FACIAL_ACTIONS[i % FACIAL_ACTIONS.len()].0;
            out.push(PlannedSample {
                key: SampleKey {
                    subject_id: subject_id.clone(),
                    facial_action: action.to_string(),
                    img_id: (t0 + 33 * i as u64).to_string(),
                },
                split,
                subject: s,
                image: i,
            });
        }
    }
    out
}

/// A subject's look.
#[derive(Clone, Debug)]
struct Subject {
    identity: [f64; IDENTITY_DIMS],
    skin: [f32; 3],
    brow: [f32; 3],
    iris: [f32; 3],
    lips: [f32; 3],
    texture_seed: u64,
}

fn subject_look(seed: u64, subject: usize) -> Subject {
    let mut r = Rng::for_stream(seed, 1 << 40 | subject as u64);
    let mut identity = [0.0; IDENTITY_DIMS];
    for v in &mut identity {
        *v = r.normal().clamp(-2.5, 2.5);
    }
    let tone = r.uniform(0.0, 1.0) as f32;
    let skin = [0.95 - 0.55 * tone, 0.78 - 0.5 * tone, 0.68 - 0.45 * tone];
    let dark = r.uniform(0.05, 0.35) as f32;
    let brow = [dark * 1.1, dark * 0.8, dark * 0.6];
    let irises = [
        [0.35, 0.22, 0.1],
        [0.2, 0.35, 0.55],
        [0.25, 0.4, 0.25],
        [0.15, 0.1, 0.06],
    ];
    let iris = irises[r.below(4) as usize];
    let lips = [skin[0] * 0.85 + 0.1, skin[1] * 0.55, skin[2] * 0.6];
    Subject {
        identity,
        skin,
        brow,
        iris,
        lips,
        texture_seed: r.next_u64(),
    }
}

/// Draws a pose over the paper's ranges: mostly moderate angles, the extremes covered.
fn draw_angles(r: &mut Rng) -> EulerAngles {
    let mut draw = |(lo, hi): (f64, f64), sd: f64| {
        if r.next_f64() < 0.3 {
            r.uniform(lo, hi)
        } else {
            (r.normal() * sd).clamp(lo, hi)
        }
    };
    let yaw = draw(ranges::YAW_DEG, 30.0);
    let pitch = draw(ranges::PITCH_DEG, 18.0);
    let roll = draw(ranges::ROLL_DEG, 15.0);
    EulerAngles::new(yaw, pitch, roll)
}

/// Everything drawn for one sample.
#[derive(Clone, Debug)]
pub struct SyntheticSample {
    /// The image.
    pub image: RgbImage,
    /// Its annotation.
    pub info: InfoAnnotation,
}

/// Renders one planned sample.
pub fn render_sample(
    source: &FaceSource,
    options: &SynthOptions,
    planned: &PlannedSample,
) -> Result<SyntheticSample> {
    // The image size must be one the rasterizer takes (it panics beyond its limit).
    options.check()?;
    let subject = subject_look(options.seed, planned.subject);
    let mut r = Rng::for_stream(
        options.seed,
        (planned.subject as u64) << 20 | planned.image as u64,
    );
    let action = FACIAL_ACTIONS
        .iter()
        .find(|(n, _)| *n == planned.key.facial_action)
        .map(|(_, e)| *e)
        .unwrap_or([0.0; EXPRESSION_DIMS]);
    let mut expression = action;
    for v in &mut expression {
        *v = (*v + r.uniform(-0.15, 0.15)).clamp(-1.0, 1.2);
    }
    let verts = source.shape.shape(&subject.identity, &expression);
    let camera = Camera::release(options.width, options.height);
    let k = camera.pinhole();
    let verts64: Vec<Point3<f64>> = verts.iter().map(|p| p.cast()).collect();
    let landmarks: Vec<Point3<f64>> = source
        .topology
        .landmarks
        .iter()
        .map(|&i| verts64[i as usize])
        .collect();
    // Draw until every landmark and vertex lands inside the image (a few tries at most).
    let mut pose = None;
    for _ in 0..200 {
        let angles = draw_angles(&mut r);
        let distance = r.uniform(ranges::DISTANCE_M.0, ranges::DISTANCE_M.1);
        let u = r.uniform(0.3, 0.7) * options.width as f64;
        let v = r.uniform(0.3, 0.7) * options.height as f64;
        let t = Vector3::new(
            (u - k.cx) * distance / k.fx,
            -(v - k.cy) * distance / k.fy,
            -distance,
        );
        let candidate = Pose::from_euler(angles, t);
        let inside = |p: &arkit_core::conventions::ImagePoint| {
            p.u > 1.0
                && p.v > 1.0
                && p.u < options.width as f64 - 1.0
                && p.v < options.height as f64 - 1.0
                && p.depth_m > 0.05
        };
        if camera.project_all(&candidate, &verts64).iter().all(inside)
            && camera
                .project_all(&candidate, &landmarks)
                .iter()
                .all(inside)
        {
            pose = Some(candidate);
            break;
        }
    }
    let pose = pose.ok_or_else(|| {
        Error::invalid(
            "--size",
            format!(
                "no pose keeps the face inside a {}x{} image; use a larger size",
                options.width, options.height
            ),
        )
    })?;
    // The camera's pose in the world, as ARKit records it (any rigid map works).
    let cam_angle = r.uniform(-180.0, 180.0);
    let camera_transform = Pose::from_euler(
        EulerAngles::new(cam_angle, 0.0, 0.0),
        Vector3::new(
            r.uniform(-1.0, 1.0),
            r.uniform(0.0, 1.5),
            r.uniform(-1.0, 1.0),
        ),
    )
    .release_matrix();
    let light = Vector3::new(r.uniform(-0.6, 0.6), r.uniform(-0.2, 0.8), 1.0)
        .normalize()
        .cast::<f32>();
    let mut image = background(options.width, options.height, &mut r);
    draw_face(&mut image, source, &subject, &verts, &pose, &camera, &light);
    let info = InfoAnnotation::complete(verts, &pose, &camera, camera_transform);
    Ok(SyntheticSample { image, info })
}

fn lerp3(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

/// A background: a two-colour gradient with soft blobs and stripes.
fn background(width: u32, height: u32, r: &mut Rng) -> RgbImage {
    let c0 = [
        r.next_f64() as f32,
        r.next_f64() as f32,
        r.next_f64() as f32,
    ];
    let c1 = [
        r.next_f64() as f32,
        r.next_f64() as f32,
        r.next_f64() as f32,
    ];
    let angle = r.uniform(0.0, std::f64::consts::TAU) as f32;
    let (dx, dy) = (angle.cos(), angle.sin());
    let blobs: Vec<(f32, f32, f32, [f32; 3])> = (0..6)
        .map(|_| {
            (
                r.next_f64() as f32 * width as f32,
                r.next_f64() as f32 * height as f32,
                (0.05 + 0.2 * r.next_f64() as f32) * width.max(height) as f32,
                [
                    r.next_f64() as f32,
                    r.next_f64() as f32,
                    r.next_f64() as f32,
                ],
            )
        })
        .collect();
    let stripe = (r.uniform(8.0, 40.0) as f32, r.uniform(0.0, 0.08) as f32);
    let diag = (width as f32).hypot(height as f32);
    RgbImage::from_fn(width, height, |x, y| {
        let (fx, fy) = (x as f32 + 0.5, y as f32 + 0.5);
        let t = (((fx - width as f32 / 2.0) * dx + (fy - height as f32 / 2.0) * dy) / diag + 0.5)
            .clamp(0.0, 1.0);
        let mut c = lerp3(c0, c1, t);
        for &(bx, by, br, bc) in &blobs {
            let d2 = ((fx - bx).powi(2) + (fy - by).powi(2)) / (br * br);
            c = lerp3(c, bc, 0.5 * (-d2).exp());
        }
        let s = stripe.1 * ((fx * dy - fy * dx) / stripe.0).sin();
        Rgb(c.map(|v| ((v + s).clamp(0.0, 1.0) * 255.0).round() as u8))
    })
}

/// Smooth value noise in [0, 1] over a 3D point (metres), cell size `cell`.
fn value_noise(p: &Point3<f32>, cell: f32, seed: u64) -> f32 {
    let q = p.coords / cell;
    let base = q.map(|v| v.floor());
    let f = q - base;
    let s = f.map(|v| v * v * (3.0 - 2.0 * v));
    let hash = |x: i64, y: i64, z: i64| -> f32 {
        let mut h = seed
            ^ (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
            ^ (z as u64).wrapping_mul(0x1656_67B1_9E37_79F9);
        (arkit_core::splitmix64(&mut h) >> 40) as f32 / (1u64 << 24) as f32
    };
    let (bx, by, bz) = (base.x as i64, base.y as i64, base.z as i64);
    let mut acc = 0.0;
    for (dz, wz) in [(0, 1.0 - s.z), (1, s.z)] {
        for (dy, wy) in [(0, 1.0 - s.y), (1, s.y)] {
            for (dx, wx) in [(0, 1.0 - s.x), (1, s.x)] {
                acc += wx * wy * wz * hash(bx + dx, by + dy, bz + dz);
            }
        }
    }
    acc
}

/// Distance from `p` to the polyline through `pts`, in the x-y plane.
fn polyline_distance(p: &Point3<f32>, pts: &[Point3<f32>]) -> f32 {
    pts.windows(2)
        .map(|w| {
            let (a, b) = (w[0].xy(), w[1].xy());
            let ab = b - a;
            let t = ((p.xy() - a).dot(&ab) / ab.norm_squared()).clamp(0.0, 1.0);
            (p.xy() - (a + ab * t)).norm()
        })
        .fold(f32::INFINITY, f32::min)
}

/// Colour of the skin surface at neutral position `p`.
fn skin_albedo(source: &FaceSource, subject: &Subject, p: &Point3<f32>) -> [f32; 3] {
    let f = &source.features;
    let n = 0.85 + 0.3 * value_noise(p, 0.012, subject.texture_seed)
        - 0.08 * value_noise(p, 0.003, subject.texture_seed ^ 1);
    let mut c = subject.skin.map(|v| v * n);
    // Cheeks and nose tip a little redder.
    let blush = (-((p - f.nose_tip).norm() / 0.012).powi(2)).exp() * 0.25;
    c = lerp3(c, [c[0] * 1.1, c[1] * 0.8, c[2] * 0.8], blush);
    // Brows: two arcs split at the centre line.
    let (left, right) = f.brows.split_at(5);
    let d = polyline_distance(p, left).min(polyline_distance(p, right));
    if d < 0.0045 && (p.x.abs() > 0.008) {
        let t = (1.0 - d / 0.0045).min(1.0).powf(0.5)
            * (0.7 + 0.3 * value_noise(p, 0.002, subject.texture_seed ^ 2));
        c = lerp3(c, subject.brow, t);
    }
    // Lips.
    let (mx, my) = f.mouth_half;
    let lx = (p.x - f.mouth_centre.x) / mx;
    let ly = (p.y - f.mouth_centre.y) / (my * 1.15);
    let l = lx * lx + ly * ly;
    if l < 1.0 {
        c = lerp3(c, subject.lips, ((1.0 - l) * 4.0).min(1.0));
    }
    // Eyelid shadow around the eye openings.
    for e in &f.eye_centres {
        let d = ((p.x - e.x) / (f.eye_radius * 2.4)).powi(2)
            + ((p.y - e.y) / (f.eye_radius * 1.3)).powi(2);
        if d < 1.6 {
            c = c.map(|v| v * (0.75 + 0.25 * ((d - 0.6).max(0.0) / 1.0).min(1.0)));
        }
    }
    c
}

/// Colour inside an eye or the mouth opening at neutral position `p`.
fn opening_albedo(
    source: &FaceSource,
    subject: &Subject,
    role: LoopRole,
    p: &Point3<f32>,
) -> [f32; 3] {
    let f = &source.features;
    match role {
        LoopRole::Mouth => {
            let t = ((p.y - f.mouth_centre.y) / f.mouth_half.1.max(1e-3)).clamp(-1.0, 1.0);
            if t > 0.2 {
                [0.92, 0.9, 0.85]
            } else {
                [0.25, 0.06, 0.06]
            }
        }
        _ => {
            let e = if role == LoopRole::RightEye {
                f.eye_centres[0]
            } else {
                f.eye_centres[1]
            };
            let d = (p.xy() - e.xy()).norm() / f.eye_radius;
            if d < 0.45 {
                [0.03, 0.03, 0.03]
            } else if d < 1.0 {
                subject.iris
            } else {
                [0.93, 0.92, 0.9]
            }
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn draw_face(
    image: &mut RgbImage,
    source: &FaceSource,
    subject: &Subject,
    verts: &[Point3<f32>],
    pose: &Pose,
    camera: &Camera,
    light: &Vector3<f32>,
) {
    let topo = &source.topology;
    let nv = topo.vertex_count;
    // Mesh plus hole centroids; triangles plus the hole fans.
    let mut all = verts.to_vec();
    all.extend(source.hole_fill.centroid_positions(verts));
    let mut neutral = source.shape.neutral.clone();
    neutral.extend(source.hole_fill.centroid_positions(&source.shape.neutral));
    let mut triangles = topo.triangles.clone();
    triangles.extend_from_slice(&source.hole_fill.triangles);
    let screen = camera.project_to_screen(pose, &all);
    // Vertex normals in camera space (area-weighted).
    let rot = pose.rotation().cast::<f32>();
    let cam: Vec<Vector3<f32>> = all.iter().map(|p| rot * p.coords).collect();
    let mut normals = vec![Vector3::zeros(); all.len()];
    for t in &triangles {
        let (a, b, c) = (cam[t[0] as usize], cam[t[1] as usize], cam[t[2] as usize]);
        let n = (b - a).cross(&(c - a));
        for &i in t {
            normals[i as usize] += n;
        }
    }
    for n in &mut normals {
        *n = n.try_normalize(1e-12).unwrap_or(Vector3::z());
    }
    let (w, h) = (camera.width, camera.height);
    let mut vis = VisibilityBuffer::new(w, h);
    vis.rasterize_mesh(&screen, &triangles)
        .expect("indices checked by the topology");
    let hole_role = |tri: usize| -> Option<LoopRole> {
        if tri < topo.triangles.len() {
            return None;
        }
        let centroid = triangles[tri][2] as usize - nv;
        Some(source.hole_fill.centroids[centroid].0)
    };
    for y in 0..h {
        for x in 0..w {
            let idx = (y * w + x) as usize;
            let tri = vis.triangle[idx];
            if tri == u32::MAX {
                continue;
            }
            let t = triangles[tri as usize];
            let b = vis.bary[idx];
            let p = Point3::from(
                neutral[t[0] as usize].coords * b[0]
                    + neutral[t[1] as usize].coords * b[1]
                    + neutral[t[2] as usize].coords * b[2],
            );
            let n = (normals[t[0] as usize] * b[0]
                + normals[t[1] as usize] * b[1]
                + normals[t[2] as usize] * b[2])
                .normalize();
            let albedo = match hole_role(tri as usize) {
                None => skin_albedo(source, subject, &p),
                Some(role) => opening_albedo(source, subject, role, &p),
            };
            let diffuse = n.dot(light).max(0.0);
            let half = (light + Vector3::z()).normalize();
            let spec = 0.12 * n.dot(&half).max(0.0).powi(24);
            let shade = 0.32 + 0.68 * diffuse;
            let px = image.get_pixel_mut(x, y);
            *px = Rgb(albedo.map(|a| ((a * shade + spec).clamp(0.0, 1.0) * 255.0).round() as u8));
        }
    }
}

/// What a run wrote.
#[derive(Clone, Debug, serde::Serialize)]
pub struct SynthSummary {
    /// Output root.
    pub output: PathBuf,
    /// Number of subjects.
    pub subjects: usize,
    /// Samples in the train list.
    pub train_samples: usize,
    /// Samples in the test list.
    pub test_samples: usize,
    /// Image size.
    pub width: u32,
    /// Image size.
    pub height: u32,
    /// The seed.
    pub seed: u64,
    /// The topology used.
    pub topology: String,
}

/// Generates the dataset into `output`, calling `progress` once per finished sample.
pub fn generate(
    source: &FaceSource,
    options: &SynthOptions,
    output: &Path,
    progress: &(dyn Fn() + Sync),
) -> Result<SynthSummary> {
    options.check()?;
    let _lock = atomic_file::FolderLock::acquire(output, "synth", "synth")?;
    atomic_file::remove_stale_temporaries(output, true)?;
    let layout = ReleaseLayout::new(output);
    let samples = plan(options);
    samples.par_iter().try_for_each(|s| -> Result<()> {
        let sample = render_sample(source, options, s)?;
        atomic_file::write_bytes(
            &layout.image_path(s.split, &s.key),
            &jpeg_bytes(&sample.image, options.jpeg_quality)?,
        )?;
        release::write_info(
            &layout.info_path(s.split, &s.key),
            &sample.info,
            NpzCompression::Deflated,
        )?;
        progress();
        Ok(())
    })?;
    let mut counts = [0usize; 2];
    let lists: Vec<Vec<SampleKey>> = [Split::Train, Split::Test]
        .into_iter()
        .map(|split| {
            let keys: Vec<SampleKey> = samples
                .iter()
                .filter(|s| s.split == split)
                .map(|s| s.key.clone())
                .collect();
            counts[split as usize] = keys.len();
            keys
        })
        .collect();
    // Both lists at once: a release with a train list and no test list is never seen.
    release::write_lists(
        &layout.root,
        &[
            (Split::Train.name(), &lists[0]),
            (Split::Test.name(), &lists[1]),
        ],
    )?;
    Ok(SynthSummary {
        output: output.to_path_buf(),
        subjects: options.subjects,
        train_samples: counts[0],
        test_samples: counts[1],
        width: options.width,
        height: options.height,
        seed: options.seed,
        topology: source.topology.source.clone(),
    })
}

/// Draws the projected face outline, eye and mouth openings (green), a sparse set of
/// mesh edges (dark green) and the 68 landmarks (red) over an image, for a person to
/// check that annotation and image agree.
pub fn draw_overlay(
    image: &mut RgbImage,
    topology: &FaceTopology,
    info: &InfoAnnotation,
) -> Result<()> {
    let pts: Vec<Point3<f64>> = info.verts.iter().map(|p| p.cast()).collect();
    crate::picture::overlay::draw_mesh(
        image,
        topology,
        &pts,
        &info.pose()?,
        &crate::picture::overlay::MeshStyle::ANNOTATION,
    )
}

/// One face of a [`group_photo`].
#[derive(Clone, Debug)]
pub struct GroupFace {
    /// The box of its 68 landmarks `[x0, y0, x1, y1]` in the photo's pixels (the kind of
    /// box a face detector gives; the official demo's 0.75 rule widens it).
    pub bbox: [f64; 4],
    /// Its pose, in the release's convention, in the photo's camera.
    pub pose: Pose,
    /// Its canonical vertices (metres).
    pub verts: Vec<Point3<f32>>,
}

/// A synthetic group photo: several subjects at several distances, side by side, in
/// one camera with square pixels.
#[derive(Clone, Debug)]
pub struct GroupPhoto {
    /// The photo.
    pub image: RgbImage,
    /// The focal length, pixels: `1.57443701 x max(W, H) / 2`, principal point at the
    /// centre. Padded to a square and resized to 800 px as the official demo does, this
    /// is the demo's camera exactly (when `max - min` of the sides is even).
    pub focal_px: f64,
    /// The faces, left to right.
    pub faces: Vec<GroupFace>,
}

/// Renders a group photo of `faces` subjects (1..=8) of `options.seed` side by side on a
/// `options.width x options.height` picture, nearer and farther (so of different
/// sizes), each posed within moderate angles (|yaw| <= 35, |pitch| <= 20, |roll| <= 15
/// degrees) and kept inside its own column, so that no two faces overlap.
pub fn group_photo(
    source: &FaceSource,
    options: &SynthOptions,
    faces: usize,
) -> Result<GroupPhoto> {
    options.check()?;
    if !(1..=8).contains(&faces) {
        return Err(Error::invalid(
            "--faces",
            format!("{faces}: a group photo has 1 to 8 faces"),
        ));
    }
    let (w, h) = (options.width, options.height);
    let long = w.max(h) as f64;
    let f = Camera::RELEASE_FOCAL_NDC * long / 2.0;
    let mut projection = Camera::release_projection();
    projection[(0, 0)] = 2.0 * f / w as f64;
    projection[(1, 1)] = 2.0 * f / h as f64;
    let camera = Camera::new(projection, w, h)?;
    let k = camera.pinhole();
    let mut r = Rng::for_stream(options.seed, 1 << 41);
    let mut image = background(w, h, &mut r);
    let column = w as f64 / faces as f64;
    let light = Vector3::new(0.3, 0.4, 1.0).normalize().cast::<f32>();
    let mut out = Vec::with_capacity(faces);
    for c in 0..faces {
        let subject = subject_look(options.seed, c);
        let expression = FACIAL_ACTIONS[c % FACIAL_ACTIONS.len()].1;
        let verts = source.shape.shape(&subject.identity, &expression);
        let verts64: Vec<Point3<f64>> = verts.iter().map(|p| p.cast()).collect();
        // Sizes from about a third of the column to most of it, in turn.
        let fill = if faces == 1 {
            0.6
        } else {
            0.35 + 0.5 * ((c * 5) % faces) as f64 / (faces - 1) as f64
        };
        let (x_lo, x_hi) = (c as f64 * column + 2.0, (c + 1) as f64 * column - 2.0);
        let mut placed = None;
        for _ in 0..400 {
            let angles = EulerAngles::new(
                r.uniform(-35.0, 35.0),
                r.uniform(-20.0, 20.0),
                r.uniform(-15.0, 15.0),
            );
            // A face is about 0.16 m across: the distance that makes it `fill` of the column.
            let distance = (f * 0.16 / (fill * column.min(h as f64))).max(0.15);
            let u = (c as f64 + r.uniform(0.4, 0.6)) * column;
            let v = r.uniform(0.35, 0.65) * h as f64;
            let t = Vector3::new(
                (u - k.cx) * distance / k.fx,
                -(v - k.cy) * distance / k.fy,
                -distance,
            );
            let pose = Pose::from_euler(angles, t);
            let p = camera.project_all(&pose, &verts64);
            let inside = p.iter().all(|q| {
                q.u > x_lo && q.u < x_hi && q.v > 2.0 && q.v < h as f64 - 2.0 && q.depth_m > 0.05
            });
            if inside {
                placed = Some((pose, p));
                break;
            }
        }
        let Some((pose, projected)) = placed else {
            return Err(Error::invalid(
                "--size",
                format!(
                    "{faces} faces do not fit side by side in a {w}x{h} photo; use a wider one"
                ),
            ));
        };
        draw_face(&mut image, source, &subject, &verts, &pose, &camera, &light);
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for &l in &source.topology.landmarks {
            let q = &projected[l as usize];
            x0 = x0.min(q.u);
            y0 = y0.min(q.v);
            x1 = x1.max(q.u);
            y1 = y1.max(q.v);
        }
        out.push(GroupFace {
            bbox: [x0, y0, x1, y1],
            pose,
            verts,
        });
    }
    Ok(GroupPhoto {
        image,
        focal_px: f,
        faces: out,
    })
}

/// A frame of a synthetic video: the picture, the focal length (pixels) and each
/// face's landmark box (`None` when it is not wholly in the picture).
pub type VideoFrame = (RgbImage, f64, Vec<Option<[f64; 4]>>);

/// One frame of a synthetic video (`synth --video`): the faces of `faces` (each a
/// subject index and its pose in the release's camera frame) drawn in order (a later
/// face covers an earlier one) on the background of `seed`, in a `width x height`
/// camera with the focal length of [`group_photo`] (`1.57443701 x max(W, H) / 2` px,
/// principal point at the centre). Gives the picture, the focal length and each face's
/// landmark box (`None` when a vertex is behind the camera or a landmark leaves the
/// picture).
pub fn video_frame(
    source: &FaceSource,
    seed: u64,
    width: u32,
    height: u32,
    faces: &[(usize, Pose)],
) -> Result<VideoFrame> {
    let long = width.max(height) as f64;
    let f = Camera::RELEASE_FOCAL_NDC * long / 2.0;
    let mut projection = Camera::release_projection();
    projection[(0, 0)] = 2.0 * f / width as f64;
    projection[(1, 1)] = 2.0 * f / height as f64;
    let camera = Camera::new(projection, width, height)?;
    let mut r = Rng::for_stream(seed, 1 << 42);
    let mut image = background(width, height, &mut r);
    let light = Vector3::new(0.3, 0.4, 1.0).normalize().cast::<f32>();
    let mut boxes = Vec::with_capacity(faces.len());
    for (k, (subject_index, pose)) in faces.iter().enumerate() {
        let subject = subject_look(seed, *subject_index);
        let expression = FACIAL_ACTIONS[k % FACIAL_ACTIONS.len()].1;
        let verts = source.shape.shape(&subject.identity, &expression);
        let verts64: Vec<Point3<f64>> = verts.iter().map(|p| p.cast()).collect();
        let projected = camera.project_all(pose, &verts64);
        if projected.iter().any(|q| q.depth_m <= 0.05) {
            boxes.push(None);
            continue;
        }
        draw_face(&mut image, source, &subject, &verts, pose, &camera, &light);
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for &l in &source.topology.landmarks {
            let q = &projected[l as usize];
            x0 = x0.min(q.u);
            y0 = y0.min(q.v);
            x1 = x1.max(q.u);
            y1 = y1.max(q.v);
        }
        let inside = x0 >= 0.0 && y0 >= 0.0 && x1 <= width as f64 && y1 <= height as f64;
        boxes.push(inside.then_some([x0, y0, x1, y1]));
    }
    Ok((image, f, boxes))
}
