//! `uv_map`: the UV position map ([`UvMapper`], stage 4 of `face`'s docs): the
//! canonical face drawn in UV space, each texel holding the 3D position interpolated
//! over the UV triangles, including the ring outside the contour and the three hole
//! centroids; rasterized once per map size ([`UvTexels`], whose lanes are
//! `lanes::texels`) and filled per mesh. Tested in `face`'s tests (the map against the
//! scalar sum, its clamped planes, the vertices given back).

use crate::lanes;
use crate::lanes::texels::TexelWeights;
pub use crate::lanes::texels::UvTexels;
use crate::mesh::topology::{FaceTopology, LoopRole};
use arkit_core::{Result, ScreenVertex, VisibilityBuffer};
use nalgebra::Point3;

/// The UV layout extended beyond the mesh, and the UV-space triangles over it.
#[derive(Clone, Debug)]
pub struct UvMapper {
    /// UV coordinates of the mesh vertices, then the ring, then the hole centroids.
    pub uv: Vec<[f32; 2]>,
    /// Triangles over those UV vertices: mesh, ring, hole fans.
    pub triangles: Vec<[u32; 3]>,
    /// The mesh vertex each ring vertex is pushed out from.
    pub ring_of: Vec<u32>,
    /// The hole loops whose centroids come after the ring (mouth, right eye, left eye).
    pub centroid_loops: Vec<Vec<u32>>,
}

/// How far the ring outside the contour is pushed (the release's `* 1.1`).
pub(crate) const RING_SCALE: f32 = 1.1;

impl UvMapper {
    /// Derives the extension from the topology: the hole centroids at the mean UV of
    /// each hole's loop (exactly the release's values), with fans; the outer contour's
    /// vertices pushed out into a ring joined to the contour by triangles. The ring's
    /// UVs are the topology's own extension rows when it has them (the release's file:
    /// each ring row is matched to the contour vertex nearest to it in UV), otherwise
    /// the contour UVs scaled by `RING_SCALE` about their mean.
    pub fn derive(topology: &FaceTopology) -> Result<Self> {
        let loops = topology.boundary_loops()?;
        let fill = topology.hole_fill()?;
        // `boundary_loops` returns four loops, the outer one among them, or an error.
        let outer = loops.get(LoopRole::Outer).expect("outer loop").clone();
        let v = topology.vertex_count as u32;
        let mut uv = topology.uv.clone();
        let n = outer.len() as f32;
        let mean = outer.iter().fold([0.0f32; 2], |a, &i| {
            [
                a[0] + topology.uv[i as usize][0] / n,
                a[1] + topology.uv[i as usize][1] / n,
            ]
        });
        let ring_rows = &topology.uv_extension[..topology.uv_extension.len().min(outer.len())];
        let use_release_ring = ring_rows.len() == outer.len();
        for &c in &outer {
            let p = topology.uv[c as usize];
            let pushed = [
                (mean[0] + (p[0] - mean[0]) * RING_SCALE).clamp(0.0, 1.0),
                (mean[1] + (p[1] - mean[1]) * RING_SCALE).clamp(0.0, 1.0),
            ];
            if use_release_ring {
                // The release row nearest to the contour vertex's UV.
                let d = |q: &[f32; 2]| (q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2);
                let best = ring_rows
                    .iter()
                    .min_by(|a, b| d(a).total_cmp(&d(b)))
                    .expect("rows");
                uv.push(*best);
            } else {
                uv.push(pushed);
            }
        }
        let mut triangles = topology.triangles.clone();
        let k = outer.len() as u32;
        for i in 0..k {
            let (c0, c1) = (outer[i as usize], outer[((i + 1) % k) as usize]);
            let (p0, p1) = (v + i, v + (i + 1) % k);
            triangles.push([c0, p1, p0]);
            triangles.push([c0, c1, p1]);
        }
        let base = v + k;
        let mut centroid_loops = Vec::new();
        for (j, (_, l)) in fill.centroids.iter().enumerate() {
            let n = l.len() as f32;
            uv.push(l.iter().fold([0.0f32; 2], |a, &i| {
                [
                    a[0] + topology.uv[i as usize][0] / n,
                    a[1] + topology.uv[i as usize][1] / n,
                ]
            }));
            for t in fill.triangles.iter().filter(|t| t[2] == v + j as u32) {
                triangles.push([t[0], t[1], base + j as u32]);
            }
            centroid_loops.push(l.clone());
        }
        Ok(UvMapper {
            uv,
            triangles,
            ring_of: outer,
            centroid_loops,
        })
    }

