//! Face profiling (out-of-plane rotation through the mesh), roll and mirroring of one
//! sample: the image and its annotation change together.
//!
//! # Profiling (yaw, pitch), after Zhu et al. (CVPR 2016) and the official code
//! 1. **Setup**: project the mesh with the old pose; the face contour is the convex hull
//!    of the projected vertices. Four rings of contour points are made by scaling the
//!    contour vertices' camera-space x and y about the nose tip (landmark 30) by 1.05,
//!    1.1, 1.15 and 1.2, keeping each contour vertex's depth, and are lifted back to the
//!    canonical frame so they turn with the face.
//! 2. **Anchors**: 40 points on a box around the 68 landmarks (half-sizes 1.125, 1.125,
//!    1.275, 0.975 of their larger side to the left, right, top, bottom, clamped to the
//!    image) and 20 on the image border. They stay fixed in the image. Unlike the
//!    official code (whose box turns with the face and whose output starts black), the
//!    fixed border keeps the background: everything outside the box is left exactly as
//!    it was.
//! 3. **Triangulation**: the contour, the rings and the anchors are triangulated in the
//!    source image by 2D Delaunay (`spade`). Each of these triangles is warped affinely
//!    from its source to its destination positions (the rings and contour move with the
//!    new pose, the anchors do not): the *band* layer.
//! 4. **Face layer**: the mesh triangles and the triangles filling the eyes and the
//!    mouth are rasterized at the new pose with the depth test ([`arkit_core::VisibilityBuffer`]); each
//!    covered pixel's perspective-correct barycentrics give the canonical surface point,
//!    which is projected with the *old* pose to find where to read the source image.
//!    This texture lookup is exact (no per-triangle affine approximation).
//! 5. **Output**: each pixel reads the source image (bilinear, pixel centres at
//!    `+0.5`) at the face layer's source point where the face covers it, else the band
//!    layer's; pixels outside both keep their value.
//!
//! The new pose changes one Euler angle ('yxz', see [`arkit_core::conventions::EulerAngles`]) and
//! keeps the others and the translation, so the new Euler angles equal the request
//! exactly. A surface hidden in the source (the far cheek) that turns into view shows
//! whatever covered it; that is why yaw is enlarged only for faces already turned away.
//!
//! # Roll
//! The scene turns about the camera's optical axis: the image rotates exactly about the
//! principal point (the image centre for the release camera), the background with it,
//! and `R' = R_z(d) R`, `t' = R_z(d) t`, so only the Euler roll changes, by exactly `d`.
//! (Turning about the projected head centre instead, as the official code does, is not
//! a rigid motion of the scene: its pose update is approximate.)
//!
//! # Mirror
//! The image is mirrored exactly (`u -> W - u`, the principal point is the centre); the
//! new mesh is `v'_i = F v_{m(i)}` with `F = diag(-1, 1, 1)` and `m` the topology's
//! mirror map (vertex `i` stays the same anatomical point), and the pose becomes
//! `R' = S R F`, `t' = S t` with `S = diag(-1, 1, 1)` in the camera: yaw and roll change
//! sign, pitch stays. Mirroring twice gives back the input exactly.

use crate::mesh::topology::FaceTopology;
use arkit_core::conventions::{Camera, EulerAngles, Pose};
use arkit_core::{ScreenVertex, TriangleSetup, VisibilityBuffer};
use image::{Rgb, RgbImage};
use nalgebra::{Matrix3, Point2, Point3, Rotation3, Vector3};

/// Ring scales about the nose tip (the official code's).
pub(crate) const RING_SCALES: [f64; 4] = [1.05, 1.1, 1.15, 1.2];

/// The official landmark index of the nose tip.
pub const NOSE_TIP_LANDMARK: usize = 30;

/// The axis of an out-of-plane or in-plane rotation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Axis {
    /// About the face's vertical axis.
    Yaw,
    /// Nodding.
    Pitch,
    /// In the image plane.
    Roll,
}

/// One sample to augment: image, canonical vertices and pose.
#[derive(Clone, Debug)]
pub struct FaceImage {
    /// The image.
    pub image: RgbImage,
    /// Canonical vertices (metres).
    pub verts: Vec<Point3<f32>>,
    /// The pose.
    pub pose: Pose,
}

