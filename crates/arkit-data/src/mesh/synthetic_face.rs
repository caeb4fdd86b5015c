//! The built-in synthetic face: a stand-in for Apple's ARKit face topology.
//!
//! **This is not Apple's mesh.** It is our own construction, made so that every command
//! and test runs without the real download: a smooth, face-like triangle mesh with
//! exactly `VERTEX_COUNT` = 1,220 vertices (as ARKit's), an outer contour, two eye
//! holes and a mouth hole (4 boundary loops, as ARKit's), UV coordinates in the
//! release's orientation (u right, v down) and 68 landmark vertices in the iBUG roles,
//! placed where ARKit's landmarks are in the canonical frame (metres, y up, +z out of the
//! face). Identity and expression are smooth low-dimensional deformation fields
//! ([`FaceShapeModel`]) that also apply to the real ARKit template.
//!
//! Construction (deterministic, computed once per process, a few tens of milliseconds):
//! 1. A triangular lattice of spacing `h` over a parameter plane `(s, t)`, `s` right,
//!    `t` up, both in [-1, 1]; lattice points inside the face ellipse and outside the
//!    eye and mouth ellipses are kept; lattice triangles whose corners, edge midpoints
//!    and centroid avoid the holes are kept. The lattice is mirror-symmetric in `s`.
//! 2. `h` is scanned and the lattice with the most vertices not above 1,220 whose
//!    boundary is 4 clean loops is taken; boundary vertices are moved onto their ellipse.
//! 3. The missing vertices are added by splitting the longest interior edges in mirror
//!    pairs (an edge split keeps the mesh manifold and its boundary unchanged).
//! 4. `(s, t)` is embedded in 3D by a height field with a dome, a nose, brows, eye
//!    sockets, lips, cheekbones and a chin, sized like ARKit's template.

use crate::mesh::topology::{FaceTopology, LoopRole};
use nalgebra::{Point3, Vector3};
use std::collections::HashMap;
use std::sync::OnceLock;

/// Number of vertices, as in ARKit's face mesh.
pub(crate) const VERTEX_COUNT: usize = 1220;

/// An axis-aligned ellipse in the parameter plane.
#[derive(Clone, Copy, Debug)]
struct Ellipse {
    cs: f64,
    ct: f64,
    a: f64,
    b: f64,
}

impl Ellipse {
    fn level(&self, s: f64, t: f64) -> f64 {
        let (ds, dt) = ((s - self.cs) / self.a, (t - self.ct) / self.b);
        ds * ds + dt * dt
    }
    fn project(&self, s: f64, t: f64) -> [f64; 2] {
        let (ds, dt) = ((s - self.cs) / self.a, (t - self.ct) / self.b);
        let r = (ds * ds + dt * dt).sqrt();
        [self.cs + self.a * ds / r, self.ct + self.b * dt / r]
    }
    fn at_angle(&self, deg: f64) -> [f64; 2] {
        let r = deg.to_radians();
        [self.cs + self.a * r.cos(), self.ct + self.b * r.sin()]
    }
}

const OUTER: Ellipse = Ellipse {
    cs: 0.0,
    ct: 0.0,
    a: 1.0,
    b: 1.0,
};
const EYE_R: Ellipse = Ellipse {
    cs: -0.435,
    ct: 0.26,
    a: 0.19,
    b: 0.075,
};
const EYE_L: Ellipse = Ellipse {
    cs: 0.435,
    ct: 0.26,
    a: 0.19,
    b: 0.075,
};
const MOUTH: Ellipse = Ellipse {
    cs: 0.0,
    ct: -0.47,
    a: 0.27,
    b: 0.055,
};
const HOLES: [Ellipse; 3] = [MOUTH, EYE_R, EYE_L];

/// Half-width, half-height and vertical offset of the face in metres (ARKit-like).
const HALF_WIDTH_M: f64 = 0.078;
const HALF_HEIGHT_M: f64 = 0.0915;
const CENTRE_Y_M: f64 = 0.0012;

