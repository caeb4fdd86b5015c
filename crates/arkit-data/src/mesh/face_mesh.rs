//! [`FaceMesh`]: one predicted face in camera space, as files other tools open.
//!
//! A face's vertices (the release's camera frame: x right, y up, looking down -z;
//! metres) over its topology's triangles and UVs, written as Wavefront OBJ
//! ([`FaceMesh::write_obj`]) and ASCII PLY ([`FaceMesh::write_ply`]), and its landmarks
//! (the topology's 68 landmark vertices, `kpt_ind.npy` for the release) as a small JSON
//! ([`FaceMesh::write_landmarks`]). Every file goes through the atomic-file helper.
//!
//! Both mesh formats carry the same numbers: vertex `i` is the topology's vertex `i`
//! (0-based in PLY, `i + 1` in OBJ), each with its one UV coordinate written as
//! `(u, 1 - v)`: the topology's v points down the texture (as the release's UV file),
//! OBJ's `vt` and PLY's `s t` point up. Coordinates are printed as Rust's shortest text
//! that reads back to the same `f64` (`f32` for the UVs).

use crate::mesh::topology::FaceTopology;
use arkit_core::{Error, Result};
use nalgebra::Point3;
use std::fmt::Write as _;
use std::path::Path;

/// One face's mesh in camera space.
#[derive(Clone, Debug)]
pub struct FaceMesh<'a> {
    /// The triangles, UVs and landmark vertices.
    pub topology: &'a FaceTopology,
    /// The vertices, in the release's camera frame, metres (one per topology vertex).
    pub vertices: Vec<Point3<f64>>,
}

/// The frame a [`FaceMesh`]'s files are in, in words (written into each file).
pub const FACE_MESH_FRAME: &str =
    "camera space, the release's frame (x right, y up, looking down -z), metres";

impl<'a> FaceMesh<'a> {
    /// A mesh of `vertices` over `topology`: one vertex per topology vertex, all finite.
    pub fn new(topology: &'a FaceTopology, vertices: Vec<Point3<f64>>) -> Result<Self> {
        if vertices.len() != topology.vertex_count {
            return Err(Error::invalid(
                "face mesh",
                format!(
                    "{} vertices for a topology of {}",
                    vertices.len(),
                    topology.vertex_count
                ),
            ));
        }
        if vertices.iter().any(|p| !p.iter().all(|v| v.is_finite())) {
            return Err(Error::invalid("face mesh", "a vertex is not finite"));
        }
        Ok(FaceMesh { topology, vertices })
    }

    /// The Wavefront OBJ text: a comment naming the frame, `v`, `vt`, then `f a/a b/b
    /// c/c` (1-based; each vertex's UV has its index).
    pub fn obj_text(&self) -> String {
        let mut s = String::with_capacity(self.vertices.len() * 80);
        let _ = writeln!(
            s,
            "# arkit-tool face mesh: {} vertices, {} triangles; {FACE_MESH_FRAME}",
            self.vertices.len(),
            self.topology.triangles.len()
        );
        for p in &self.vertices {
            let _ = writeln!(s, "v {} {} {}", p.x, p.y, p.z);
        }
        for t in &self.topology.uv {
            let _ = writeln!(s, "vt {} {}", t[0], 1.0 - t[1]);
        }
        for t in &self.topology.triangles {
            let (a, b, c) = (t[0] + 1, t[1] + 1, t[2] + 1);
            let _ = writeln!(s, "f {a}/{a} {b}/{b} {c}/{c}");
        }
        s
    }

    /// The ASCII PLY text: vertices with `x y z` (double) and `s t` (float, the UV),
    /// faces as `vertex_indices` lists (0-based).
    pub fn ply_text(&self) -> String {
        let mut s = String::with_capacity(self.vertices.len() * 90);
        let _ = write!(
            s,
            "ply\nformat ascii 1.0\ncomment arkit-tool face mesh: {FACE_MESH_FRAME}\n\
             element vertex {}\nproperty double x\nproperty double y\nproperty double z\n\
             property float s\nproperty float t\n\
             element face {}\nproperty list uchar int vertex_indices\nend_header\n",
            self.vertices.len(),
            self.topology.triangles.len()
        );
        for (p, t) in self.vertices.iter().zip(&self.topology.uv) {
            let _ = writeln!(s, "{} {} {} {} {}", p.x, p.y, p.z, t[0], 1.0 - t[1]);
        }
        for t in &self.topology.triangles {
            let _ = writeln!(s, "3 {} {} {}", t[0], t[1], t[2]);
        }
        s
    }

    /// Writes [`FaceMesh::obj_text`] to `path` (atomically).
    pub fn write_obj(&self, path: &Path) -> Result<()> {
        arkit_core::atomic_file::write_bytes(path, self.obj_text().as_bytes())
    }

    /// Writes [`FaceMesh::ply_text`] to `path` (atomically).
    pub fn write_ply(&self, path: &Path) -> Result<()> {
        arkit_core::atomic_file::write_bytes(path, self.ply_text().as_bytes())
    }

    /// The landmark vertices' positions (camera space), in the topology's landmark order.
    pub fn landmark_points(&self) -> Vec<Point3<f64>> {
        self.topology
            .landmarks
            .iter()
            .map(|&i| self.vertices[i as usize])
            .collect()
    }