/// Why a sample was not augmented.
#[derive(Clone, Debug, PartialEq)]
pub enum Skip {
    /// The requested change would pass the limit, or is too small to be worth it.
    AngleLimit(String),
    /// Part of the face is outside the image (before or after).
    OutsideImage(String),
    /// A vertex is behind (or on) the camera's near plane.
    BehindCamera,
    /// Inconsistent input (vertex count, topology).
    BadInput(String),
}

impl std::fmt::Display for Skip {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Skip::AngleLimit(s) => write!(f, "angle limit: {s}"),
            Skip::OutsideImage(s) => write!(f, "face outside the image: {s}"),
            Skip::BehindCamera => write!(f, "a vertex is behind the camera"),
            Skip::BadInput(s) => write!(f, "bad input: {s}"),
        }
    }
}

/// The pose after changing one Euler angle by `delta_deg` (others and translation
/// kept; roll turns the translation with the scene, see the module docs).
fn rotated_pose(pose: &Pose, axis: Axis, delta_deg: f64) -> Pose {
    let e = pose.euler();
    match axis {
        Axis::Yaw => Pose::from_euler(
            EulerAngles::new(e.yaw_deg + delta_deg, e.pitch_deg, e.roll_deg),
            pose.translation_m(),
        ),
        Axis::Pitch => Pose::from_euler(
            EulerAngles::new(e.yaw_deg, e.pitch_deg + delta_deg, e.roll_deg),
            pose.translation_m(),
        ),
        Axis::Roll => {
            let rz = Rotation3::from_axis_angle(&Vector3::z_axis(), delta_deg.to_radians());
            Pose::new(rz * pose.rotation(), rz * pose.translation_m())
        }
    }
}

/// Checks that every vertex is in front of the camera and projects inside the image
/// with `margin` pixels to spare.
fn check_inside(
    camera: &Camera,
    pose: &Pose,
    verts: &[Point3<f32>],
    margin: f64,
    when: &str,
) -> Result<(), Skip> {
    let pts: Vec<Point3<f64>> = verts.iter().map(|p| p.cast()).collect();
    let projected = camera.project_all(pose, &pts);
    if projected
        .iter()
        .any(|p| p.depth_m.is_nan() || p.depth_m <= camera.near_plane_m() || !p.u.is_finite())
    {
        return Err(Skip::BehindCamera);
    }
    let (w, h) = (camera.width as f64, camera.height as f64);
    if let Some(p) = projected
        .iter()
        .find(|p| p.u < margin || p.v < margin || p.u > w - margin || p.v > h - margin)
    {
        return Err(Skip::OutsideImage(format!(
            "{when}, a vertex projects to ({:.1}, {:.1}) in a {}x{} image",
            p.u, p.v, camera.width, camera.height
        )));
    }
    Ok(())
}

/// Bilinear read of `image` at continuous pixel coordinates (pixel `(i, j)` has its
/// centre at `(i + 0.5, j + 0.5)`); taps outside the image are clamped to the border.
fn sample_bilinear(image: &RgbImage, u: f64, v: f64) -> [f32; 3] {
    let (w, h) = (image.width() as i64, image.height() as i64);
    let (x, y) = (u - 0.5, v - 0.5);
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
    let raw = image.as_raw();
    let tap = |xi: i64, yi: i64| -> [f32; 3] {
        let (xi, yi) = (xi.clamp(0, w - 1), yi.clamp(0, h - 1));
        let o = ((yi * w + xi) * 3) as usize;
        [raw[o] as f32, raw[o + 1] as f32, raw[o + 2] as f32]
    };
    let (x0, y0) = (x0 as i64, y0 as i64);
    if x0 >= 0 && y0 >= 0 && x0 + 1 < w && y0 + 1 < h {
        // Inside: the four taps are two adjacent pairs, no clamping.
        let o = ((y0 * w + x0) * 3) as usize;
        let row = (w * 3) as usize;
        let mut out = [0.0; 3];
        for k in 0..3 {
            let (a, b) = (raw[o + k] as f32, raw[o + 3 + k] as f32);
            let (c, d) = (raw[o + row + k] as f32, raw[o + row + 3 + k] as f32);
            let top = a + (b - a) * fx;
            let bottom = c + (d - c) * fx;
            out[k] = top + (bottom - top) * fy;
        }
        return out;
    }
    let (a, b, c, d) = (
        tap(x0, y0),
        tap(x0 + 1, y0),
        tap(x0, y0 + 1),
        tap(x0 + 1, y0 + 1),
    );
    let mut out = [0.0; 3];
    for k in 0..3 {
        let top = a[k] + (b[k] - a[k]) * fx;
        let bottom = c[k] + (d[k] - c[k]) * fx;
        out[k] = top + (bottom - top) * fy;
    }
    out
}

