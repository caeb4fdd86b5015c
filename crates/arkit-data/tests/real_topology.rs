//! Checks against the real ARKit topology in `$ARKIT_RESOURCES` (default
//! `../shared/arkitface-resources/`). Every test skips, saying so, when that folder is
//! absent (a fresh clone alone).

use arkit_core::conventions::{Camera, EulerAngles, Pose};
use arkit_data::mesh::FaceTopology;
use arkit_data::mesh::{LANDMARK_MIRROR, LoopRole, NOSE_TIP_LANDMARK, nearest_mirror_partners};
use nalgebra::{Point3, Vector3};
use std::collections::HashSet;
use std::path::PathBuf;

fn resources() -> Option<PathBuf> {
    let dir = crate::support::resources();
    if dir.is_none() {
        eprintln!(
            "SKIPPED: the real ARKit topology is absent (ARKIT_RESOURCES); real-topology checks not run"
        );
    }
    dir
}

#[test]
fn reads_the_real_topology() {
    let Some(dir) = resources() else { return };
    let topo = FaceTopology::from_resources(&dir).unwrap();
    assert_eq!(topo.vertex_count, 1220);
    assert_eq!(topo.triangles.len(), 2304);
    assert_eq!(topo.landmarks.len(), 68);
    assert_eq!(topo.landmarks[NOSE_TIP_LANDMARK], 8);
    // triangles.npy is Fortran-order uint16: the first row must be read as a row.
    let raw = arkit_core::read_npy(&dir.join("triangles.npy")).unwrap();
    assert_eq!(raw.shape(), &[2304, 3]);
    let t = topo.template.as_ref().unwrap();
    // Counter-clockwise seen from +z: most triangles face the front.
    let front = topo
        .triangles
        .iter()
        .filter(|tr| {
            let (a, b, c) = (t[tr[0] as usize], t[tr[1] as usize], t[tr[2] as usize]);
            (b - a).cross(&(c - a)).z > 0.0
        })
        .count();
    assert!(front as f64 > 0.9 * 2304.0, "{front}");
}

#[test]
fn boundary_loops_of_the_real_mesh() {
    let Some(dir) = resources() else { return };
    let topo = FaceTopology::from_resources(&dir).unwrap();
    let loops = topo.boundary_loops().unwrap();
    assert_eq!(loops.loops.len(), 4);
    assert_eq!(loops.edge_count(), 140);
    let len = |r| loops.get(r).unwrap().len();
    // The official loader's hand-written index lists have these lengths.
    assert_eq!(len(LoopRole::Outer), 56);
    assert_eq!(len(LoopRole::Mouth), 36);
    assert_eq!(len(LoopRole::RightEye), 24);
    assert_eq!(len(LoopRole::LeftEye), 24);
    // Landmark 36 (right eye's outer corner) lies on the right eye loop.
    assert!(
        loops
            .get(LoopRole::RightEye)
            .unwrap()
            .contains(&topo.landmarks[36])
    );
    // V - E + F = -2 for a disc with three holes.
    let mut edges = HashSet::new();
    for t in &topo.triangles {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            edges.insert((a.min(b), a.max(b)));
        }
    }
    assert_eq!(1220 - edges.len() as i64 + 2304, -2);
}