/// The built-in face: topology, neutral shape and the parameter of each vertex.
#[derive(Debug)]
pub struct SyntheticFace {
    /// The topology (source `"built-in synthetic face (stand-in, not Apple's ARKit mesh)"`),
    /// with the neutral shape as its template.
    pub topology: FaceTopology,
    /// The `(s, t)` parameter of each vertex.
    pub parameters: Vec<[f64; 2]>,
    /// The lattice spacing the construction chose.
    pub lattice_spacing: f64,
}

/// The built-in face, built on first use.
pub fn builtin() -> &'static SyntheticFace {
    static FACE: OnceLock<SyntheticFace> = OnceLock::new();
    FACE.get_or_init(build)
}

struct Lattice {
    params: Vec<[f64; 2]>,
    triangles: Vec<[u32; 3]>,
}

fn inside(s: f64, t: f64) -> bool {
    OUTER.level(s, t) < 1.0 && HOLES.iter().all(|h| h.level(s, t) > 1.0)
}

fn build_lattice(h: f64) -> Lattice {
    let row = h * 3f64.sqrt() / 2.0;
    let jmax = (1.0 / row).ceil() as i64 + 1;
    let imax = (1.0 / h).ceil() as i64 + 2;
    // Dense (i, j) -> vertex id table over the lattice's index box.
    let (ni, nj) = ((2 * imax + 1) as usize, (2 * jmax + 1) as usize);
    let mut table = vec![u32::MAX; ni * nj];
    let slot = |i: i64, j: i64| -> Option<usize> {
        (i.abs() <= imax && j.abs() <= jmax).then(|| (j + jmax) as usize * ni + (i + imax) as usize)
    };
    let mut params = Vec::new();
    let pos = |i: i64, j: i64| -> [f64; 2] {
        let off = if j.rem_euclid(2) == 1 { 0.5 } else { 0.0 };
        [(i as f64 + off) * h, j as f64 * row]
    };
    for j in -jmax..=jmax {
        for i in -imax..=imax {
            let p = pos(i, j);
            if inside(p[0], p[1]) {
                table[slot(i, j).expect("in the box")] = params.len() as u32;
                params.push(p);
            }
        }
    }
    let mut triangles = Vec::new();
    for j in -jmax..jmax {
        let lower_odd = j.rem_euclid(2) == 1;
        for i in -imax..imax {
            let cands: [[(i64, i64); 3]; 2] = if !lower_odd {
                [
                    [(i, j), (i + 1, j), (i, j + 1)],
                    [(i + 1, j), (i + 1, j + 1), (i, j + 1)],
                ]
            } else {
                [
                    [(i, j), (i + 1, j + 1), (i, j + 1)],
                    [(i, j), (i + 1, j), (i + 1, j + 1)],
                ]
            };
            for c in cands {
                let id =
                    |(i, j): (i64, i64)| slot(i, j).map(|k| table[k]).filter(|&v| v != u32::MAX);
                let (Some(a), Some(b), Some(d)) = (id(c[0]), id(c[1]), id(c[2])) else {
                    continue;
                };
                let (pa, pb, pd) = (params[a as usize], params[b as usize], params[d as usize]);
                let probes = [
                    [(pa[0] + pb[0] + pd[0]) / 3.0, (pa[1] + pb[1] + pd[1]) / 3.0],
                    [(pa[0] + pb[0]) / 2.0, (pa[1] + pb[1]) / 2.0],
                    [(pb[0] + pd[0]) / 2.0, (pb[1] + pd[1]) / 2.0],
                    [(pa[0] + pd[0]) / 2.0, (pa[1] + pd[1]) / 2.0],
                ];
                if probes.iter().all(|p| inside(p[0], p[1])) {
                    triangles.push([a, b, d]);
                }
            }
        }
    }
    // Drop unreferenced vertices.
    let mut used = vec![false; params.len()];
    for t in &triangles {
        for &v in t {
            used[v as usize] = true;
        }
    }
    let mut remap = vec![u32::MAX; params.len()];
    let mut kept = Vec::new();
    for (i, p) in params.iter().enumerate() {
        if used[i] {
            remap[i] = kept.len() as u32;
            kept.push(*p);
        }
    }
    for t in &mut triangles {
        for v in t.iter_mut() {
            *v = remap[*v as usize];
        }
    }
    Lattice {
        params: kept,
        triangles,
    }
}