fn to_rgb(c: [f32; 3]) -> Rgb<u8> {
    Rgb(c.map(|v| v.round().clamp(0.0, 255.0) as u8))
}

/// Convex hull of 2D points (Andrew's monotone chain), as indices counter-clockwise in
/// a y-up view, without collinear points.
fn convex_hull(points: &[Point2<f64>]) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..points.len())
        .filter(|&i| points[i].x.is_finite() && points[i].y.is_finite())
        .collect();
    idx.sort_by(|&a, &b| {
        points[a]
            .x
            .total_cmp(&points[b].x)
            .then(points[a].y.total_cmp(&points[b].y))
    });
    idx.dedup_by(|a, b| points[*a] == points[*b]);
    if idx.len() < 3 {
        return idx;
    }
    let cross = |o: usize, a: usize, b: usize| {
        let (o, a, b) = (points[o], points[a], points[b]);
        (a.x - o.x) * (b.y - o.y) - (a.y - o.y) * (b.x - o.x)
    };
    let mut hull: Vec<usize> = Vec::with_capacity(2 * idx.len());
    for pass in 0..2 {
        let start = hull.len();
        let iter: Box<dyn Iterator<Item = &usize>> = if pass == 0 {
            Box::new(idx.iter())
        } else {
            Box::new(idx.iter().rev())
        };
        for &p in iter {
            while hull.len() >= start + 2
                && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0
            {
                hull.pop();
            }
            hull.push(p);
        }
        hull.pop();
    }
    hull
}

/// The profiling geometry of one sample (stages 1-3 of the module docs), exposed for
/// tests and previews.
#[derive(Clone, Debug)]
pub struct ProfileMesh {
    /// Vertex indices of the contour (convex hull of the projected mesh).
    pub contour: Vec<u32>,
    /// Canonical positions of the ring points, ring by ring (`RING_SCALES` order).
    pub rings: Vec<Vec<Point3<f64>>>,
    /// Fixed anchors in image pixels (box, then border).
    pub anchors: Vec<Point2<f64>>,
    /// Band triangles over the points `[contour..., rings..., anchors...]`.
    pub band: Vec<[u32; 3]>,
}

fn landmark_box(
    projected: &[Point2<f64>],
    landmarks: &[u32],
    width: u32,
    height: u32,
) -> (f64, f64, f64, f64) {
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for &l in landmarks {
        let p = projected[l as usize];
        x0 = x0.min(p.x);
        x1 = x1.max(p.x);
        y0 = y0.min(p.y);
        y1 = y1.max(p.y);
    }
    let size = (x1 - x0).max(y1 - y0);
    let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
    let (w, h) = (width as f64, height as f64);
    (
        (cx - 1.125 * size).clamp(0.0, w),
        (cy - 1.275 * size).clamp(0.0, h),
        (cx + 1.125 * size).clamp(0.0, w),
        (cy + 0.975 * size).clamp(0.0, h),
    )
}

fn points_on_rectangle(x0: f64, y0: f64, x1: f64, y1: f64, per_side: usize) -> Vec<Point2<f64>> {
    let mut out = Vec::with_capacity(4 * per_side);
    for k in 0..per_side {
        let t = k as f64 / per_side as f64;
        out.push(Point2::new(x0 + (x1 - x0) * t, y0));
        out.push(Point2::new(x1, y0 + (y1 - y0) * t));
        out.push(Point2::new(x1 - (x1 - x0) * t, y1));
        out.push(Point2::new(x0, y1 - (y1 - y0) * t));
    }
    out
}

