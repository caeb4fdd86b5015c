//! [`FaceTopology`]: the mesh facts every geometric module shares.
//!
//! A topology is the triangle list over the face's vertices, one UV coordinate per
//! vertex (u to the right, v downward, in [0, 1], as the release's UV file), and the 68
//! landmark vertex indices in the iBUG roles (0-16 jaw from the subject's right, 17-26
//! brows, 27-35 nose with 30 the tip, 36-41 and 42-47 the eyes, 48-67 the mouth).
//!
//! Everything else is derived from the triangles, not hard-coded:
//! - [`FaceTopology::boundary_loops`]: the outer contour and the eye and mouth holes
//!   (edges used by one triangle, chained into oriented loops); the real ARKit mesh has
//!   4 loops and 140 boundary edges.
//! - [`FaceTopology::hole_fill`]: fan triangles that close the mouth and the two eyes
//!   around one extra centroid vertex each (ids `V`, `V+1`, `V+2` in the order mouth,
//!   eye of landmarks 36-41, eye of landmarks 42-47), as the release's `tris_2388x3.npy`.
//! - [`FaceTopology::mirror_map`]: each vertex's partner under `x -> -x`, read from the
//!   symmetric UV layout.

use arkit_core::{Error, Result};
use nalgebra::Point3;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Number of landmarks (iBUG 68-point scheme).
pub(crate) const LANDMARK_COUNT: usize = 68;
/// Index of the nose-tip landmark.
pub const NOSE_TIP_LANDMARK: usize = 30;

/// Triangles, UVs and landmarks of a face mesh, plus a template face when one is known.
#[derive(Clone, Debug)]
pub struct FaceTopology {
    /// Where it came from (`"synthetic stand-in"`, a resources folder, an OBJ file).
    pub source: String,
    /// Number of mesh vertices (1,220 for ARKit).
    pub vertex_count: usize,
    /// Triangles over `0..vertex_count`, counter-clockwise seen from the face front.
    pub triangles: Vec<[u32; 3]>,
    /// One UV coordinate per vertex, in [0, 1], v downward.
    pub uv: Vec<[f32; 2]>,
    /// The 68 landmark vertex indices.
    pub landmarks: Vec<u32>,
    /// A neutral face in the canonical frame (metres), when the source has one.
    pub template: Option<Vec<Point3<f32>>>,
    /// UV rows beyond the mesh vertices, when the source has them: the release's
    /// `uv_coords_std_202109.npy` has 59 (the ring outside the contour, then the mouth
    /// and eye centroids), which [`crate::render::uv_map::UvMapper`] uses.
    pub uv_extension: Vec<[f32; 2]>,
}

/// A boundary loop: vertex indices in order, following the triangles' orientation.
pub(crate) type BoundaryLoop = Vec<u32>;

/// What a boundary loop is, as found from the landmarks on or near it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LoopRole {
    /// The outer contour of the face.
    Outer,
    /// The mouth opening.
    Mouth,
    /// The eye of landmarks 36-41 (the subject's right eye, image left).
    RightEye,
    /// The eye of landmarks 42-47 (the subject's left eye, image right).
    LeftEye,
}

/// The mesh's boundary loops, each with its role.
#[derive(Clone, Debug)]
pub struct BoundaryLoops {
    /// Loops in the order outer, mouth, right eye, left eye.
    pub loops: Vec<(LoopRole, BoundaryLoop)>,
}

impl BoundaryLoops {
    /// The loop of a given role.
    pub fn get(&self, role: LoopRole) -> Option<&BoundaryLoop> {
        self.loops.iter().find(|(r, _)| *r == role).map(|(_, l)| l)
    }

    /// Total number of boundary edges.
    pub fn edge_count(&self) -> usize {
        self.loops.iter().map(|(_, l)| l.len()).sum()
    }
}

/// Triangles closing the eye and mouth holes around extra centroid vertices.
#[derive(Clone, Debug)]
pub struct HoleFill {
    /// For each extra vertex (id `vertex_count + k`): the hole it fills and its loop.
    pub centroids: Vec<(LoopRole, BoundaryLoop)>,
    /// Fan triangles, oriented like the mesh.
    pub triangles: Vec<[u32; 3]>,
}