fn placeholder_topology(l: &Lattice) -> FaceTopology {
    FaceTopology {
        source: "built-in synthetic face (stand-in, not Apple's ARKit mesh)".into(),
        vertex_count: l.params.len(),
        triangles: l.triangles.clone(),
        uv: l.params.iter().map(|p| param_to_uv(*p)).collect(),
        landmarks: vec![0; 68],
        template: None,
        uv_extension: Vec::new(),
    }
}

fn param_to_uv(p: [f64; 2]) -> [f32; 2] {
    [
        (0.03 + 0.94 * (p[0] + 1.0) / 2.0) as f32,
        (0.03 + 0.94 * (1.0 - p[1]) / 2.0) as f32,
    ]
}

/// Loops of a lattice, if its boundary is 4 clean loops.
fn clean_loops(l: &Lattice) -> Option<Vec<Vec<u32>>> {
    let loops = placeholder_topology(l).unclassified_boundary_loops().ok()?;
    (loops.len() == 4).then_some(loops)
}

fn split_edges_to(l: &mut Lattice, target: usize) {
    while l.params.len() < target {
        // Interior edges with their two triangles.
        let mut edge_tris: HashMap<(u32, u32), Vec<usize>> = HashMap::new();
        for (ti, t) in l.triangles.iter().enumerate() {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                edge_tris.entry((a.min(b), a.max(b))).or_default().push(ti);
            }
        }
        let len = |e: &(u32, u32)| {
            let (p, q) = (l.params[e.0 as usize], l.params[e.1 as usize]);
            ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt()
        };
        let need = target - l.params.len();
        let mut candidates: Vec<(u32, u32)> = edge_tris
            .iter()
            .filter(|(e, ts)| {
                let (p, q) = (l.params[e.0 as usize], l.params[e.1 as usize]);
                let self_mirror = (p[0] + q[0]).abs() < 1e-12;
                // Splits go in mirror pairs (one edge on each side), or one self-mirrored
                // edge when an odd count remains.
                ts.len() == 2
                    && if need % 2 == 1 {
                        self_mirror
                    } else {
                        p[0] + q[0] < -1e-12
                    }
            })
            .map(|(e, _)| *e)
            .collect();
        candidates.sort_by(|a, b| len(b).total_cmp(&len(a)).then(a.cmp(b)));
        let e = candidates[0];
        let mut to_split = vec![e];
        if need.is_multiple_of(2) {
            // Find the mirror edge.
            let (p, q) = (l.params[e.0 as usize], l.params[e.1 as usize]);
            let find = |x: [f64; 2]| {
                l.params
                    .iter()
                    .position(|r| (r[0] + x[0]).abs() < 1e-12 && (r[1] - x[1]).abs() < 1e-12)
                    .expect("symmetric mesh") as u32
            };
            let (mp, mq) = (find(p), find(q));
            to_split.push((mp.min(mq), mp.max(mq)));
        }
        for e in to_split {
            split_edge(l, e);
        }
    }
}

/// Boundary edges crossing the centre line symmetrically (`s_a = -s_b`).
fn centre_boundary_edges(l: &Lattice) -> Vec<(u32, u32)> {
    let mut uses: HashMap<(u32, u32), u32> = HashMap::new();
    for t in &l.triangles {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            *uses.entry((a.min(b), a.max(b))).or_default() += 1;
        }
    }
    let mut edges: Vec<(u32, u32)> = uses
        .into_iter()
        .filter(|(e, n)| {
            *n == 1
                && (l.params[e.0 as usize][0] + l.params[e.1 as usize][0]).abs() < 1e-12
                && l.params[e.0 as usize][0] != 0.0
        })
        .map(|(e, _)| e)
        .collect();
    edges.sort_unstable();
    edges
}