#[test]
fn hole_fill_equals_the_release_tris_2388() {
    let Some(dir) = resources() else { return };
    let topo = FaceTopology::from_resources(&dir).unwrap();
    let fill = topo.hole_fill().unwrap();
    let release = arkit_core::read_npy(&dir.join("tris_2388x3.npy"))
        .unwrap()
        .to_i64_vec()
        .unwrap();
    let norm = |t: [i64; 3]| {
        let mut s = t;
        s.sort();
        s
    };
    let theirs: HashSet<[i64; 3]> = release[2304 * 3..]
        .chunks(3)
        .map(|c| norm([c[0], c[1], c[2]]))
        .collect();
    let ours: HashSet<[i64; 3]> = fill
        .triangles
        .iter()
        .map(|t| norm([t[0] as i64, t[1] as i64, t[2] as i64]))
        .collect();
    assert_eq!(fill.triangles.len(), 84);
    assert_eq!(
        ours, theirs,
        "centroid order mouth, right eye, left eye as in the release"
    );
    // The first 2304 rows are the mesh triangles themselves.
    let mesh: Vec<[i64; 3]> = release[..2304 * 3]
        .chunks(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    let topo_tris: Vec<[i64; 3]> = topo
        .triangles
        .iter()
        .map(|t| [t[0] as i64, t[1] as i64, t[2] as i64])
        .collect();
    assert_eq!(mesh, topo_tris);
}

#[test]
fn mirror_map_of_the_real_template() {
    let Some(dir) = resources() else { return };
    let topo = FaceTopology::from_resources(&dir).unwrap();
    let t = topo.template.as_ref().unwrap();
    // The release's UV layout is symmetric, so the map exists and is an involution.
    let map = topo.mirror_map().unwrap();
    // Landmarks map to their iBUG partners, except two pairs the release's kpt_ind.npy
    // places one vertex off symmetric (jaw 1/15 and lower eyelid 41/46).
    let off: Vec<usize> = (0..68)
        .filter(|&i| map[topo.landmarks[i] as usize] != topo.landmarks[LANDMARK_MIRROR[i]])
        .collect();
    assert_eq!(off, vec![1, 15, 41, 46]);
    // Geometrically, partners sit at mirrored positions within a few millimetres (a
    // real face is not exactly symmetric).
    let worst = (0..1220)
        .map(|i| {
            let (p, q) = (t[i], t[map[i] as usize]);
            (Point3::new(-p.x, p.y, p.z) - q).norm()
        })
        .fold(0.0f32, f32::max);
    eprintln!(
        "real template: UV mirror map, largest geometric mismatch {:.2} mm",
        worst * 1000.0
    );
    assert!(worst < 0.015, "{worst}");
    // The mesh is denser than the face's asymmetry, so nearest neighbours under x -> -x
    // often pick another vertex: that is why the map comes from the UV layout.
    let (nn, _) = nearest_mirror_partners(t);
    let agree = (0..1220).filter(|&i| nn[i] == map[i]).count();
    eprintln!("nearest-neighbour map agrees on {agree} of 1220 vertices");
    let mut d: Vec<f32> = (0..1220)
        .map(|i| (Point3::new(-t[i].x, t[i].y, t[i].z) - t[map[i] as usize]).norm())
        .collect();
    d.sort_by(f32::total_cmp);
    assert!(d[610] < 0.003, "median mirror mismatch {} m", d[610]);
}

#[test]
fn projection_matrix_file_matches_the_release_camera() {
    let Some(dir) = resources() else { return };
    let p = Camera::read_projection_txt(&dir.join("projection_matrix.txt")).unwrap();
    assert_eq!(p, Camera::release_projection());
}

#[test]
fn real_nose_tip_projects_where_the_pinhole_says() {
    let Some(dir) = resources() else { return };
    let topo = FaceTopology::from_resources(&dir).unwrap();
    let tip =
        topo.template.as_ref().unwrap()[topo.landmarks[NOSE_TIP_LANDMARK] as usize].cast::<f64>();
    // yaw 30 degrees, 0.5 m away on the optical axis, 800x800 camera (f = 629.774804 px).
    let pose = Pose::from_euler(
        EulerAngles::new(30.0, 0.0, 0.0),
        Vector3::new(0.0, 0.0, -0.5),
    );
    let cam = Camera::release(800, 800);
    let q = cam.project(&pose, &tip);
    // By hand: Ry(30) (x, y, z) = (x cos30 + z sin30, y, -x sin30 + z cos30).
    let (s, c) = (0.5f64, 3f64.sqrt() / 2.0);
    let pc = Point3::new(tip.x * c + tip.z * s, tip.y, -tip.x * s + tip.z * c - 0.5);
    let f = 1.57443701 * 400.0;
    let u = 400.0 + f * pc.x / -pc.z;
    let v = 400.0 - f * pc.y / -pc.z;
    assert!((q.u - u).abs() < 1e-9 && (q.v - v).abs() < 1e-9);
    // Numbers: tip (0.00067574, -0.00429178, 0.0693207) -> (u, v) = (450.41, 406.14).
    assert!(
        (q.u - 450.412).abs() < 0.01 && (q.v - 406.139).abs() < 0.01,
        "{q:?}"
    );
}

#[test]
fn real_topology_survives_an_obj_round_trip() {
    let Some(dir) = resources() else { return };
    let topo = FaceTopology::from_resources(&dir).unwrap();
    let out = tempfile::tempdir().unwrap();
    let path = out.path().join("arkit.obj");
    topo.write_obj(&path, topo.template.as_ref().unwrap())
        .unwrap();
    let back = FaceTopology::from_obj(&path, topo.landmarks.clone()).unwrap();
    assert_eq!(back.triangles, topo.triangles);
    assert_eq!(back.boundary_loops().unwrap().edge_count(), 140);
    assert_eq!(back.mirror_map().unwrap(), topo.mirror_map().unwrap());
}

#[test]
fn real_mask_area_agrees_with_the_projected_contour() {
    use arkit_core::VisibilityBuffer;
    use arkit_data::crop::CropTransform;
    use arkit_data::render::FaceRenderer;
    let Some(dir) = resources() else { return };
    let topo = FaceTopology::from_resources(&dir).unwrap();
    let verts = topo.template.clone().unwrap();
    let renderer = FaceRenderer::new(topo.clone(), Camera::release_projection()).unwrap();
    // Frontal: no part of the face hides another, so face + openings fill the contour.
    let pose = Pose::from_euler(
        EulerAngles::new(0.0, 0.0, 0.0),
        Vector3::new(0.0, 0.0, -0.45),
    );
    let crop = CropTransform {
        x0: 200.0,
        y0: 200.0,
        side: 400.0,
        side_y: 400.0,
        size: 400,
        rules: arkit_data::crop::RuleSet::Exact,
    };
    let mut vb = VisibilityBuffer::new(400, 400);
    let t = renderer
        .render(&verts, &pose, 800, 800, &crop, &mut vb)
        .unwrap();
    let covered = vb.covered_pixels() as f64; // face plus eye and mouth openings
    let face = t.mask.iter().filter(|&&m| m).count() as f64;
    let cam = Camera::release(800, 800);
    let outer = topo
        .boundary_loops()
        .unwrap()
        .get(LoopRole::Outer)
        .unwrap()
        .clone();
    let poly: Vec<(f64, f64)> = outer
        .iter()
        .map(|&i| {
            let p = cam.project(&pose, &verts[i as usize].cast());
            crop.to_crop(p.u, p.v)
        })
        .collect();
    let (mut area, mut perimeter) = (0.0, 0.0);
    for k in 0..poly.len() {
        let (a, b) = (poly[k], poly[(k + 1) % poly.len()]);
        area += a.0 * b.1 - b.0 * a.1;
        perimeter += ((b.0 - a.0).powi(2) + (b.1 - a.1).powi(2)).sqrt();
    }
    let area = area.abs() / 2.0;
    eprintln!("contour polygon {area:.0} px, covered {covered:.0} px, face mask {face:.0} px");
    // Everything inside the contour is covered (up to a half-pixel band along it); the
    // surface also bulges a little beyond the contour in projection (the contour runs
    // along the back of the cheeks), measured here at 2%.
    assert!(covered >= area - 0.5 * perimeter, "{covered} vs {area}");
    assert!(covered <= 1.03 * area, "{covered} vs {area}");
    assert!(face < covered && face > 0.85 * covered);
}

#[test]
fn uv_map_matches_one_drawn_from_the_release_files() {
    use arkit_core::{ScreenVertex, VisibilityBuffer};
    use arkit_data::render::UvMapper;
    let Some(dir) = resources() else { return };
    let topo = FaceTopology::from_resources(&dir).unwrap();
    assert_eq!(topo.uv_extension.len(), 59);
    let verts = topo.template.clone().unwrap();
    let ours = UvMapper::derive(&topo).unwrap();
    // Our extension reproduces the release's 1,279 UVs as a set: the centroids are the
    // loop means, the ring rows are the release's own.
    let release_uv: Vec<[f32; 2]> = topo.uv.iter().chain(&topo.uv_extension).copied().collect();
    for (k, p) in ours.uv.iter().enumerate() {
        let d = release_uv
            .iter()
            .map(|q| (q[0] - p[0]).hypot(q[1] - p[1]))
            .fold(f32::MAX, f32::min);
        assert!(
            d < 1e-6,
            "our UV vertex {k} {p:?} is not a release UV vertex ({d})"
        );
    }
    // The release's own map: its 1,279 UVs and tris_2500x3, positions from our
    // extension (mesh, contour x 1.1, hole centroids) matched by UV.
    let tris = arkit_core::read_npy(&dir.join("tris_2500x3_202110.npy"))
        .unwrap()
        .to_i64_vec()
        .unwrap();
    let ext = ours.extended_positions(&verts);
    let pos_of_release: Vec<Point3<f32>> = release_uv
        .iter()
        .map(|q| {
            let k = (0..ours.uv.len())
                .min_by(|&a, &b| {
                    let d = |i: usize| (ours.uv[i][0] - q[0]).hypot(ours.uv[i][1] - q[1]);
                    d(a).total_cmp(&d(b))
                })
                .unwrap();
            ext[k]
        })
        .collect();
    let size = 192u32;
    let screen: Vec<ScreenVertex> = release_uv
        .iter()
        .map(|t| ScreenVertex {
            x: t[0] * size as f32,
            y: t[1] * size as f32,
            inv_w: 1.0,
        })
        .collect();
    let tri: Vec<[u32; 3]> = tris
        .chunks(3)
        .map(|c| [c[0] as u32, c[1] as u32, c[2] as u32])
        .collect();
    let mut vb = VisibilityBuffer::new(size, size);
    let mut theirs = vec![[f32::NAN; 3]; (size * size) as usize];
    vb.rasterize_mesh_with(&screen, &tri, |idx, t, f| {
        let tr = tri[t as usize];
        let p = pos_of_release[tr[0] as usize].coords * f.bary[0]
            + pos_of_release[tr[1] as usize].coords * f.bary[1]
            + pos_of_release[tr[2] as usize].coords * f.bary[2];
        theirs[idx] = [p.x, p.y, p.z];
    })
    .unwrap();
    let mine = ours.position_map(&verts, size);
    let (mut both, mut only_one, mut worst) = (0, 0, 0.0f32);
    for (a, b) in mine.iter().zip(&theirs) {
        match (a[0].is_nan(), b[0].is_nan()) {
            (false, false) => {
                both += 1;
                worst = worst.max((0..3).map(|k| (a[k] - b[k]).abs()).fold(0.0, f32::max));
            }
            (true, true) => {}
            _ => only_one += 1,
        }
    }
    eprintln!(
        "UV map vs release triangulation: {both} texels in both, {only_one} in one only, largest difference {:.3} mm",
        worst * 1000.0
    );
    assert!(
        only_one * 100 < both,
        "coverage differs: {only_one} of {both}"
    );
    // The ring quads may be split along the other diagonal: differences stay within the ring.
    assert!(worst < 0.01, "{worst}");
}

/// Mean and largest error (mm) of the vertices read back from a UV position map of
/// `size`, read as our network reads it (bilinear, texel centres at `(i + 0.5) / S`, as
/// `grid_sample(align_corners=False)`), when the map was drawn with texel `i` at
/// `u = (i + 0.5) / S` (ours) or at `u = i / (S - 1)` (the official loader's
/// `u * (S - 1)`).
///
/// Returns (mean, max, unreadable) per layout; unreadable vertices (whose bilinear
/// footprint touches a texel no triangle covers) are left out of the mean and max.
fn uv_read_errors(topo: &FaceTopology, verts: &[Point3<f32>], size: u32) -> [(f64, f64, usize); 2] {
    use arkit_data::render::UvMapper;
    let s = size as f32;
    let official_layout = {
        // Texel i holds u = i / (S - 1): draw with UVs moved so that our texel centre
        // (i + 0.5) / S lands on it.
        let mut t = topo.clone();
        for uv in &mut t.uv {
            *uv = uv.map(|u| (u * (s - 1.0) + 0.5) / s);
        }
        t
    };
    [topo, &official_layout].map(|layout| {
        let map = UvMapper::derive(layout).unwrap().position_map(verts, size);
        let errs: Vec<f64> = verts
            .iter()
            .zip(&topo.uv)
            .map(|(v, &uv)| {
                let p = UvMapper::sample(&map, size, uv);
                ((p[0] - v.x).powi(2) + (p[1] - v.y).powi(2) + (p[2] - v.z).powi(2)).sqrt() as f64
                    * 1e3
            })
            .collect();
        let ok: Vec<f64> = errs.iter().copied().filter(|e| e.is_finite()).collect();
        (
            ok.iter().sum::<f64>() / ok.len() as f64,
            ok.iter().copied().fold(0.0, f64::max),
            errs.len() - ok.len(),
        )
    })
}

#[test]
fn the_official_half_texel_uv_offset_costs_more_than_our_one_convention() {
    let builtin = arkit_data::mesh::builtin().topology.clone();
    let bverts: Vec<Point3<f32>> = builtin.template.clone().expect("built-in template");
    let mut cases = vec![("built-in", builtin, bverts)];
    if let Some(dir) = resources() {
        let topo = FaceTopology::from_resources(&dir).unwrap();
        if let Some(t) = topo.template.clone() {
            cases.push(("real", topo, t));
        }
    }
    for (name, topo, verts) in &cases {
        for size in [32, 192] {
            let [
                (ours_mean, ours_max, ours_bad),
                (off_mean, off_max, off_bad),
            ] = uv_read_errors(topo, verts, size);
            eprintln!(
                "{name} face, {size}x{size} UV map: ours mean {ours_mean:.3} mm, max {ours_max:.3} mm, {ours_bad} unreadable; official mean {off_mean:.3} mm, max {off_max:.3} mm, {off_bad} unreadable"
            );
            assert!(ours_mean < off_mean && ours_bad <= off_bad, "{name} {size}");
        }
    }
}