    /// The extended positions of a face: the mesh, the ring (contour vertices scaled by
    /// `RING_SCALE` about the canonical origin, as the release), the hole centroids.
    pub fn extended_positions(&self, verts: &[Point3<f32>]) -> Vec<Point3<f32>> {
        let mut out = verts.to_vec();
        out.extend(
            self.ring_of
                .iter()
                .map(|&c| Point3::from(verts[c as usize].coords * RING_SCALE)),
        );
        for l in &self.centroid_loops {
            let sum = l.iter().fold(nalgebra::Vector3::zeros(), |a, &i| {
                a + verts[i as usize].coords
            });
            out.push(Point3::from(sum / l.len() as f32));
        }
        out
    }

    /// The UV position map of `verts`: `size x size` texels, row-major, each the
    /// canonical position (metres) interpolated over the UV triangles, or NaN where no
    /// triangle covers the texel. Texel `(i, j)` is sampled at UV `((i + 0.5) / size,
    /// (j + 0.5) / size)`. Rasterizes the layout on every call: for many meshes, make
    /// the [`UvTexels`] once ([`UvMapper::texels`]) and use
    /// [`UvTexels::position_map`].
    pub fn position_map(&self, verts: &[Point3<f32>], size: u32) -> Vec<[f32; 3]> {
        self.texels(size)
            .position_map(&self.extended_positions(verts))
    }

    /// The UV layout rasterized at `size x size` (the UV square scaled to the map).
    pub(crate) fn rasterize_layout(&self, size: u32) -> VisibilityBuffer {
        let screen: Vec<ScreenVertex> = (self.uv.iter())
            .map(|t| ScreenVertex {
                x: t[0] * size as f32,
                y: t[1] * size as f32,
                inv_w: 1.0,
            })
            .collect();
        let mut vb = VisibilityBuffer::new(size, size);
        vb.rasterize_mesh(&screen, &self.triangles)
            .expect("UV triangles index the extended vertices");
        vb
    }

    /// Which UV triangle covers each texel of a `size x size` map and with which
    /// weights: the rasterization of the layout, which depends on the layout and the
    /// size only, never on a face's positions. Texels are sampled at their centres
    /// with the rasterizer's rules (top-left fill, the earlier triangle keeps a texel
    /// two overlapping triangles reach at equal depth).
    pub fn texels(&self, size: u32) -> UvTexels {
        let vb = self.rasterize_layout(size);
        // Covered texels grouped by triangle, row-major within a triangle.
        let mut covered: Vec<(u32, u32)> = (vb.triangle.iter().enumerate())
            .filter(|&(_, &t)| t != VisibilityBuffer::EMPTY)
            .map(|(i, &t)| (t, i as u32))
            .collect();
        covered.sort_unstable();
        let mut texels = UvTexels {
            size,
            extended_vertices: self.uv.len(),
            triangles: Vec::new(),
            ends: Vec::new(),
            index: Vec::with_capacity(covered.len()),
            layout: next_layout_id(),
            weights: Vec::with_capacity(covered.len()),
        };
        // The groups in the order of their first texel: the writes then sweep the map
        // from top to bottom, a few rows at a time, instead of landing anywhere in it
        // in the layout's triangle order (each texel is written once either way).
        let mut groups: Vec<&[(u32, u32)]> = covered.chunk_by(|a, b| a.0 == b.0).collect();
        groups.sort_unstable_by_key(|g| g[0].1);
        for group in groups {
            texels.triangles.push(self.triangles[group[0].0 as usize]);
            for &(_, i) in group {
                texels.index.push(i);
                let b = vb.bary[i as usize];
                texels.weights.push(TexelWeights([b[0], b[1], b[2], 0.0]));
            }
            texels.ends.push(texels.index.len() as u32);
        }
        // `position_map` relies on these (its unchecked reads).
        assert!(
            (texels.triangles.iter().flatten()).all(|&v| (v as usize) < self.uv.len()),
            "UV triangles index the extended vertices"
        );
        assert!(texels.index.iter().all(|&i| i < size * size));
        texels
    }