/// Builds the contour, rings, anchors and band triangulation for a face at `pose`.
pub fn profile_mesh(
    topology: &FaceTopology,
    verts: &[Point3<f32>],
    pose: &Pose,
    camera: &Camera,
) -> Result<ProfileMesh, Skip> {
    let pts: Vec<Point3<f64>> = verts.iter().map(|p| p.cast()).collect();
    let projected: Vec<Point2<f64>> = camera
        .project_all(pose, &pts)
        .iter()
        .map(|p| Point2::new(p.u, p.v))
        .collect();
    // Hull in a y-up view so its order is counter-clockwise as drawn.
    let flipped: Vec<Point2<f64>> = projected.iter().map(|p| Point2::new(p.x, -p.y)).collect();
    let contour: Vec<u32> = convex_hull(&flipped).iter().map(|&i| i as u32).collect();
    if contour.len() < 3 {
        return Err(Skip::BadInput("the projected face has no area".into()));
    }
    let nose_id = *topology
        .landmarks
        .get(NOSE_TIP_LANDMARK)
        .ok_or_else(|| Skip::BadInput("the topology has no landmark 30".into()))?;
    let nose = pose.to_camera(&pts[nose_id as usize]);
    let inverse = pose.face_to_camera.inverse();
    let rings: Vec<Vec<Point3<f64>>> = RING_SCALES
        .iter()
        .map(|&s| {
            contour
                .iter()
                .map(|&i| {
                    let c = pose.to_camera(&pts[i as usize]);
                    let scaled = Point3::new(
                        nose.x + s * (c.x - nose.x),
                        nose.y + s * (c.y - nose.y),
                        c.z,
                    );
                    inverse * scaled
                })
                .collect()
        })
        .collect();
    let (bx0, by0, bx1, by1) =
        landmark_box(&projected, &topology.landmarks, camera.width, camera.height);
    let mut anchors = points_on_rectangle(bx0, by0, bx1, by1, 10);
    let (w, h) = (camera.width as f64, camera.height as f64);
    anchors.extend(points_on_rectangle(0.0, 0.0, w, h, 5));
    // Source positions of every band point, in the order documented on `band`.
    let mut source: Vec<Point2<f64>> = contour.iter().map(|&i| projected[i as usize]).collect();
    for ring in &rings {
        for p in ring {
            let q = camera.project(pose, p);
            source.push(Point2::new(q.u, q.v));
        }
    }
    source.extend(anchors.iter().copied());
    let band = delaunay(&source)?;
    Ok(ProfileMesh {
        contour,
        rings,
        anchors,
        band,
    })
}

/// 2D Delaunay triangles over `points` (indices into it; repeated points share one).
fn delaunay(points: &[Point2<f64>]) -> Result<Vec<[u32; 3]>, Skip> {
    use spade::Triangulation;
    let mut t: spade::DelaunayTriangulation<spade::Point2<f64>> =
        spade::DelaunayTriangulation::new();
    let mut owner: Vec<u32> = Vec::new();
    for (i, p) in points.iter().enumerate() {
        let h = t
            .insert(spade::Point2::new(p.x, p.y))
            .map_err(|e| Skip::BadInput(format!("band point {i} at {p:?}: {e:?}")))?;
        if h.index() == owner.len() {
            owner.push(i as u32);
        }
    }
    Ok(t.inner_faces()
        .map(|f| f.vertices().map(|v| owner[v.fix().index()]))
        .collect())
}