impl HoleFill {
    /// Positions of the centroid vertices: the mean of each hole's loop vertices.
    pub fn centroid_positions(&self, verts: &[Point3<f32>]) -> Vec<Point3<f32>> {
        self.centroids
            .iter()
            .map(|(_, l)| {
                let sum = l.iter().fold(nalgebra::Vector3::zeros(), |acc, &i| {
                    acc + verts[i as usize].coords
                });
                Point3::from(sum / l.len() as f32)
            })
            .collect()
    }
}

impl FaceTopology {
    /// Checks indices, counts and values; `source` names the origin in errors.
    pub fn validate(&self) -> Result<()> {
        let bad = |msg: String| Err(Error::format(&self.source, msg));
        if self.vertex_count == 0 || self.triangles.is_empty() {
            return bad("the mesh has no vertices or no triangles".into());
        }
        for (i, t) in self.triangles.iter().enumerate() {
            if t.iter().any(|&v| v as usize >= self.vertex_count) {
                return bad(format!(
                    "triangle {i} {t:?} refers to a vertex >= {}",
                    self.vertex_count
                ));
            }
            if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
                return bad(format!("triangle {i} {t:?} repeats a vertex"));
            }
        }
        if self.uv.len() != self.vertex_count {
            return bad(format!(
                "{} UV coordinates for {} vertices",
                self.uv.len(),
                self.vertex_count
            ));
        }
        if let Some(i) = self.uv.iter().position(|p| {
            !p.iter()
                .all(|c| c.is_finite() && (-1e-6..=1.0 + 1e-6).contains(c))
        }) {
            return bad(format!(
                "UV coordinate {i} {:?} is outside [0, 1]",
                self.uv[i]
            ));
        }
        if self.landmarks.len() != LANDMARK_COUNT {
            return bad(format!(
                "{} landmarks, expected {LANDMARK_COUNT}",
                self.landmarks.len()
            ));
        }
        if let Some(i) = self
            .landmarks
            .iter()
            .position(|&v| v as usize >= self.vertex_count)
        {
            return bad(format!(
                "landmark {i} is vertex {} >= {}",
                self.landmarks[i], self.vertex_count
            ));
        }
        if let Some(t) = &self.template
            && t.len() != self.vertex_count
        {
            return bad(format!(
                "template has {} vertices, expected {}",
                t.len(),
                self.vertex_count
            ));
        }
        Ok(())
    }

    /// Reads the release's resource folder: `triangles.npy`, `uv_coords_std_202109.npy`
    /// (its first `V` rows), `kpt_ind.npy`, and `template_verts.npy` when present.
    pub fn from_resources(dir: &Path) -> Result<Self> {
        let tri_path = dir.join("triangles.npy");
        let tri = arkit_core::read_npy(&tri_path)?;
        if tri.shape().len() != 2 || tri.shape()[1] != 3 {
            return Err(Error::format(
                &tri_path,
                format!("expected shape (T, 3), found {:?}", tri.shape()),
            ));
        }
        let flat = tri.to_i64_vec().map_err(|e| e.in_file(&tri_path))?;
        let max = flat.iter().copied().max().unwrap_or(-1);
        if flat.iter().any(|&v| v < 0) {
            return Err(Error::format(&tri_path, "negative vertex index"));
        }
        let triangles: Vec<[u32; 3]> = flat
            .chunks(3)
            .map(|c| [c[0] as u32, c[1] as u32, c[2] as u32])
            .collect();

        let uv_path = dir.join("uv_coords_std_202109.npy");
        let uv_arr = arkit_core::read_npy(&uv_path)?;
        if uv_arr.shape().len() != 2 || uv_arr.shape()[1] != 2 {
            return Err(Error::format(
                &uv_path,
                format!("expected shape (N, 2), found {:?}", uv_arr.shape()),
            ));
        }
        let vertex_count = (max + 1) as usize;
        if uv_arr.shape()[0] < vertex_count {
            return Err(Error::format(
                &uv_path,
                format!(
                    "{} UV rows for {} mesh vertices",
                    uv_arr.shape()[0],
                    vertex_count
                ),
            ));
        }
        let uv_flat = uv_arr.to_f32_vec();
        let mut uv: Vec<[f32; 2]> = uv_flat.chunks(2).map(|c| [c[0], c[1]]).collect();
        let uv_extension = uv.split_off(vertex_count);

        let kpt_path = dir.join("kpt_ind.npy");
        let kpt = arkit_core::read_npy(&kpt_path)?;
        let landmarks: Vec<u32> = kpt
            .to_i64_vec()
            .map_err(|e| e.in_file(&kpt_path))?
            .into_iter()
            .map(|v| {
                u32::try_from(v).map_err(|_| {
                    Error::format(&kpt_path, format!("landmark index {v} is negative"))
                })
            })
            .collect::<Result<_>>()?;

        let template_path = dir.join("template_verts.npy");
        let template = if template_path.exists() {
            let t = arkit_core::read_npy(&template_path)?;
            if t.shape() != [vertex_count, 3] {
                return Err(Error::format(
                    &template_path,
                    format!("expected shape ({vertex_count}, 3), found {:?}", t.shape()),
                ));
            }
            let f = t.to_f32_vec();
            if f.iter().any(|v| !v.is_finite()) {
                return Err(Error::format(
                    &template_path,
                    "non-finite vertex coordinate",
                ));
            }
            Some(f.chunks(3).map(|c| Point3::new(c[0], c[1], c[2])).collect())
        } else {
            None
        };
        let topo = FaceTopology {
            source: dir.display().to_string(),
            vertex_count,
            triangles,
            uv,
            landmarks,
            template,
            uv_extension,
        };
        topo.validate()?;
        Ok(topo)
    }

    /// Reads an OBJ mesh (positions, triangles and texture coordinates) with the given
    /// 68 landmark indices, which refer to the file's vertex numbering. Positions become
    /// the template. Polygons are triangulated as fans; a vertex given two different
    /// UVs is an error.
    ///
    /// tobj renumbers a model's vertices in the order faces first use them; landmarks
    /// (and every other per-vertex table) need the file's own numbering, so it is
    /// recovered by matching each loaded position to the file's `v` lines (exact f32
    /// values, as both parse the same text). Two vertices at exactly the same position
    /// make that ambiguous and are reported.
    pub fn from_obj(path: &Path, landmarks: Vec<u32>) -> Result<Self> {
        let (models, _) = tobj::load_obj(
            path,
            &tobj::LoadOptions {
                triangulate: true,
                single_index: false,
                ..Default::default()
            },
        )
        .map_err(|e| Error::format(path, format!("cannot read OBJ: {e}")))?;
        if models.len() != 1 {
            return Err(Error::format(
                path,
                format!("expected one mesh, found {}", models.len()),
            ));
        }
        let mesh = &models[0].mesh;
        let file_positions = obj_vertex_lines(path)?;
        let bits = |p: &[f32]| [p[0].to_bits(), p[1].to_bits(), p[2].to_bits()];
        let mut by_position: HashMap<[u32; 3], u32> = HashMap::new();
        for (i, p) in file_positions.iter().enumerate() {
            if by_position.insert(bits(p), i as u32).is_some() {
                return Err(Error::format(
                    path,
                    format!(
                        "vertex {i} repeats the position of an earlier vertex; the numbering cannot be recovered"
                    ),
                ));
            }
        }
        let original: Vec<u32> = mesh
            .positions
            .chunks(3)
            .map(|p| {
                by_position
                    .get(&bits(p))
                    .copied()
                    .ok_or_else(|| Error::format(path, "a loaded position matches no 'v' line"))
            })
            .collect::<Result<_>>()?;
        let vertex_count = file_positions.len();
        let indices: Vec<u32> = mesh.indices.iter().map(|&i| original[i as usize]).collect();
        let triangles: Vec<[u32; 3]> = indices.chunks(3).map(|c| [c[0], c[1], c[2]]).collect();
        if mesh.texcoords.is_empty() {
            return Err(Error::format(
                path,
                "the OBJ has no texture coordinates (vt): UVs are required",
            ));
        }
        if mesh.texcoord_indices.len() != mesh.indices.len() {
            return Err(Error::format(
                path,
                "texture coordinates do not cover every face corner",
            ));
        }
        let mut uv = vec![[f32::NAN; 2]; vertex_count];
        for (&vi, &ti) in indices.iter().zip(&mesh.texcoord_indices) {
            let (vi, ti) = (vi as usize, ti as usize);
            // OBJ's v points up; ours points down.
            let t = [mesh.texcoords[2 * ti], 1.0 - mesh.texcoords[2 * ti + 1]];
            if uv[vi][0].is_nan() {
                uv[vi] = t;
            } else if (uv[vi][0] - t[0]).abs() > 1e-6 || (uv[vi][1] - t[1]).abs() > 1e-6 {
                return Err(Error::format(
                    path,
                    format!("vertex {vi} has two different texture coordinates"),
                ));
            }
        }
        if let Some(i) = uv.iter().position(|p| p[0].is_nan()) {
            return Err(Error::format(
                path,
                format!("vertex {i} has no texture coordinate (is it used by a face?)"),
            ));
        }
        let template = file_positions
            .iter()
            .map(|c| Point3::new(c[0], c[1], c[2]))
            .collect();
        let topo = FaceTopology {
            source: path.display().to_string(),
            vertex_count,
            triangles,
            uv,
            landmarks,
            template: Some(template),
            uv_extension: Vec::new(),
        };
        topo.validate()?;
        Ok(topo)
    }

    /// Writes the topology and `verts` as an OBJ (v, vt with v upward, f), so other
    /// tools can open a face; [`FaceTopology::from_obj`] reads it back.
    pub fn write_obj(&self, path: &Path, verts: &[Point3<f32>]) -> Result<()> {
        use std::fmt::Write as _;
        let mut s = String::new();
        let _ = writeln!(s, "# written by arkit-tool ({} vertices)", verts.len());
        for v in verts {
            let _ = writeln!(s, "v {} {} {}", v.x, v.y, v.z);
        }
        for t in &self.uv {
            let _ = writeln!(s, "vt {} {}", t[0], 1.0 - t[1]);
        }
        for t in &self.triangles {
            let _ = writeln!(
                s,
                "f {a}/{a} {b}/{b} {c}/{c}",
                a = t[0] + 1,
                b = t[1] + 1,
                c = t[2] + 1
            );
        }
        arkit_core::atomic_file::write_bytes(path, s.as_bytes())
    }

    /// Directed boundary edges `(a, b)`: edges used by exactly one triangle, in that
    /// triangle's orientation. Errors if an edge is shared by more than two triangles or
    /// twice in the same direction (a non-manifold or inconsistently oriented mesh).
    pub fn boundary_edges(&self) -> Result<Vec<(u32, u32)>> {
        let mut count: HashMap<(u32, u32), (u32, u32)> = HashMap::new(); // undirected -> (uses, (a,b) of first use)
        let mut first_dir: HashMap<(u32, u32), (u32, u32)> = HashMap::new();
        for t in &self.triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                let key = (a.min(b), a.max(b));
                let e = count.entry(key).or_insert((0, 0));
                e.0 += 1;
                first_dir.entry(key).or_insert((a, b));
                if e.0 > 2 {
                    return Err(Error::format(
                        &self.source,
                        format!("edge {a}-{b} is shared by more than two triangles"),
                    ));
                }
            }
        }
        let mut edges: Vec<(u32, u32)> = count
            .iter()
            .filter(|(_, (n, _))| *n == 1)
            .map(|(k, _)| first_dir[k])
            .collect();
        edges.sort_unstable();
        Ok(edges)
    }

    /// The boundary edges chained into closed loops, in no particular order. Errors
    /// where the boundary pinches (a vertex starts two boundary edges) or breaks off.
    pub(crate) fn unclassified_boundary_loops(&self) -> Result<Vec<BoundaryLoop>> {
        let edges = self.boundary_edges()?;
        let mut next: HashMap<u32, u32> = HashMap::new();
        for &(a, b) in &edges {
            if next.insert(a, b).is_some() {
                return Err(Error::format(
                    &self.source,
                    format!("vertex {a} starts two boundary edges (the boundary pinches there)"),
                ));
            }
        }
        let mut loops: Vec<BoundaryLoop> = Vec::new();
        let mut seen = std::collections::HashSet::new();
        for &(start, _) in &edges {
            if seen.contains(&start) {
                continue;
            }
            let mut l = vec![start];
            seen.insert(start);
            let mut cur = next[&start];
            while cur != start {
                if !seen.insert(cur) {
                    return Err(Error::format(
                        &self.source,
                        format!("boundary revisits vertex {cur}"),
                    ));
                }
                l.push(cur);
                cur = *next.get(&cur).ok_or_else(|| {
                    Error::format(&self.source, format!("boundary stops at vertex {cur}"))
                })?;
            }
            loops.push(l);
        }
        Ok(loops)
    }

    /// The boundary loops with their roles (see module docs). Needs 4 loops; the outer
    /// one is the longest, the others are told apart by the landmarks nearest to them
    /// (mouth: 60-67, right eye: 36-41, left eye: 42-47) measured along the mesh.
    pub fn boundary_loops(&self) -> Result<BoundaryLoops> {
        let mut loops = self.unclassified_boundary_loops()?;
        if loops.len() != 4 {
            return Err(Error::format(
                &self.source,
                format!(
                    "expected 4 boundary loops (outer contour, two eyes, mouth), found {}",
                    loops.len()
                ),
            ));
        }
        loops.sort_by_key(|l| std::cmp::Reverse(l.len()));
        let outer = loops.remove(0);
        // Hop distance on the mesh from each landmark group to each hole.
        let dist = |group: std::ops::Range<usize>, hole: &BoundaryLoop| -> usize {
            let d = self.hop_distances(hole);
            group.map(|i| d[self.landmarks[i] as usize]).sum()
        };
        let groups = [
            (LoopRole::Mouth, 60..68),
            (LoopRole::RightEye, 36..42),
            (LoopRole::LeftEye, 42..48),
        ];
        let mut result = vec![(LoopRole::Outer, outer)];
        let mut remaining = loops;
        for (role, range) in groups {
            let (best, _) = remaining
                .iter()
                .enumerate()
                .map(|(i, l)| (i, dist(range.clone(), l)))
                .min_by_key(|&(_, d)| d)
                .expect("three holes");
            result.push((role, remaining.remove(best)));
        }
        Ok(BoundaryLoops { loops: result })
    }

    /// Breadth-first hop counts from a set of vertices over the mesh edges.
    fn hop_distances(&self, sources: &[u32]) -> Vec<usize> {
        let mut adj = vec![Vec::new(); self.vertex_count];
        for t in &self.triangles {
            for k in 0..3 {
                adj[t[k] as usize].push(t[(k + 1) % 3]);
                adj[t[(k + 1) % 3] as usize].push(t[k]);
            }
        }
        let mut dist = vec![usize::MAX; self.vertex_count];
        let mut queue = std::collections::VecDeque::new();
        for &s in sources {
            dist[s as usize] = 0;
            queue.push_back(s);
        }
        while let Some(v) = queue.pop_front() {
            for &n in &adj[v as usize] {
                if dist[n as usize] == usize::MAX {
                    dist[n as usize] = dist[v as usize] + 1;
                    queue.push_back(n);
                }
            }
        }
        dist
    }

    /// Fan triangles closing the mouth and both eyes (see module docs).
    pub fn hole_fill(&self) -> Result<HoleFill> {
        let loops = self.boundary_loops()?;
        let mut centroids = Vec::new();
        let mut triangles = Vec::new();
        for (k, role) in [LoopRole::Mouth, LoopRole::RightEye, LoopRole::LeftEye]
            .into_iter()
            .enumerate()
        {
            let l = loops.get(role).expect("roles assigned").clone();
            let c = (self.vertex_count + k) as u32;
            // A boundary edge a->b runs along its triangle; the fan triangle uses b->a.
            for i in 0..l.len() {
                let (a, b) = (l[i], l[(i + 1) % l.len()]);
                triangles.push([b, a, c]);
            }
            centroids.push((role, l));
        }
        Ok(HoleFill {
            centroids,
            triangles,
        })
    }

    /// The left-right mirror map: vertex `i` of a face is vertex `map[i]` of its
    /// mirror image (used to flip samples). It is read from the UV layout, which is
    /// exactly symmetric under `u -> 1 - u` in the release (to 1e-7) and in the built-in
    /// face, so it does not depend on any one face being symmetric (a real face is not:
    /// nearest neighbours under `x -> -x` on the real template pair up only about 1,040
    /// of 1,220 vertices, and the mesh's connectivity is not symmetric either).
    /// Errors if the UV layout has no symmetric partner for some vertex.
    pub fn mirror_map(&self) -> Result<Vec<u32>> {
        // Bucket UVs on a grid so the search is near-linear.
        const CELL: f32 = 0.01;
        let key = |u: f32, v: f32| ((u / CELL).floor() as i64, (v / CELL).floor() as i64);
        let mut grid: HashMap<(i64, i64), Vec<u32>> = HashMap::new();
        for (i, t) in self.uv.iter().enumerate() {
            grid.entry(key(t[0], t[1])).or_default().push(i as u32);
        }
        let mut map = Vec::with_capacity(self.vertex_count);
        for (i, t) in self.uv.iter().enumerate() {
            let target = [1.0 - t[0], t[1]];
            let (cx, cy) = key(target[0], target[1]);
            let mut best = (u32::MAX, f32::INFINITY);
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for &j in grid
                        .get(&(cx + dx, cy + dy))
                        .map(|v| v.as_slice())
                        .unwrap_or(&[])
                    {
                        let q = self.uv[j as usize];
                        let d = (q[0] - target[0]).hypot(q[1] - target[1]);
                        if d < best.1 {
                            best = (j, d);
                        }
                    }
                }
            }
            if best.1 > 1e-4 {
                return Err(Error::format(
                    &self.source,
                    format!(
                        "the UV layout is not left-right symmetric: vertex {i} at UV {t:?} has no partner at u = 1 - u"
                    ),
                ));
            }
            map.push(best.0);
        }
        if let Some(v) = (0..self.vertex_count).find(|&v| map[map[v] as usize] as usize != v) {
            return Err(Error::format(
                &self.source,
                format!("the UV mirror map is not an involution at vertex {v}"),
            ));
        }
        Ok(map)
    }

    /// The source as a path, for error messages.
    pub fn source_path(&self) -> PathBuf {
        PathBuf::from(&self.source)
    }
}