    /// Reads the map bilinearly at a UV coordinate (texel centres at `(i + 0.5) / size`).
    pub fn sample(map: &[[f32; 3]], size: u32, uv: [f32; 2]) -> [f32; 3] {
        let (fx, fy) = (uv[0] * size as f32 - 0.5, uv[1] * size as f32 - 0.5);
        let (x, y) = (fx.floor(), fy.floor());
        let (tx, ty) = (fx - x, fy - y);
        let at = |x: f32, y: f32| {
            let (xi, yi) = (
                (x.max(0.0) as u32).min(size - 1),
                (y.max(0.0) as u32).min(size - 1),
            );
            map[(yi * size + xi) as usize]
        };
        let (a, b, c, d) = (
            at(x, y),
            at(x + 1.0, y),
            at(x, y + 1.0),
            at(x + 1.0, y + 1.0),
        );
        let mut out = [0.0; 3];
        for k in 0..3 {
            let top = a[k] + (b[k] - a[k]) * tx;
            let bottom = c[k] + (d[k] - c[k]) * tx;
            out[k] = top + (bottom - top) * ty;
        }
        out
    }
}

impl UvTexels {
    /// The map side, in texels.
    pub fn size(&self) -> u32 {
        self.size
    }

    /// Number of texels some UV triangle covers.
    pub fn covered(&self) -> usize {
        self.index.len()
    }

    /// The position map of a face from its extended positions
    /// ([`UvMapper::extended_positions`]): row-major `size x size`, NaN where no
    /// triangle covers the texel. Panics if `extended` has not one position per UV
    /// vertex of the layout.
    ///
    /// Each covered texel is `(p0 * w0 + p1 * w1) + p2 * w2`, per coordinate, its
    /// texels grouped by triangle so that the triangle's positions are loaded once. On
    /// x86-64 one four-float SSE2 operation per texel (positions padded to four
    /// floats), one eight-float AVX operation per two texels where the CPU has AVX
    /// (`UvTexels::fill_avx`), or one sixteen-float operation per four texels where it
    /// has AVX-512 (`UvTexels::fill_avx512`), detected at run time. Invariant: every path gives the
    /// bits of one coordinate at a time (tested). Measurements: `docs/performance.md`
    /// ("The UV position map").
    pub fn position_map(&self, extended: &[Point3<f32>]) -> Vec<[f32; 3]> {
        let mut out = vec![[f32::NAN; 3]; self.size as usize * self.size as usize];
        self.fill_covered(extended, &mut out);
        out
    }

    /// The covered texels of [`UvTexels::position_map`] written into `out` (one per
    /// texel of the map), the others left as they are, by the fastest path the CPU has.
    fn fill_covered(&self, extended: &[Point3<f32>], out: &mut [[f32; 3]]) {
        assert_eq!(
            extended.len(),
            self.extended_vertices,
            "one position per UV vertex"
        );
        self.fill_covered_at(lanes::level(), extended, out);
    }

    /// The position map scaled for a network's input, channels first: each coordinate
    /// of [`UvTexels::position_map`] times `scale`, clamped to [-1, 1]; a texel without
    /// a position (uncovered, or whose x is NaN, the map's mark for it) is -1 in all
    /// three planes. Written into `out` (`3 x size x size` values) in one pass over a
    /// position map the thread keeps for this table (no allocation; NaN where the
    /// table covers nothing, its covered texels drawn anew each call), eight texels at
    /// a time where the CPU has AVX, sixteen with AVX-512 (the planes then written with
    /// streaming stores). The same bits as mapping
    /// [`UvTexels::position_map`] one value at a time (tested).
    ///
    /// # Panics
    /// When `extended` is not one position per UV vertex or `out` not `3 x size x size`.
    pub(crate) fn clamped_planes_into(
        &self,
        extended: &[Point3<f32>],
        scale: f32,
        out: &mut [f32],
    ) {
        thread_local! {
            /// The last table's identity and a position map for it: NaN wherever that
            /// table covers nothing (no texel of it is ever written there).
            static MAP: std::cell::RefCell<(u64, Vec<[f32; 3]>)> =
                const { std::cell::RefCell::new((u64::MAX, Vec::new())) };
        }
        let n = self.size as usize * self.size as usize;
        assert_eq!(out.len(), 3 * n, "a 3 x size x size map");
        let (u, rest) = out.split_at_mut(n);
        let (v, w) = rest.split_at_mut(n);
        MAP.with_borrow_mut(|(layout, map)| {
            if *layout != self.layout || map.len() != n {
                map.clear();
                map.resize(n, [f32::NAN; 3]);
                *layout = self.layout;
            }
            self.fill_covered(extended, map);
            lanes::texels::clamp_planes(map, scale, [u, v, w]);
        });
    }
}

/// A new identity for a [`UvTexels`] table.
fn next_layout_id() -> u64 {
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
}