    /// The landmarks as JSON: `frame`, `vertex_ids` (the topology's landmark vertices,
    /// `kpt_ind.npy` for the release), `points_m` (camera space, metres), `pixels`
    /// (`pixels[k]`, where landmark `k` falls in the image, `null` behind the camera:
    /// the caller projects them, in the pixels it says in `about`), and `about`'s keys.
    pub fn landmarks_json(
        &self,
        pixels: &[Option<(f64, f64)>],
        about: serde_json::Map<String, serde_json::Value>,
    ) -> Result<serde_json::Value> {
        if pixels.len() != self.topology.landmarks.len() {
            return Err(Error::invalid(
                "landmark pixels",
                format!(
                    "{} pixels for {} landmarks",
                    pixels.len(),
                    self.topology.landmarks.len()
                ),
            ));
        }
        let mut out = about;
        out.insert("frame".into(), FACE_MESH_FRAME.into());
        out.insert(
            "vertex_ids".into(),
            serde_json::json!(self.topology.landmarks),
        );
        let points: Vec<[f64; 3]> = self
            .landmark_points()
            .iter()
            .map(|p| [p.x, p.y, p.z])
            .collect();
        out.insert("points_m".into(), serde_json::json!(points));
        let px: Vec<Option<[f64; 2]>> = pixels.iter().map(|p| p.map(|(x, y)| [x, y])).collect();
        out.insert("pixels".into(), serde_json::json!(px));
        Ok(serde_json::Value::Object(out))
    }

    /// Writes [`FaceMesh::landmarks_json`] to `path` (atomically).
    pub fn write_landmarks(
        &self,
        path: &Path,
        pixels: &[Option<(f64, f64)>],
        about: serde_json::Map<String, serde_json::Value>,
    ) -> Result<()> {
        let v = self.landmarks_json(pixels, about)?;
        let text = serde_json::to_string_pretty(&v).expect("json");
        arkit_core::atomic_file::write_bytes(path, text.as_bytes())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn a_mesh(topology: &FaceTopology) -> FaceMesh<'_> {
        // The built-in face moved in front of the camera, with awkward decimals.
        let verts = topology
            .template
            .as_ref()
            .expect("the built-in face has a template")
            .iter()
            .enumerate()
            .map(|(i, p)| {
                Point3::new(
                    p.x as f64 + 0.1 / 3.0,
                    p.y as f64 - 1e-7 * i as f64,
                    p.z as f64 - 0.4,
                )
            })
            .collect();
        FaceMesh::new(topology, verts).unwrap()
    }

    #[test]
    fn the_obj_reads_back_through_tobj_with_the_same_triangles_and_uvs() {
        let topology = &crate::mesh::builtin().topology;
        let mesh = a_mesh(topology);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("face.obj");
        mesh.write_obj(&path).unwrap();
        // `from_obj` reads through tobj, and restores the file's own vertex order.
        let back = FaceTopology::from_obj(&path, topology.landmarks.clone()).unwrap();
        assert_eq!(back.triangles, topology.triangles);
        assert_eq!(back.vertex_count, topology.vertex_count);
        for (a, b) in back.uv.iter().zip(&topology.uv) {
            // from_obj turns vt's upward v back down.
            assert!((a[0] - b[0]).abs() < 1e-6 && (a[1] - b[1]).abs() < 1e-6);
        }
        for (a, b) in back.template.unwrap().iter().zip(&mesh.vertices) {
            assert_eq!(*a, b.cast::<f32>());
        }
        // The text holds each f64 exactly.
        let text = mesh.obj_text();
        let v: Vec<f64> = text
            .lines()
            .find(|l| l.starts_with("v "))
            .unwrap()
            .split_whitespace()
            .skip(1)
            .map(|x| x.parse().unwrap())
            .collect();
        let p = mesh.vertices[0];
        assert_eq!(v, [p.x, p.y, p.z]);
    }

    #[test]
    fn the_ply_holds_the_same_vertices_uvs_and_faces() {
        let topology = &crate::mesh::builtin().topology;
        let mesh = a_mesh(topology);
        let text = mesh.ply_text();
        let (header, body) = text.split_once("end_header\n").unwrap();
        assert!(header.contains(&format!("element vertex {}", topology.vertex_count)));
        assert!(header.contains(&format!("element face {}", topology.triangles.len())));
        let lines: Vec<&str> = body.lines().collect();
        assert_eq!(
            lines.len(),
            topology.vertex_count + topology.triangles.len()
        );
        for (i, line) in lines[..topology.vertex_count].iter().enumerate() {
            let f: Vec<f64> = line.split(' ').map(|x| x.parse().unwrap()).collect();
            let p = mesh.vertices[i];
            assert_eq!(&f[..3], &[p.x, p.y, p.z]);
            assert_eq!(f[3] as f32, topology.uv[i][0]);
            assert_eq!(f[4] as f32, 1.0 - topology.uv[i][1]);
        }
        for (line, t) in lines[topology.vertex_count..]
            .iter()
            .zip(&topology.triangles)
        {
            assert_eq!(*line, format!("3 {} {} {}", t[0], t[1], t[2]));
        }
    }

    #[test]
    fn landmarks_are_the_topologys_vertices_and_bad_input_is_refused() {
        let topology = &crate::mesh::builtin().topology;
        let mesh = a_mesh(topology);
        let n = topology.landmarks.len();
        let pixels: Vec<Option<(f64, f64)>> = (0..n).map(|k| Some((k as f64, 2.0))).collect();
        let v = mesh
            .landmarks_json(&pixels, serde_json::Map::new())
            .unwrap();
        let k = 30;
        let id = topology.landmarks[k] as usize;
        assert_eq!(v["vertex_ids"][k], id);
        assert_eq!(v["points_m"][k][2], mesh.vertices[id].z);
        assert_eq!(v["pixels"][k][0], k as f64);
        assert!(
            mesh.landmarks_json(&pixels[1..], serde_json::Map::new())
                .is_err()
        );
        assert!(FaceMesh::new(topology, mesh.vertices[1..].to_vec()).is_err());
        let mut bad = mesh.vertices.clone();
        bad[3].y = f64::NAN;
        assert!(FaceMesh::new(topology, bad).is_err());
    }
}