/// The positions of an OBJ file's `v` lines, in file order.
fn obj_vertex_lines(path: &Path) -> Result<Vec<[f32; 3]>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let mut it = line.split_whitespace();
        if it.next() != Some("v") {
            continue;
        }
        let mut p = [0f32; 3];
        for c in &mut p {
            *c = it.next().and_then(|s| s.parse().ok()).ok_or_else(|| {
                Error::format(
                    path,
                    format!("line {}: a 'v' line needs three numbers", n + 1),
                )
            })?;
        }
        out.push(p);
    }
    Ok(out)
}

/// For each vertex, the vertex nearest to its mirror position `(-x, y, z)`, and the
/// largest such distance (metres): 0 on an exactly symmetric face. A measure of a
/// face's symmetry; the mirror map used for flipping is [`FaceTopology::mirror_map`].
pub fn nearest_mirror_partners(verts: &[Point3<f32>]) -> (Vec<u32>, f32) {
    let mut map = Vec::with_capacity(verts.len());
    let mut worst = 0.0f32;
    for v in verts {
        let m = Point3::new(-v.x, v.y, v.z);
        let (best, d2) = verts
            .iter()
            .enumerate()
            .map(|(j, w)| (j, (w - m).norm_squared()))
            .fold(
                (0, f32::INFINITY),
                |acc, x| if x.1 < acc.1 { x } else { acc },
            );
        worst = worst.max(d2.sqrt());
        map.push(best as u32);
    }
    (map, worst)
}