fn split_edge(l: &mut Lattice, e: (u32, u32)) {
    let (p, q) = (l.params[e.0 as usize], l.params[e.1 as usize]);
    let m = l.params.len() as u32;
    l.params.push([(p[0] + q[0]) / 2.0, (p[1] + q[1]) / 2.0]);
    let mut added = Vec::new();
    for t in l.triangles.iter_mut() {
        for k in 0..3 {
            let (a, b, c) = (t[k], t[(k + 1) % 3], t[(k + 2) % 3]);
            if (a.min(b), a.max(b)) == e {
                *t = [a, m, c];
                added.push([m, b, c]);
                break;
            }
        }
    }
    l.triangles.extend(added);
}

fn build() -> SyntheticFace {
    // 1-2: scan the lattice spacing.
    let mut best: Option<(f64, Lattice, Vec<Vec<u32>>)> = None;
    for k in 0..300 {
        let h = 0.075 - k as f64 * 0.0001;
        let l = build_lattice(h);
        // Cheap tests first: the size budget, then whether it would improve.
        let better = best
            .as_ref()
            .is_none_or(|b| l.params.len() > b.1.params.len());
        if !better
            || l.params.len() > VERTEX_COUNT
            || l.params.len() + centre_boundary_edges(&l).len() > VERTEX_COUNT
        {
            continue;
        }
        if let Some(loops) = clean_loops(&l) {
            best = Some((h, l, loops));
        }
    }
    let (h, mut lattice, loops) = best.expect("a lattice with 4 clean boundary loops exists");
    // Move boundary vertices onto their ellipse: each loop goes to the curve it lies
    // nearest to on average (distance approximated in the ellipse's own scale).
    for lp in &loops {
        let distance = |e: &Ellipse| -> f64 {
            lp.iter()
                .map(|&v| {
                    let p = lattice.params[v as usize];
                    (e.level(p[0], p[1]).sqrt() - 1.0).abs() * e.a.min(e.b)
                })
                .sum::<f64>()
        };
        let curve = HOLES
            .iter()
            .chain(std::iter::once(&OUTER))
            .min_by(|a, b| distance(a).total_cmp(&distance(b)))
            .expect("curves");
        for &v in lp {
            let p = lattice.params[v as usize];
            lattice.params[v as usize] = curve.project(p[0], p[1]);
        }
    }
    // Give the outer contour and the mouth a vertex on the centre line (chin, lips).
    for e in centre_boundary_edges(&lattice) {
        let p = lattice.params[e.0 as usize];
        let curve = if MOUTH.level(0.0, p[1]) < 4.0 {
            MOUTH
        } else {
            OUTER
        };
        split_edge(&mut lattice, e);
        let m = lattice.params.len() - 1;
        let q = lattice.params[m];
        lattice.params[m] = curve.project(q[0], q[1]);
    }
    // 3: exact vertex count.
    split_edges_to(&mut lattice, VERTEX_COUNT);
    let verts: Vec<Point3<f32>> = lattice.params.iter().map(|p| embed(*p)).collect();
    let mut topology = placeholder_topology(&lattice);
    topology.template = Some(verts.clone());
    topology.landmarks = place_landmarks(&topology, &lattice.params);
    topology.validate().expect("the built-in face is valid");
    SyntheticFace {
        topology,
        parameters: lattice.params,
        lattice_spacing: h,
    }
}

