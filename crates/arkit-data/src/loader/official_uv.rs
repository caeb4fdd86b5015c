//! `official_uv`: the official loader's UV map ([`OfficialUvLayout`], the layout the
//! official rule set's items use: the UV triangles drawn at `uv * (S - 1)` by the
//! official rasterizer, the ring at 1.1 times the contour in the `4.5 v + 0.5` space),
//! and the organ triangles that close its holes as the official mask closes them
//! ([`official_organ_triangles`]). Its lanes are `lanes::uv`; tested in `item`'s tests
//! (every texel against the per-texel definition, the organ strips' vertex order).

use crate::lanes;
use crate::lanes::uv::TexelRun;
use crate::render::uv_map::UvMapper;
use arkit_core::{Error, Result, ScreenVertex, VisibilityBuffer};
use nalgebra::Point3;

/// The release's UV layout: `tris_2500x3_202110.npy` and the 1,279 rows of
/// `uv_coords_std_202109.npy`.
pub(crate) type ReleaseUvLayout = (Vec<[u32; 3]>, Vec<[f32; 2]>);

/// The official UV layout rasterized once for one map size: per texel the UV triangle
/// and its screen-space weights, by the official rasterizer's rules at `uv * (S - 1)`.
#[derive(Clone, Debug)]
pub(crate) struct OfficialUvLayout {
    pub(crate) size: u32,
    /// The texels a triangle covers, in texel order, as runs of one triangle's texels.
    pub(crate) covered: Vec<TexelRun>,
    /// The official rasterizer's weights of each covered texel's corners (weight `k` of
    /// the covered texels in order in plane `k`).
    pub(crate) weights: [Vec<f32>; 3],
    /// The runs of texels no triangle covers (texel indices), in order.
    pub(crate) uncovered: Vec<std::ops::Range<usize>>,
    pub(crate) ring_of: Vec<u32>,
    pub(crate) centroid_loops: Vec<Vec<u32>>,
    pub(crate) extended: usize,
}

impl OfficialUvLayout {
    /// The layout of `uv` (its UV coordinates, triangles, ring and hole loops) drawn at
    /// `size` by the official rasterizer's rules at `uv * (S - 1)`; with `release` (the
    /// release's `tris_2500x3_202110.npy` and the 1,279 rows of
    /// `uv_coords_std_202109.npy`) the release's own triangles and vertex order instead
    /// ([`OfficialUvLayout::release_order`]).
    pub fn new(
        uv: &UvMapper,
        release: Option<ReleaseUvLayout>,
        vertex_count: usize,
        size: u32,
    ) -> Result<Self> {
        let (coords, triangles, ring_of, centroid_loops) = match release {
            Some((tris, coords)) => {
                let (ring_of, loops) = Self::release_order(&tris, vertex_count, coords.len())?;
                (coords, tris, ring_of, loops)
            }
            None => (
                uv.uv.clone(),
                uv.triangles.clone(),
                uv.ring_of.clone(),
                uv.centroid_loops.clone(),
            ),
        };
        if let Some(t) = triangles
            .iter()
            .flatten()
            .find(|&&v| v as usize >= coords.len())
        {
            return Err(Error::invalid(
                "UV triangles",
                format!("vertex {t} beyond the {} UV vertices", coords.len()),
            ));
        }
        let vb = Self::raster(&coords, &triangles, size)?;
        let mut covered: Vec<TexelRun> = Vec::new();
        let mut weights: [Vec<f32>; 3] = Default::default();
        let mut uncovered: Vec<std::ops::Range<usize>> = Vec::new();
        for (texel, (&t, &wt)) in vb.triangle.iter().zip(&vb.bary).enumerate() {
            if t == VisibilityBuffer::EMPTY {
                match uncovered.last_mut() {
                    Some(run) if run.end == texel => run.end += 1,
                    _ => uncovered.push(texel..texel + 1),
                }
                continue;
            }
            // A texel continues the last run when it is the next texel and its triangle
            // has the run's corners (the values depend on the corners, not the index).
            let (texel, corners) = (texel as u32, triangles[t as usize]);
            match covered.last_mut() {
                Some(run) if run.corners == corners && run.start + run.len == texel => run.len += 1,
                _ => covered.push(TexelRun {
                    start: texel,
                    len: 1,
                    first: weights[0].len() as u32,
                    corners,
                }),
            }
            for (plane, w) in weights.iter_mut().zip(wt) {
                plane.push(w);
            }
        }
        Ok(OfficialUvLayout {
            size,
            covered,
            weights,
            uncovered,
            ring_of,
            centroid_loops,
            extended: coords.len(),
        })
    }