/// The iBUG-68 landmark mirror pairs: landmark `i` of a face is landmark
/// `LANDMARK_MIRROR[i]` of its mirror image.
pub const LANDMARK_MIRROR: [usize; LANDMARK_COUNT] = {
    let mut m = [0usize; LANDMARK_COUNT];
    let mut i = 0;
    while i < LANDMARK_COUNT {
        m[i] = match i {
            0..=16 => 16 - i,
            17..=26 => 43 - i,
            27..=30 => i,
            31..=35 => 66 - i,
            36..=39 => 81 - i,
            40 | 41 => 87 - i,
            42..=45 => 81 - i,
            46 | 47 => 87 - i,
            48..=54 => 102 - i,
            55..=59 => 114 - i,
            60..=64 => 124 - i,
            65..=67 => 132 - i,
            _ => i,
        };
        i += 1;
    }
    m
};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn landmark_mirror_is_an_involution_with_known_pairs() {
        for i in 0..LANDMARK_COUNT {
            assert_eq!(LANDMARK_MIRROR[LANDMARK_MIRROR[i]], i, "landmark {i}");
        }
        // Hand-checked pairs of the iBUG scheme.
        let pairs = [
            (0, 16),
            (8, 8),
            (17, 26),
            (21, 22),
            (30, 30),
            (31, 35),
            (33, 33),
            (36, 45),
            (39, 42),
            (40, 47),
            (41, 46),
            (37, 44),
            (48, 54),
            (51, 51),
            (57, 57),
            (55, 59),
            (60, 64),
            (62, 62),
            (66, 66),
            (65, 67),
        ];
        for (a, b) in pairs {
            assert_eq!(LANDMARK_MIRROR[a], b, "{a}");
        }
    }

    fn square_topology() -> FaceTopology {
        // A 4x4 grid of vertices with the centre cell removed: 1 outer loop and 1 hole.
        let mut triangles = Vec::new();
        for j in 0..3u32 {
            for i in 0..3u32 {
                if i == 1 && j == 1 {
                    continue;
                }
                let a = j * 4 + i;
                triangles.push([a, a + 1, a + 5]);
                triangles.push([a, a + 5, a + 4]);
            }
        }
        FaceTopology {
            source: "test grid".into(),
            vertex_count: 16,
            triangles,
            uv: vec![[0.5, 0.5]; 16],
            landmarks: vec![0; 68],
            template: None,
            uv_extension: Vec::new(),
        }
    }

    #[test]
    fn boundary_edges_of_a_grid_with_a_hole() {
        let t = square_topology();
        let e = t.boundary_edges().unwrap();
        // 12 outer edges and 4 around the hole.
        assert_eq!(e.len(), 16);
        // Only 2 loops, so the role assignment refuses it.
        assert!(
            t.boundary_loops()
                .unwrap_err()
                .to_string()
                .contains("found 2")
        );
    }

    #[test]
    fn non_manifold_edge_is_reported() {
        let mut t = square_topology();
        t.triangles.push([0, 1, 9]);
        t.triangles.push([1, 0, 10]);
        assert!(
            t.boundary_edges()
                .unwrap_err()
                .to_string()
                .contains("more than two")
        );
    }

    #[test]
    fn validate_names_the_problem() {
        let mut t = square_topology();
        t.triangles.push([0, 1, 99]);
        let msg = t.validate().unwrap_err().to_string();
        assert!(
            msg.starts_with("test grid:") && msg.contains("refers to a vertex"),
            "{msg}"
        );
        let mut t = square_topology();
        t.uv[3] = [1.5, 0.0];
        assert!(
            t.validate()
                .unwrap_err()
                .to_string()
                .contains("UV coordinate 3")
        );
    }

    #[test]
    fn mirror_map_of_a_symmetric_set() {
        let v = vec![
            Point3::new(-1.0, 0.0, 0.0),
            Point3::new(0.0, 1.0, 0.0),
            Point3::new(1.0, 0.0, 0.0),
        ];
        let (m, worst) = nearest_mirror_partners(&v);
        assert_eq!(m, vec![2, 1, 0]);
        assert_eq!(worst, 0.0);
    }
}

#[cfg(test)]
mod obj_tests {
    use super::*;

    #[test]
    fn obj_errors_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("no_uv.obj");
        std::fs::write(&path, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").unwrap();
        let e = FaceTopology::from_obj(&path, vec![0; 68])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("no_uv.obj") && e.contains("no texture coordinates"),
            "{e}"
        );
        let path = dir.path().join("bad_index.obj");
        std::fs::write(&path, "v 0 0 0\nvt 0 0\nf 1/1 2/1 9/1\n").unwrap();
        assert!(FaceTopology::from_obj(&path, vec![0; 68]).is_err());
    }
}