/// Landmark targets in the parameter plane, with the loop they must lie on (if any).
fn landmark_targets() -> Vec<([f64; 2], Option<LoopRole>)> {
    let mut t = Vec::with_capacity(68);
    for k in 0..17 {
        t.push((
            OUTER.at_angle(190.0 + k as f64 * 10.0),
            Some(LoopRole::Outer),
        ));
    }
    let brow = |s: f64| [s, 0.50 + 0.07 * (1.0 - ((s.abs() - 0.42) / 0.3).powi(2))];
    for s in [-0.72, -0.6, -0.46, -0.32, -0.18] {
        t.push((brow(s), None));
    }
    for s in [0.18, 0.32, 0.46, 0.6, 0.72] {
        t.push((brow(s), None));
    }
    for tt in [0.22, 0.1, -0.02, -0.07] {
        t.push(([0.0, tt], None));
    }
    for s in [-0.16, -0.08, 0.0, 0.08, 0.16] {
        t.push(([s, -0.2 + 0.03 * (s.abs() / 0.16)], None));
    }
    for a in [180.0, 120.0, 60.0, 0.0, -60.0, -120.0] {
        t.push((EYE_R.at_angle(a), Some(LoopRole::RightEye)));
    }
    for a in [180.0, 120.0, 60.0, 0.0, -60.0, -120.0] {
        t.push((EYE_L.at_angle(a), Some(LoopRole::LeftEye)));
    }
    let outer_lip = Ellipse {
        cs: 0.0,
        ct: -0.47,
        a: 0.36,
        b: 0.16,
    };
    for k in 0..12 {
        t.push((outer_lip.at_angle(180.0 - 30.0 * k as f64), None));
    }
    for k in 0..8 {
        t.push((
            MOUTH.at_angle(180.0 - 45.0 * k as f64),
            Some(LoopRole::Mouth),
        ));
    }
    t
}

fn place_landmarks(topo: &FaceTopology, params: &[[f64; 2]]) -> Vec<u32> {
    // Loops by role, from the mesh; landmark roles are not known yet, so tell the holes
    // apart by position here.
    let edges = topo.boundary_edges().expect("manifold");
    let on_boundary: std::collections::HashSet<u32> = edges.iter().map(|e| e.0).collect();
    let role_of = |v: u32| -> Option<LoopRole> {
        if !on_boundary.contains(&v) {
            return None;
        }
        let p = params[v as usize];
        let d = |e: &Ellipse| (e.level(p[0], p[1]) - 1.0).abs();
        let cands = [
            (LoopRole::Outer, d(&OUTER)),
            (LoopRole::Mouth, d(&MOUTH)),
            (LoopRole::RightEye, d(&EYE_R)),
            (LoopRole::LeftEye, d(&EYE_L)),
        ];
        cands.iter().min_by(|a, b| a.1.total_cmp(&b.1)).map(|c| c.0)
    };
    let mirror_of = |v: u32| -> u32 {
        let p = params[v as usize];
        params
            .iter()
            .position(|q| (q[0] + p[0]).abs() < 1e-9 && (q[1] - p[1]).abs() < 1e-9)
            .expect("symmetric mesh") as u32
    };
    let targets = landmarks_targets_cached();
    let mut chosen = vec![u32::MAX; 68];
    // The nose tip first: the most forward vertex on the centre line.
    chosen[crate::mesh::topology::NOSE_TIP_LANDMARK] = (0..params.len() as u32)
        .filter(|&v| params[v as usize][0].abs() < 1e-9)
        .max_by(|&a, &b| {
            embed(params[a as usize])
                .z
                .total_cmp(&embed(params[b as usize]).z)
                .then(b.cmp(&a))
        })
        .expect("centre-line vertices");
    for (i, (target, role)) in targets.iter().enumerate() {
        let mirror = crate::mesh::topology::LANDMARK_MIRROR[i];
        if target[0] > 1e-9 && mirror != i && chosen[mirror] != u32::MAX {
            chosen[i] = mirror_of(chosen[mirror]);
            continue;
        }
        let centre_line = target[0].abs() < 1e-9;
        if i == crate::mesh::topology::NOSE_TIP_LANDMARK {
            continue;
        }
        let best = (0..params.len() as u32)
            .filter(|&v| role.is_none_or(|r| role_of(v) == Some(r)))
            .filter(|&v| {
                !centre_line
                    || params[v as usize][0].abs() < 1e-9
                    || !has_centre_vertex(params, role, &role_of)
            })
            .filter(|&v| !chosen.contains(&v))
            .min_by(|&a, &b| {
                let d = |v: u32| {
                    let p = params[v as usize];
                    (p[0] - target[0]).powi(2) + (p[1] - target[1]).powi(2)
                };
                d(a).total_cmp(&d(b)).then(a.cmp(&b))
            })
            .expect("a vertex for every landmark");
        chosen[i] = best;
    }
    chosen
}