    /// The UV triangles drawn by the official rasterizer's rules at `uv * (size - 1)`
    /// into a `size x size` buffer: each texel's triangle and weights.
    pub(crate) fn raster(
        coords: &[[f32; 2]],
        triangles: &[[u32; 3]],
        size: u32,
    ) -> Result<VisibilityBuffer> {
        let s = (size - 1) as f32;
        let screen: Vec<ScreenVertex> = coords
            .iter()
            .map(|t| ScreenVertex {
                x: t[0] * s,
                y: t[1] * s,
                inv_w: 1.0,
            })
            .collect();
        let mut vb = VisibilityBuffer::new(size, size);
        arkit_core::rasterize_mesh_official(&mut vb, &screen, triangles)
            .map_err(|e| Error::invalid("UV triangles", e.to_string()))?;
        Ok(vb)
    }

    /// The release's extended vertices, read off its UV triangles: after the mesh
    /// triangles come, for ring vertex `V + k`, the pair `[c_k, V+k+1, V+k]`,
    /// `[c_k, c_k+1, V+k+1]` (so `c_k`, the first column of every other ring triangle,
    /// is the contour vertex the official loader scales by 1.1 for row `V + k`), then a
    /// fan `[l_i, centre, l_i+1]` around each hole centroid (the last three rows), whose
    /// first column is the hole's loop in the official order.
    pub(crate) fn release_order(
        tris: &[[u32; 3]],
        vertex_count: usize,
        rows: usize,
    ) -> Result<(Vec<u32>, Vec<Vec<u32>>)> {
        let v = vertex_count as u32;
        let bad = |why: &str| Error::invalid("tris_2500x3_202110.npy", why.to_string());
        if rows < vertex_count + 3 {
            return Err(bad("fewer UV rows than the mesh and three hole centroids"));
        }
        let centres: Vec<u32> = (rows as u32 - 3..rows as u32).collect();
        let first_extra = tris
            .iter()
            .position(|t| t.iter().any(|&x| x >= v))
            .ok_or_else(|| bad("no triangle beyond the mesh"))?;
        let extra = &tris[first_extra..];
        let ring: Vec<&[u32; 3]> = extra
            .iter()
            .filter(|t| !t.iter().any(|x| centres.contains(x)))
            .collect();
        let ring_of: Vec<u32> = ring.iter().step_by(2).map(|t| t[0]).collect();
        if ring_of.len() != rows - vertex_count - 3 || ring_of.iter().any(|&c| c >= v) {
            return Err(bad(
                "the ring triangles do not pair one contour vertex per ring row",
            ));
        }
        let loops = centres
            .iter()
            .map(|&c| {
                let fan: Vec<u32> = extra.iter().filter(|t| t[1] == c).map(|t| t[0]).collect();
                if fan.len() < 3 || fan.iter().any(|&x| x >= v) {
                    return Err(bad("a hole centroid without its fan"));
                }
                Ok(fan)
            })
            .collect::<Result<Vec<_>>>()?;
        Ok((ring_of, loops))
    }

    /// The side, in texels, of the maps [`OfficialUvLayout::uv_map_into`] draws.
    pub fn size(&self) -> u32 {
        self.size
    }

    /// The official UV map of `verts` (metres), channels first, in [-1, 1], into `out`:
    /// the positions mapped by `4.5 v + 0.5`, the ring at 1.1 times its contour vertex
    /// in that space, the hole centroids their loops' means, interpolated with the
    /// layout's weights, clipped to [0, 1] and mapped by `2 x - 1`; every value written
    /// (`-1` where uncovered), in one pass.
    ///
    /// # Panics
    /// When `out` is not `3 x size x size` values.
    pub(crate) fn uv_map_into(&self, verts: &[Point3<f32>], out: &mut [f32]) {
        let colors = self.colours(verts);
        let planes = self.planes_uncovered_filled(out);
        lanes::uv::covered(&self.covered, &self.weights, &colors, planes);
    }