/// Rotates the face out of plane (yaw or pitch) by `delta_deg` and re-renders the image
/// (see the module docs). The verts are unchanged; the pose gets the new angle.
pub fn profile(
    topology: &FaceTopology,
    input: &FaceImage,
    axis: Axis,
    delta_deg: f64,
) -> Result<FaceImage, Skip> {
    if axis == Axis::Roll {
        return roll(input, delta_deg);
    }
    if input.verts.len() != topology.vertex_count {
        return Err(Skip::BadInput(format!(
            "{} vertices, the topology has {}",
            input.verts.len(),
            topology.vertex_count
        )));
    }
    let (width, height) = input.image.dimensions();
    // The rasterizer's buffer has a size limit (it panics beyond it).
    let max = arkit_core::MAX_VIEWPORT;
    if !(1..=max).contains(&width) || !(1..=max).contains(&height) {
        return Err(Skip::BadInput(format!(
            "image {width}x{height}: profiling renders images of at most {max} pixels a side"
        )));
    }
    let camera = Camera::release(width, height);
    check_inside(&camera, &input.pose, &input.verts, 0.0, "before")?;
    let new_pose = rotated_pose(&input.pose, axis, delta_deg);
    check_inside(&camera, &new_pose, &input.verts, 0.0, "after the rotation")?;
    let geometry = profile_mesh(topology, &input.verts, &input.pose, &camera)?;

    // Band layer: destination positions (screen) and source positions of its points.
    let pts: Vec<Point3<f64>> = input.verts.iter().map(|p| p.cast()).collect();
    let mut canonical: Vec<Point3<f64>> =
        geometry.contour.iter().map(|&i| pts[i as usize]).collect();
    for ring in &geometry.rings {
        canonical.extend(ring.iter().copied());
    }
    let moving = canonical.len();
    let mut dst: Vec<Point2<f64>> = camera
        .project_all(&new_pose, &canonical)
        .iter()
        .map(|p| Point2::new(p.u, p.v))
        .collect();
    let mut src: Vec<Point2<f64>> = camera
        .project_all(&input.pose, &canonical)
        .iter()
        .map(|p| Point2::new(p.u, p.v))
        .collect();
    dst.extend(geometry.anchors.iter().copied());
    src.extend(geometry.anchors.iter().copied());
    let n = width as usize * height as usize;
    let mut source_at: Vec<[f32; 2]> = vec![[f32::NAN; 2]; n];
    for t in &geometry.band {
        // Triangles of fixed anchors only map onto themselves: nothing to redraw.
        if t.iter().all(|&i| i as usize >= moving) {
            continue;
        }
        let v = t.map(|i| ScreenVertex {
            x: dst[i as usize].x as f32,
            y: dst[i as usize].y as f32,
            inv_w: 1.0,
        });
        if let Some(setup) = TriangleSetup::new(v, width, height, arkit_core::Culling::None) {
            setup.for_each_covered(|f| {
                let idx = f.y as usize * width as usize + f.x as usize;
                let mut s = [0.0f32; 2];
                for k in 0..3 {
                    let p = src[t[k] as usize];
                    s[0] += f.screen_bary[k] * p.x as f32;
                    s[1] += f.screen_bary[k] * p.y as f32;
                }
                source_at[idx] = s;
            });
        }
    }

    // Face layer: mesh and hole fills at the new pose, depth-tested.
    let fill = topology
        .hole_fill()
        .map_err(|e| Skip::BadInput(e.to_string()))?;
    let mut all_verts = input.verts.clone();
    all_verts.extend(fill.centroid_positions(&input.verts));
    let mut triangles = topology.triangles.clone();
    triangles.extend(fill.triangles.iter().copied());
    let screen = camera.project_to_screen(&new_pose, &all_verts);
    let mut vis = VisibilityBuffer::new(width, height);
    vis.rasterize_mesh(&screen, &triangles)
        .map_err(|e| Skip::BadInput(e.to_string()))?;
    let k = camera.pinhole();
    let old_r = input.pose.rotation().cast::<f32>();
    let old_t = input.pose.translation_m().cast::<f32>();
    for (idx, &tri) in vis.triangle.iter().enumerate() {
        if tri == VisibilityBuffer::EMPTY {
            continue;
        }
        let t = triangles[tri as usize];
        let b = vis.bary[idx];
        let p = all_verts[t[0] as usize].coords * b[0]
            + all_verts[t[1] as usize].coords * b[1]
            + all_verts[t[2] as usize].coords * b[2];
        let c = old_r * p + old_t;
        let depth = -c.z as f64;
        source_at[idx] = [
            (k.cx + k.fx * c.x as f64 / depth) as f32,
            (k.cy - k.fy * c.y as f64 / depth) as f32,
        ];
    }

    let mut image = input.image.clone();
    let out = image.as_mut();
    for (idx, s) in source_at.iter().enumerate() {
        if s[0].is_finite() {
            let c = to_rgb(sample_bilinear(&input.image, s[0] as f64, s[1] as f64));
            out[3 * idx..3 * idx + 3].copy_from_slice(&c.0);
        }
    }
    Ok(FaceImage {
        image,
        verts: input.verts.clone(),
        pose: new_pose,
    })
}