fn has_centre_vertex(
    params: &[[f64; 2]],
    role: &Option<LoopRole>,
    role_of: &dyn Fn(u32) -> Option<LoopRole>,
) -> bool {
    (0..params.len() as u32)
        .any(|v| params[v as usize][0].abs() < 1e-9 && role.is_none_or(|r| role_of(v) == Some(r)))
}

fn landmarks_targets_cached() -> &'static Vec<([f64; 2], Option<LoopRole>)> {
    static T: OnceLock<Vec<([f64; 2], Option<LoopRole>)>> = OnceLock::new();
    T.get_or_init(landmark_targets)
}

fn gauss(x: f64, c: f64, w: f64) -> f64 {
    let d = (x - c) / w;
    (-d * d).exp()
}

fn smoothstep(e0: f64, e1: f64, x: f64) -> f64 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// The neutral 3D position (metres) of parameter `(s, t)`.
fn embed(p: [f64; 2]) -> Point3<f32> {
    let [s, t] = p;
    let taper = 1.0 - 0.16 * smoothstep(0.0, 1.0, -t);
    let x = HALF_WIDTH_M * s * taper;
    let y = HALF_HEIGHT_M * t + CENTRE_Y_M;
    let dome = (1.0 - s * s).max(0.0).powf(0.55) * (1.0 - 0.28 * t * t);
    let mut z = -0.025 + 0.070 * dome;
    // Nose: a ridge from the bridge to the tip, then a quick fall to the base.
    let ridge = smoothstep(0.32, -0.07, t) * (1.0 - smoothstep(-0.07, -0.2, t))
        + 0.25 * smoothstep(0.45, 0.3, t) * smoothstep(-0.2, 0.3, t);
    let width = 0.11 + 0.08 * smoothstep(0.2, -0.15, t);
    z += 0.024 * ridge.min(1.0) * gauss(s, 0.0, width);
    // Nostril wings.
    z += 0.004 * (gauss(s, -0.14, 0.06) + gauss(s, 0.14, 0.06)) * gauss(t, -0.16, 0.05);
    // Eye sockets and brows.
    for cs in [-0.435, 0.435] {
        z -= 0.007 * gauss(s, cs, 0.22) * gauss(t, 0.26, 0.13);
        z += 0.004 * gauss(s, cs, 0.3) * gauss(t, 0.52, 0.08);
        // Cheekbones.
        z += 0.004 * gauss(s, cs * 1.2, 0.18) * gauss(t, -0.05, 0.15);
    }
    // Lips and chin.
    z += 0.008 * gauss(s, 0.0, 0.3) * gauss(t, -0.47, 0.12);
    z += 0.014 * gauss(s, 0.0, 0.3) * gauss(t, -0.85, 0.15);
    Point3::new(x as f32, y as f32, z as f32)
}

/// Number of identity coefficients of [`FaceShapeModel`].
pub(crate) const IDENTITY_DIMS: usize = 6;
/// Number of expression coefficients of [`FaceShapeModel`].
pub(crate) const EXPRESSION_DIMS: usize = 4;

/// Smooth identity and expression deformations of a neutral face, defined on the
/// canonical position so that they apply to any ARKit-like face (built-in or real).
///
/// Identity (coefficients about N(0, 1)): face width, face length, nose protrusion,
/// jaw width, roundness, brow ridge. Expression (coefficients in [0, 1]): mouth open,
/// smile, brows raised, eyes narrowed.
#[derive(Clone, Debug)]
pub struct FaceShapeModel {
    /// The neutral face (metres, canonical frame).
    pub neutral: Vec<Point3<f32>>,
}

impl FaceShapeModel {
    /// A model over a neutral face.
    pub fn new(neutral: Vec<Point3<f32>>) -> Self {
        FaceShapeModel { neutral }
    }