    /// `out`'s three planes (`3 x size x size` values, channels first), with `-1` written
    /// at every uncovered texel.
    pub(crate) fn planes_uncovered_filled<'a>(&self, out: &'a mut [f32]) -> [&'a mut [f32]; 3] {
        let n = (self.size * self.size) as usize;
        assert_eq!(out.len(), 3 * n, "a 3 x size x size map");
        let (u, rest) = out.split_at_mut(n);
        let (v, w) = rest.split_at_mut(n);
        for run in &self.uncovered {
            for plane in [&mut *u, &mut *v, &mut *w] {
                plane[run.clone()].fill(-1.0);
            }
        }
        [u, v, w]
    }

    /// The official colours of the extended vertices: the positions mapped by
    /// `4.5 v + 0.5`, then the ring's and the hole centroids'.
    pub(crate) fn colours(&self, verts: &[Point3<f32>]) -> Vec<[f32; 3]> {
        let mut colors: Vec<[f32; 3]> = verts
            .iter()
            .map(|p| [p.x * 4.5 + 0.5, p.y * 4.5 + 0.5, p.z * 4.5 + 0.5])
            .collect();
        for &c in &self.ring_of {
            let v = colors[c as usize];
            colors.push([v[0] * 1.1, v[1] * 1.1, v[2] * 1.1]);
        }
        for l in &self.centroid_loops {
            // numpy's float32 mean over axis 0: a running float32 sum, then / n.
            let mut sum = [0f32; 3];
            for &i in l {
                for (s, v) in sum.iter_mut().zip(colors[i as usize]) {
                    *s += v;
                }
            }
            colors.push(sum.map(|s| s / l.len() as f32));
        }
        debug_assert_eq!(colors.len(), self.extended);
        colors
    }
}

/// The official loader's eye and mouth triangles (`vert_index[face_em]` of its
/// `lib/eyemouth_index.py`), which it draws after the mesh, with attribute 0, into the
/// full-resolution mask (`arkit_dataset.py:146-151`). `loops` are the two eyes' and the
/// mouth's boundary loops in that order and in the official direction (the release's
/// hole fans list them so, `OfficialUvLayout::release_order`); `uv` the topology's UV
/// coordinates. Each loop starts at its vertex of smallest `u` (an eye or mouth corner)
/// and is closed by a strip between its two ends: `[0, 1, n-1]`, then alternately `[a,
/// a+1, b]` and `[a, b, b-1]`. The official list departs from that pattern in the vertex
/// order of three triangles (each eye's third is `[2, n-2, n-1]`, the mouth's last
/// `[17, 19, 18]`); the order changes the float32 rounding of the depth, so it is kept.
/// With the release's files this gives the official 78 triangles exactly (checked beside
/// the official code).
pub fn official_organ_triangles(loops: [&[u32]; 3], uv: &[[f32; 2]]) -> Vec<[u32; 3]> {
    let mut out = Vec::new();
    for (k, lp) in loops.into_iter().enumerate() {
        let n = lp.len();
        if n < 3 {
            continue;
        }
        // numpy's argmin: the first smallest.
        let start = (0..n).fold(0, |best, i| {
            if uv[lp[i] as usize][0] < uv[lp[best] as usize][0] {
                i
            } else {
                best
            }
        });
        let at = |i: usize| lp[(start + i) % n];
        let mut local = vec![[0, 1, n - 1]];
        let (mut a, mut b, mut step_a) = (1, n - 1, true);
        while local.len() < n - 2 {
            if step_a {
                local.push([a, a + 1, b]);
                a += 1;
            } else {
                local.push([a, b, b - 1]);
                b -= 1;
            }
            step_a = !step_a;
        }
        let odd = if k < 2 { 2 } else { local.len() - 1 };
        if let Some(t) = local.get_mut(odd) {
            t.swap(1, 2);
        }
        out.extend(local.into_iter().map(|t| t.map(at)));
    }
    out
}