/// Rolls the scene by `delta_deg` about the optical axis (see the module docs).
pub fn roll(input: &FaceImage, delta_deg: f64) -> Result<FaceImage, Skip> {
    let (width, height) = input.image.dimensions();
    let camera = Camera::release(width, height);
    check_inside(&camera, &input.pose, &input.verts, 0.0, "before")?;
    let new_pose = rotated_pose(&input.pose, Axis::Roll, delta_deg);
    check_inside(&camera, &new_pose, &input.verts, 0.0, "after the roll")?;
    let k = camera.pinhole();
    let (s, c) = (-delta_deg.to_radians()).sin_cos();
    let mut image = RgbImage::new(width, height);
    let out = image.as_mut();
    for y in 0..height {
        // Normalised camera coordinates (y up) of the output pixel, turned back.
        let b = -(y as f64 + 0.5 - k.cy) / k.fy;
        for x in 0..width {
            let a = (x as f64 + 0.5 - k.cx) / k.fx;
            let (a0, b0) = (c * a - s * b, s * a + c * b);
            let (u, v) = (k.cx + k.fx * a0, k.cy - k.fy * b0);
            if u >= 0.0 && v >= 0.0 && u <= width as f64 && v <= height as f64 {
                let o = 3 * (y as usize * width as usize + x as usize);
                out[o..o + 3].copy_from_slice(&to_rgb(sample_bilinear(&input.image, u, v)).0);
            }
        }
    }
    Ok(FaceImage {
        image,
        verts: input.verts.clone(),
        pose: new_pose,
    })
}