    /// The face of an identity and an expression.
    pub fn shape(
        &self,
        identity: &[f64; IDENTITY_DIMS],
        expression: &[f64; EXPRESSION_DIMS],
    ) -> Vec<Point3<f32>> {
        self.neutral
            .iter()
            .map(|p| deform(p, identity, expression))
            .collect()
    }
}

fn deform(p: &Point3<f32>, id: &[f64; IDENTITY_DIMS], ex: &[f64; EXPRESSION_DIMS]) -> Point3<f32> {
    let (x, y, z) = (p.x as f64, p.y as f64, p.z as f64);
    let (s, t) = (x / HALF_WIDTH_M, (y - CENTRE_Y_M) / HALF_HEIGHT_M);
    let lower = smoothstep(0.0, -0.8, t);
    let mut d = Vector3::new(0.0, 0.0, 0.0);
    d.x += x * (0.06 * id[0] + 0.06 * id[3] * lower);
    d.y += (y - CENTRE_Y_M) * 0.05 * id[1];
    d.z += 0.006 * id[2] * gauss(s, 0.0, 0.15) * gauss(t, -0.02, 0.2);
    d.z += 0.006 * id[4] * (1.0 - s * s).max(0.0);
    d.z += 0.003 * id[5] * gauss(t, 0.45, 0.12);
    // Expressions.
    let jaw = smoothstep(-0.45, -0.6, t) * gauss(s, 0.0, 0.6);
    d.y -= 0.012 * ex[0] * jaw;
    let corners = gauss(t, -0.47, 0.12) * (gauss(s, -0.3, 0.12) + gauss(s, 0.3, 0.12));
    d.y += 0.006 * ex[1] * corners;
    d.x += 0.004 * ex[1] * corners * s.signum();
    d.y += 0.005 * ex[2] * gauss(t, 0.52, 0.12) * gauss(s.abs(), 0.43, 0.3);
    for cs in [-0.435, 0.435] {
        let around = gauss(s, cs, 0.2) * gauss(t, 0.26, 0.1);
        d.y -= 0.25 * (y - (0.26 * HALF_HEIGHT_M + CENTRE_Y_M)) * ex[3] * around;
    }
    Point3::new((x + d.x) as f32, (y + d.y) as f32, (z + d.z) as f32)
}

#[cfg(test)]
mod tests {
    #[test]
    fn obj_round_trip_of_the_built_in_face() {
        let topo = &builtin().topology;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("face.obj");
        topo.write_obj(&path, topo.template.as_ref().unwrap())
            .unwrap();
        let back =
            crate::mesh::topology::FaceTopology::from_obj(&path, topo.landmarks.clone()).unwrap();
        assert_eq!(back.vertex_count, topo.vertex_count);
        assert_eq!(back.triangles, topo.triangles);
        for (a, b) in back.uv.iter().zip(&topo.uv) {
            assert!((a[0] - b[0]).abs() < 1e-6 && (a[1] - b[1]).abs() < 1e-6);
        }
        for (a, b) in back
            .template
            .unwrap()
            .iter()
            .zip(topo.template.as_ref().unwrap())
        {
            assert!((a - b).norm() < 1e-7);
        }
    }

    use super::*;
    use crate::mesh::topology::{LANDMARK_MIRROR, NOSE_TIP_LANDMARK, nearest_mirror_partners};

    #[test]
    fn exact_counts_and_four_loops() {
        let face = builtin();
        let topo = &face.topology;
        assert_eq!(topo.vertex_count, VERTEX_COUNT);
        assert_eq!(topo.landmarks.len(), 68);
        let loops = topo.boundary_loops().unwrap();
        assert_eq!(loops.loops.len(), 4);
        // Euler characteristic of a disc with three holes: V - E + F = -2.
        let mut edges = std::collections::HashSet::new();
        for t in &topo.triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                edges.insert((a.min(b), a.max(b)));
            }
        }
        let chi = topo.vertex_count as i64 - edges.len() as i64 + topo.triangles.len() as i64;
        assert_eq!(chi, -2);
        // Landmarks are distinct.
        let set: std::collections::HashSet<_> = topo.landmarks.iter().collect();
        assert_eq!(set.len(), 68);
    }

    #[test]
    fn triangles_face_the_front() {
        let topo = &builtin().topology;
        let v = topo.template.as_ref().unwrap();
        for t in &topo.triangles {
            let (a, b, c) = (v[t[0] as usize], v[t[1] as usize], v[t[2] as usize]);
            let n = (b - a).cross(&(c - a));
            assert!(n.z > 0.0, "triangle {t:?} faces back");
        }
    }

    #[test]
    fn exactly_mirror_symmetric_with_mirrored_landmarks() {
        let topo = &builtin().topology;
        let v = topo.template.as_ref().unwrap();
        let (map, worst) = nearest_mirror_partners(v);
        assert!(worst < 1e-6, "{worst}");
        // The UV-derived map used for flipping agrees with the geometry exactly.
        assert_eq!(topo.mirror_map().unwrap(), map);
        for i in 0..v.len() {
            assert_eq!(map[map[i] as usize] as usize, i);
        }
        for i in 0..68 {
            assert_eq!(
                map[topo.landmarks[i] as usize], topo.landmarks[LANDMARK_MIRROR[i]],
                "landmark {i}"
            );
        }
    }

    #[test]
    fn landmarks_sit_in_their_roles() {
        let topo = &builtin().topology;
        let v = topo.template.as_ref().unwrap();
        let lm = |i: usize| v[topo.landmarks[i] as usize];
        // Nose tip is the most forward landmark; chin lowest; right-side landmarks at x<0.
        let tip = lm(NOSE_TIP_LANDMARK);
        assert!((0..68).all(|i| lm(i).z <= tip.z));
        assert!((0..68).all(|i| lm(i).y >= lm(8).y - 1e-6));
        assert!(lm(0).x < 0.0 && lm(16).x > 0.0 && lm(36).x < lm(39).x && lm(39).x < 0.0);
        // Eyes above the nose tip, mouth below it, brows above eyes.
        assert!(lm(37).y > tip.y && lm(62).y < tip.y && lm(19).y > lm(37).y);
        // Sized like the ARKit template: ~16 cm wide, ~18 cm tall.
        let (xmin, xmax) = v
            .iter()
            .fold((f32::MAX, f32::MIN), |a, p| (a.0.min(p.x), a.1.max(p.x)));
        let (ymin, ymax) = v
            .iter()
            .fold((f32::MAX, f32::MIN), |a, p| (a.0.min(p.y), a.1.max(p.y)));
        assert!((0.14..0.17).contains(&(xmax - xmin)) && (0.17..0.19).contains(&(ymax - ymin)));
        // Each hole's landmarks lie on that hole's loop.
        let loops = topo.boundary_loops().unwrap();
        for (role, range) in [
            (LoopRole::Mouth, 60..68),
            (LoopRole::RightEye, 36..42),
            (LoopRole::LeftEye, 42..48),
        ] {
            let l = loops.get(role).unwrap();
            for i in range {
                assert!(
                    l.contains(&topo.landmarks[i]),
                    "landmark {i} not on {role:?}"
                );
            }
        }
    }

    #[test]
    fn deformations_are_smooth_and_zero_at_rest() {
        let face = builtin();
        let model = FaceShapeModel::new(face.topology.template.clone().unwrap());
        assert_eq!(model.shape(&[0.0; 6], &[0.0; 4]), model.neutral);
        let open = model.shape(&[0.0; 6], &[1.0, 0.0, 0.0, 0.0]);
        let lm = &face.topology.landmarks;
        // Opening the mouth moves the lower lip (66) down and leaves the nose tip.
        assert!(open[lm[66] as usize].y < model.neutral[lm[66] as usize].y - 0.005);
        assert!((open[lm[30] as usize] - model.neutral[lm[30] as usize]).norm() < 1e-4);
        let wide = model.shape(&[1.0, 0.0, 0.0, 0.0, 0.0, 0.0], &[0.0; 4]);
        assert!(wide[lm[16] as usize].x > model.neutral[lm[16] as usize].x * 1.05);
    }
}