/// Mirrors a sample left-right (see the module docs); `mirror` is
/// [`FaceTopology::mirror_map`].
pub fn mirror(input: &FaceImage, mirror: &[u32]) -> Result<FaceImage, Skip> {
    if mirror.len() != input.verts.len() {
        return Err(Skip::BadInput(format!(
            "mirror map of {} vertices for a face of {}",
            mirror.len(),
            input.verts.len()
        )));
    }
    let f = Matrix3::from_diagonal(&Vector3::new(-1.0, 1.0, 1.0));
    let verts: Vec<Point3<f32>> = mirror
        .iter()
        .map(|&m| {
            let p = input.verts[m as usize];
            Point3::new(-p.x, p.y, p.z)
        })
        .collect();
    let r = Rotation3::from_matrix_unchecked(f * input.pose.rotation().matrix() * f);
    let t = f * input.pose.translation_m();
    let image = image::imageops::flip_horizontal(&input.image);
    Ok(FaceImage {
        image,
        verts,
        pose: Pose::new(r, t),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::synthetic_face::builtin;

    #[test]
    fn hull_of_a_square_with_inner_points() {
        let p: Vec<Point2<f64>> = [
            (0.0, 0.0),
            (1.0, 0.0),
            (1.0, 1.0),
            (0.0, 1.0),
            (0.5, 0.5),
            (0.5, 0.0),
        ]
        .iter()
        .map(|&(x, y)| Point2::new(x, y))
        .collect();
        let h = convex_hull(&p);
        assert_eq!(h, vec![0, 1, 2, 3]);
    }

    #[test]
    fn bilinear_reads_pixel_centres_exactly_and_blends_between() {
        let img = RgbImage::from_fn(2, 1, |x, _| Rgb([x as u8 * 100, 0, 0]));
        assert_eq!(sample_bilinear(&img, 0.5, 0.5)[0], 0.0);
        assert_eq!(sample_bilinear(&img, 1.5, 0.5)[0], 100.0);
        assert_eq!(sample_bilinear(&img, 1.0, 0.5)[0], 50.0);
        assert_eq!(sample_bilinear(&img, -3.0, 0.5)[0], 0.0);
    }

    fn face_at(yaw: f64, pitch: f64, roll: f64) -> FaceImage {
        let verts = builtin()
            .topology
            .template
            .clone()
            .expect("the built-in face has a template");
        let pose = Pose::from_euler(
            EulerAngles::new(yaw, pitch, roll),
            Vector3::new(0.01, -0.02, -0.5),
        );
        let image = RgbImage::from_fn(256, 256, |x, y| Rgb([(x % 256) as u8, (y % 256) as u8, 90]));
        FaceImage { image, verts, pose }
    }

    #[test]
    fn new_euler_angles_equal_the_request() {
        let f = face_at(25.0, 10.0, -5.0);
        for (axis, d) in [(Axis::Yaw, 12.0), (Axis::Pitch, -7.0), (Axis::Roll, 9.0)] {
            let e0 = f.pose.euler();
            let e1 = rotated_pose(&f.pose, axis, d).euler();
            let want = match axis {
                Axis::Yaw => [e0.yaw_deg + d, e0.pitch_deg, e0.roll_deg],
                Axis::Pitch => [e0.yaw_deg, e0.pitch_deg + d, e0.roll_deg],
                Axis::Roll => [e0.yaw_deg, e0.pitch_deg, e0.roll_deg + d],
            };
            let got = [e1.yaw_deg, e1.pitch_deg, e1.roll_deg];
            for k in 0..3 {
                assert!(
                    (got[k] - want[k]).abs() < 1e-9,
                    "{axis:?}: {got:?} vs {want:?}"
                );
            }
        }
    }

    #[test]
    fn mirror_twice_is_the_identity_and_flips_yaw_and_roll() {
        let face = builtin();
        let map = face.topology.mirror_map().unwrap();
        let f = face_at(30.0, 12.0, -8.0);
        let m = mirror(&f, &map).unwrap();
        let e0 = f.pose.euler();
        let e1 = m.pose.euler();
        assert!((e1.yaw_deg + e0.yaw_deg).abs() < 1e-9);
        assert!((e1.roll_deg + e0.roll_deg).abs() < 1e-9);
        assert!((e1.pitch_deg - e0.pitch_deg).abs() < 1e-9);
        // Each new vertex projects to the mirror of its partner's old projection.
        let cam = Camera::release(256, 256);
        let old: Vec<Point3<f64>> = f.verts.iter().map(|p| p.cast()).collect();
        let new: Vec<Point3<f64>> = m.verts.iter().map(|p| p.cast()).collect();
        let po = cam.project_all(&f.pose, &old);
        let pn = cam.project_all(&m.pose, &new);
        for (i, p) in pn.iter().enumerate() {
            let q = &po[map[i] as usize];
            assert!((p.u - (256.0 - q.u)).abs() < 1e-6 && (p.v - q.v).abs() < 1e-6);
        }
        let back = mirror(&m, &map).unwrap();
        assert_eq!(back.image, f.image);
        assert_eq!(back.verts, f.verts);
        assert!(
            (back.pose.to_release_rt().iter())
                .zip(f.pose.to_release_rt().iter())
                .all(|(a, b)| (a - b).abs() < 1e-12)
        );
    }

    #[test]
    fn roll_there_and_back_restores_the_centre() {
        let f = face_at(10.0, 5.0, 0.0);
        let a = roll(&f, 15.0).unwrap();
        let b = roll(&a, -15.0).unwrap();
        // Bilinear twice blurs a smooth ramp by less than a grey level or two.
        let mut worst = 0i32;
        for y in 64..192 {
            for x in 64..192 {
                let (p, q) = (f.image.get_pixel(x, y), b.image.get_pixel(x, y));
                for k in 0..3 {
                    worst = worst.max((p[k] as i32 - q[k] as i32).abs());
                }
            }
        }
        assert!(worst <= 2, "{worst}");
        let e = b.pose.euler();
        assert!(e.roll_deg.abs() < 1e-9);
    }

    #[test]
    fn skips_are_reasons_not_panics() {
        let f = face_at(10.0, 0.0, 0.0);
        let topo = &builtin().topology;
        // Pushed out of the image by a large translation.
        let mut off = f.clone();
        off.pose = Pose::from_euler(
            EulerAngles::new(0.0, 0.0, 0.0),
            Vector3::new(0.5, 0.0, -0.5),
        );
        assert!(matches!(
            profile(topo, &off, Axis::Yaw, 10.0),
            Err(Skip::OutsideImage(_))
        ));
        // Behind the camera.
        let mut behind = f.clone();
        behind.pose =
            Pose::from_euler(EulerAngles::new(0.0, 0.0, 0.0), Vector3::new(0.0, 0.0, 0.5));
        assert_eq!(
            profile(topo, &behind, Axis::Yaw, 10.0).unwrap_err(),
            Skip::BehindCamera
        );
        // Wrong vertex count.
        let mut short = f.clone();
        short.verts.pop();
        assert!(matches!(
            profile(topo, &short, Axis::Yaw, 10.0),
            Err(Skip::BadInput(_))
        ));
    }
}
