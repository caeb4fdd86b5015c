//! The CPU triangle rasterizer core, shared by `synth`, `render` and `augment`.
//!
//! # Design
//! Four small stages, each tested alone:
//! 1. **Setup** ([`TriangleSetup::new`]): reject invalid triangles (non-finite, behind
//!    the camera, zero area), snap vertices to fixed point (1/256 pixel), orient the
//!    triangle counter-clockwise in image space, compute the integer edge functions and
//!    the bounding box clipped to the viewport. A mesh
//!    ([`VisibilityBuffer::rasterize_mesh`]) checks and snaps each vertex once, not once
//!    per triangle using it.
//! 2. **Coverage** ([`TriangleSetup::for_each_covered`]): walk the box, stepping the
//!    three edge functions by integer increments; a pixel centre is inside when every
//!    edge function is positive, or zero on a *top* or *left* edge (the top-left rule).
//!    A row of a triangle is covered on one run of pixels, so for boxes up to 64 pixels
//!    wide (a face crop's triangles are 3.6 pixels wide on average) each row's
//!    coverage is taken as a bit mask, two pixels at a time in SSE2 lanes, and the run
//!    between its first and last set bits is visited: no branch per pixel. A small
//!    triangle's box up to 8x8 pixels (most of a face crop's) is taken whole: its
//!    edge values as `i32` in SSE2 lanes, one bit per pixel (`BoxCoverage`), then
//!    one loop over the set bits, with no branch per row or run. Every vector path has
//!    a scalar twin it is tested against (the box walk visits exactly what the pixel
//!    walk visits, on thousands of small triangles with edges through pixel centres).
//!    How much each choice saved is in `docs/performance.md`
//!    (`cargo bench --bench raster`, `--bench render`).
//! 3. **Interpolation**: screen-space barycentrics from the edge functions, then
//!    perspective-correct barycentrics `b_i = l_i w_i^-1 / sum_j l_j w_j^-1` and the
//!    depth key `sum_i l_i w_i^-1` (1/w, larger is nearer), one division per pixel.
//! 4. **Output**: a [`Fragment`] goes to the caller's closure (`rasterize_triangle`),
//!    or through a depth test into a [`VisibilityBuffer`] of flat per-pixel arrays
//!    (triangle id, barycentrics, depth key) that callers turn into masks, colours,
//!    correspondences or coordinate maps.
//!
//! The official loader's rasterizer ([`rasterize_mesh_official`], for the official-compat
//! paths) is a separate, plain loop. It can fill a buffer holding only a window of the
//! image ([`rasterize_mesh_official_in`], [`PixelWindow`]): every value is computed in
//! image coordinates and only the walked boxes are clamped to the window, so the window
//! holds the whole image's values, and [`PixelWindow::official_extent`] is a window
//! outside which the whole image gets nothing (tested against whole-image buffers on
//! random meshes and windows).//!
//! # Conventions (the crate's contract; see also `conventions::camera`)
//! - Image coordinates: x right, y **down**, in pixels; pixel `(i, j)` covers
//!   `[i, i+1) x [j, j+1)` and is sampled at its centre `(i + 0.5, j + 0.5)`.
//! - Each vertex carries `inv_w = 1 / w`, `w > 0` the distance along the view axis
//!   (`-z` in the OpenGL camera frame). A triangle with a vertex at `inv_w <= 0` or a
//!   non-finite coordinate is skipped, not clipped: faces are always well in front of
//!   the camera, and a partly-behind triangle is a data error upstream.
//! - Fixed point: coordinates are rounded to 1/256 pixel and edge functions are exact
//!   `i64` arithmetic, so the edge function of `(a, b)` in one triangle is exactly the
//!   negation of `(b, a)` in its neighbour. With the top-left rule this makes every
//!   pixel centre on an edge shared by two triangles covered by exactly one of them,
//!   and leaves no gap. Viewports are limited to [`MAX_VIEWPORT`] pixels a side
//!   (coordinates are checked against a guard band so products stay far below 2^63).
//! - Fill rule, for y down and counter-clockwise-on-screen orientation (as displayed):
//!   a *top* edge is horizontal with the triangle below it; a *left* edge is one the
//!   triangle lies to the right of, going down. Both windings are accepted (the
//!   setup takes a clockwise triangle's edges reversed) unless back faces are culled.
//! - Depth test: the fragment with the larger `inv_w` wins; on an exact tie the
//!   earlier triangle keeps the pixel.

use crate::lanes::Level;
#[cfg(test)]
use lanes::ScalarRowCoverage;
use lanes::{BoxCoverage, RowCoverage};

mod lanes;

/// Largest supported viewport side, in pixels.
pub const MAX_VIEWPORT: u32 = 16384;
/// Sub-pixel bits of the fixed-point grid.
pub(crate) const SUBPIXEL_BITS: u32 = 8;
const ONE: i64 = 1 << SUBPIXEL_BITS;
const HALF: i64 = ONE / 2;
/// Vertices farther than this outside the viewport (pixels) are rejected with their
/// triangle, which keeps every edge-function product within `i64`.
const GUARD_BAND: f32 = 65536.0;

/// A vertex projected to image coordinates (see the module's conventions).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScreenVertex {
    /// Pixels from the left edge.
    pub x: f32,
    /// Pixels from the top edge.
    pub y: f32,
    /// `1 / w`, the reciprocal of the positive view depth.
    pub inv_w: f32,
}

/// One covered pixel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fragment {
    /// Pixel column.
    pub x: u32,
    /// Pixel row.
    pub y: u32,
    /// Perspective-correct barycentric weights of the triangle's vertices, in the order
    /// the caller gave them; they sum to 1.
    pub bary: [f32; 3],
    /// Screen-space (linear, not perspective-correct) barycentric weights.
    pub screen_bary: [f32; 3],
    /// Interpolated `1 / w` (larger is nearer).
    pub inv_w: f32,
}

/// Which triangles to drop by their on-screen orientation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Culling {
    /// Draw both windings (the default; the official renderer does not cull).
    #[default]
    None,
    /// Drop triangles that appear clockwise on screen (y down), i.e. whose front
    /// (counter-clockwise in a y-up view) faces away.
    BackFaces,
}

/// A triangle prepared for coverage: fixed-point vertices, edge functions, box.
#[derive(Clone, Debug)]
pub struct TriangleSetup {
    /// Per edge `k` (opposite the caller's vertex `k`, oriented so that it is positive
    /// inside): value at the first pixel centre of
    /// the box, step per pixel in x, step per row in y, and the top-left bias.
    pub(crate) e0: [i64; 3],
    pub(crate) dx: [i64; 3],
    pub(crate) dy: [i64; 3],
    pub(crate) bias: [i64; 3],
    pub(crate) area2: i64,
    pub(crate) inv_w: [f32; 3],
    pub(crate) x0: u32,
    pub(crate) x1: u32,
    pub(crate) y0: u32,
    pub(crate) y1: u32,
    /// Whether the vertices span less than [`BOX_SPAN`] pixels on both axes, so that
    /// every edge value over the box widened to [`BoxCoverage`]'s 8x8 pixels fits an
    /// `i32`.
    pub(crate) small: bool,
}

/// Largest vertex span (pixels, exclusive, per axis) of a triangle whose box is walked
/// with `i32` edge values ([`BoxCoverage`]). A pixel centre of the box is within the
/// vertices' span, and the widened box adds at most 7 pixels, so each product of an
/// edge function is below `(64 + 8) * 256 * 64 * 256`, and `E` below `2^30`.
const BOX_SPAN: i64 = 64 * ONE;

fn snap(v: f32) -> i64 {
    // Round half away from zero without a libm call (|v| is bounded by the guard band).
    let s = v as f64 * ONE as f64;
    (s + 0.5f64.copysign(s)) as i64
}

/// A vertex snapped to the fixed-point grid, with its `1 / w`.
#[derive(Clone, Copy, Debug, PartialEq)]
struct FixedVertex {
    x: i64,
    y: i64,
    inv_w: f32,
}

impl FixedVertex {
    /// Snaps a vertex; `None` when it cannot be drawn (non-finite, outside the guard
    /// band, or behind the camera).
    #[inline]
    fn new(p: ScreenVertex) -> Option<Self> {
        let finite = p.x.is_finite() && p.y.is_finite() && p.inv_w.is_finite();
        let in_band = p.x.abs() < GUARD_BAND && p.y.abs() < GUARD_BAND;
        if !finite || !in_band || p.inv_w <= 0.0 {
            return None;
        }
        Some(FixedVertex {
            x: snap(p.x),
            y: snap(p.y),
            inv_w: p.inv_w,
        })
    }
}

/// Whether a viewport has a supported size.
fn viewport_ok(width: u32, height: u32) -> bool {
    width != 0 && height != 0 && width <= MAX_VIEWPORT && height <= MAX_VIEWPORT
}

impl TriangleSetup {
    /// Prepares a triangle for a `width` x `height` viewport; `None` when nothing can be
    /// drawn (invalid vertex, behind the camera, zero area, culled, or off-screen).
    pub fn new(v: [ScreenVertex; 3], width: u32, height: u32, culling: Culling) -> Option<Self> {
        if !viewport_ok(width, height) {
            return None;
        }
        let [a, b, c] = v;
        let v = [
            FixedVertex::new(a)?,
            FixedVertex::new(b)?,
            FixedVertex::new(c)?,
        ];
        Self::from_fixed(v, width, height, culling)
    }

    /// [`TriangleSetup::new`] from snapped vertices, for a checked viewport. A mesh's
    /// vertices are snapped and checked once ([`VisibilityBuffer::rasterize_mesh_with`])
    /// instead of once per triangle using them (about six): the checks and the snapping
    /// were a third of the setup's instructions.
    #[inline(always)]
    fn from_fixed(v: [FixedVertex; 3], width: u32, height: u32, culling: Culling) -> Option<Self> {
        // Twice the signed area, cross(v1 - v0, v2 - v0). With y down, a negative value
        // is counter-clockwise as displayed: the edges below run that way round, which
        // makes their functions positive inside. For a clockwise triangle each edge is
        // taken reversed instead (its function negated), so edge `k` stays opposite
        // the caller's vertex `k` and no pixel needs its weights permuted back (a
        // permutation chosen per pixel had been 4 of the ~50 instructions of a pixel
        // that passes the depth test).
        let area = (v[1].x - v[0].x) * (v[2].y - v[0].y) - (v[2].x - v[0].x) * (v[1].y - v[0].y);
        if area == 0 {
            return None;
        }
        let clockwise = area > 0;
        if clockwise && culling == Culling::BackFaces {
            return None;
        }
        let px = [v[0].x, v[1].x, v[2].x];
        let py = [v[0].y, v[1].y, v[2].y];
        // Bounding box of pixel centres inside the triangle's box, clipped.
        let min_x = px.iter().min().copied().unwrap_or(0);
        let max_x = px.iter().max().copied().unwrap_or(0);
        let min_y = py.iter().min().copied().unwrap_or(0);
        let max_y = py.iter().max().copied().unwrap_or(0);
        // Pixel i has centre i*ONE + HALF; first i with centre >= min: ceil((min-HALF)/ONE).
        let first = |m: i64| (m - HALF + ONE - 1).div_euclid(ONE);
        let last = |m: i64| (m - HALF).div_euclid(ONE);
        let x0 = first(min_x).max(0);
        let x1 = last(max_x).min(width as i64 - 1);
        let y0 = first(min_y).max(0);
        let y1 = last(max_y).min(height as i64 - 1);
        if x0 > x1 || y0 > y1 {
            return None;
        }
        // Edge k runs from vertex k+1 to k+2 (opposite vertex k):
        // E_k(p) = (px - ax)(by - ay) - (py - ay)(bx - ax), which equals |area| at vertex
        // k and 0 on the edge; an edge's E is exactly the negation of the reversed edge's.
        let mut e0 = [0i64; 3];
        let mut dx = [0i64; 3];
        let mut dy = [0i64; 3];
        let mut bias = [0i64; 3];
        let (cx, cy) = (x0 * ONE + HALF, y0 * ONE + HALF);
        // The reversed edge's function is `sign * E`, as `E` is affine and zero at both
        // ends: multiplying by the sign, rather than choosing the vertices in the
        // reversed order, took the edge setup from about 120 to about 60 instructions
        // per triangle (the choice and the top-left tests were computed as selects).
        let sign = if clockwise { -1 } else { 1 };
        for k in 0..3 {
            let (ex, ey) = edge_slopes(&px, &py, k, sign);
            e0[k] = edge_value(&px, &py, k, (ex, ey), (cx, cy));
            dx[k] = ex * ONE;
            dy[k] = ey * ONE;
            // Top-left rule: a centre exactly on the edge (E = 0) is inside only on a
            // top or left edge.
            bias[k] = top_left_bias(ex, ey);
        }
        Some(TriangleSetup {
            e0,
            dx,
            dy,
            bias,
            area2: area.abs(),
            inv_w: [v[0].inv_w, v[1].inv_w, v[2].inv_w],
            x0: x0 as u32,
            x1: x1 as u32,
            y0: y0 as u32,
            y1: y1 as u32,
            small: max_x - min_x < BOX_SPAN && max_y - min_y < BOX_SPAN,
        })
    }

    /// The coverage stage: visits every covered pixel in row-major order with its three
    /// edge-function values, stepping them incrementally.
    ///
    /// A row of a triangle is covered on one run of pixels (each edge's test is a half
    /// line along the row). For boxes up to 64 pixels wide (all but the largest
    /// triangles at crop resolution) the row's coverage is first gathered as a bit mask
    /// without a branch per pixel, and the run between its first and last set bits is
    /// visited; wider boxes are walked pixel by pixel, where long runs keep the branches
    /// predictable. On x86-64 a small triangle's box up to 8x8 pixels is taken whole
    /// instead ([`BoxCoverage`]): one mask for the box, one loop over its set bits.
    #[inline]
    fn walk(&self, mut visit: impl FnMut(u32, u32, [i64; 3])) {
        #[cfg(target_arch = "x86_64")]
        if self.small {
            // A box up to 8x8 pixels: its coverage at once, then its covered pixels in
            // one loop ([`BoxCoverage`]).
            let mut cover = BoxCoverage::new();
            let inside = match (self.x1 - self.x0, self.y1 - self.y0) {
                (0..=3, 0..=3) => Some(cover.fill::<1, 4>(self)),
                (0..=3, 4..=7) => Some(cover.fill::<1, 8>(self)),
                (4..=7, 0..=7) => Some(cover.fill::<2, 8>(self)),
                _ => None,
            };
            if let Some((mut bits, shift)) = inside {
                while bits != 0 {
                    let b = bits.trailing_zeros();
                    bits &= bits - 1;
                    let (row, col) = (b >> shift, b & ((1 << shift) - 1));
                    // SAFETY: `fill` set only bits of the groups it wrote.
                    let e = unsafe { cover.edges(b as usize) };
                    visit(self.x0 + col, self.y0 + row, e);
                }
                return;
            }
        }
        if self.x1 - self.x0 < 64 {
            self.walk_rows(visit)
        } else {
            self.walk_pixels(visit)
        }
    }

    /// [`TriangleSetup::walk`] for a box up to 64 pixels wide: each row's coverage as a
    /// bit mask ([`RowCoverage`]), then the run between its first and last set bits.
    /// Visits the same pixels in the same order as [`TriangleSetup::walk_pixels`]
    /// (tested); chosen for a face crop's small boxes because it mispredicts fewer
    /// branches (measurements: `docs/performance.md`, "The rasterizer's stages").
    #[inline(always)]
    fn walk_rows(&self, mut visit: impl FnMut(u32, u32, [i64; 3])) {
        let mut row = self.e0;
        let width = self.x1 - self.x0 + 1;
        let mut coverage = RowCoverage::new(row, self.dx, self.dy, self.bias, width);
        for y in self.y0..=self.y1 {
            let bits = coverage.next_row();
            if bits != 0 {
                let (first, last) = (bits.trailing_zeros(), 63 - bits.leading_zeros());
                let f = first as i64;
                let mut e = [
                    row[0] + self.dx[0] * f,
                    row[1] + self.dx[1] * f,
                    row[2] + self.dx[2] * f,
                ];
                for x in self.x0 + first..=self.x0 + last {
                    visit(x, y, e);
                    step(&mut e, self.dx);
                }
            }
            step(&mut row, self.dy);
        }
    }

    /// [`TriangleSetup::walk`] pixel by pixel, for any box: three edge tests per pixel.
    #[inline]
    fn walk_pixels(&self, mut visit: impl FnMut(u32, u32, [i64; 3])) {
        let mut row = self.e0;
        for y in self.y0..=self.y1 {
            let mut e = row;
            for x in self.x0..=self.x1 {
                if e[0] + self.bias[0] >= 0 && e[1] + self.bias[1] >= 0 && e[2] + self.bias[2] >= 0
                {
                    visit(x, y, e);
                }
                step(&mut e, self.dx);
            }
            step(&mut row, self.dy);
        }
    }

    /// Calls `emit` for every covered pixel, in row-major order.
    pub fn for_each_covered(&self, mut emit: impl FnMut(Fragment)) {
        let inv_area = 1.0 / self.area2 as f64;
        self.walk(|x, y, e| emit(self.fragment(x, y, e, inv_area)));
    }

    /// Depth-tested coverage: for every covered pixel whose interpolated `1 / w` is
    /// larger than `depth[idx]` (row-major, `width` wide), stores it there and calls
    /// `emit(idx, fragment)`. The depth key is computed first and the barycentrics only
    /// for pixels that pass, so hidden pixels cost one multiply-add per edge.
    pub(crate) fn for_each_nearer(
        &self,
        depth: &mut [f32],
        width: usize,
        mut emit: impl FnMut(usize, Fragment),
    ) {
        let inv_area = 1.0 / self.area2 as f64;
        self.walk_nearer(depth, width, |idx, x, y, e, key| {
            let mut f = self.fragment(x, y, e, inv_area);
            f.inv_w = key;
            emit(idx, f);
        });
    }

    /// Depth-tested coverage without the fragments: as [`TriangleSetup::for_each_nearer`]
    /// (the same depth keys, tests and stores into `depth`), calling `emit(idx)` where a
    /// pixel passes. The barycentrics are left to [`VisibilityBuffer::fragment_at`], for
    /// the pixels a caller needs.
    pub(crate) fn for_each_nearer_key(
        &self,
        depth: &mut [f32],
        width: usize,
        mut emit: impl FnMut(usize),
    ) {
        self.walk_nearer(depth, width, |idx, _, _, _, _| emit(idx));
    }

    /// The depth test of both [`TriangleSetup::for_each_nearer`] and
    /// [`TriangleSetup::for_each_nearer_key`]: each covered pixel's key, `1 / w`
    /// interpolated from the edge values; where it is larger than `depth[idx]`, stored
    /// there and `pass(idx, x, y, edges, key)` called.
    #[inline(always)]
    fn walk_nearer(
        &self,
        depth: &mut [f32],
        width: usize,
        mut pass: impl FnMut(usize, u32, u32, [i64; 3], f32),
    ) {
        let inv_area = 1.0 / self.area2 as f64;
        let w = self.inv_w.map(|v| v as f64 * inv_area);
        self.walk(|x, y, e| {
            let key = (e[0] as f64 * w[0] + e[1] as f64 * w[1] + e[2] as f64 * w[2]) as f32;
            let idx = y as usize * width + x as usize;
            if key > depth[idx] {
                depth[idx] = key;
                pass(idx, x, y, e, key);
            }
        });
    }

    #[inline]
    fn fragment(&self, x: u32, y: u32, e: [i64; 3], inv_area: f64) -> Fragment {
        fragment_of(self.inv_w, x, y, e, inv_area)
    }
}

/// The fragment at pixel `(x, y)` of a triangle whose vertices have `1 / w` of
/// `inv_w`, from its edge values `e` there and `1 / area2` (`inv_area`): the weights
/// are the edge values over the area, made perspective-correct through the `1 / w`.
#[inline(always)]
fn fragment_of(inv_w: [f32; 3], x: u32, y: u32, e: [i64; 3], inv_area: f64) -> Fragment {
    // One reciprocal per triangle instead of three divisions per pixel (the
    // interpolation was about half of the visibility stage's time at crop size).
    let l = [
        e[0] as f64 * inv_area,
        e[1] as f64 * inv_area,
        e[2] as f64 * inv_area,
    ];
    let pw = [
        l[0] * inv_w[0] as f64,
        l[1] * inv_w[1] as f64,
        l[2] * inv_w[2] as f64,
    ];
    let inv_w = pw[0] + pw[1] + pw[2];
    let r = 1.0 / inv_w;
    Fragment {
        x,
        y,
        bary: [(pw[0] * r) as f32, (pw[1] * r) as f32, (pw[2] * r) as f32],
        screen_bary: [l[0] as f32, l[1] as f32, l[2] as f32],
        inv_w: inv_w as f32,
    }
}

/// Edge `k`'s (from vertex `k + 1` to `k + 2`, opposite vertex `k`) function
/// `E(p) = (px - ax) (by - ay) - (py - ay) (bx - ax)` times `sign`: its increments
/// per fixed-point unit along x and down y.
#[inline(always)]
fn edge_slopes(px: &[i64; 3], py: &[i64; 3], k: usize, sign: i64) -> (i64, i64) {
    let (a, b) = ((k + 1) % 3, (k + 2) % 3);
    (sign * (py[b] - py[a]), sign * (px[a] - px[b]))
}

/// Edge `k`'s function (slopes `(ex, ey)`, [`edge_slopes`]) at fixed-point point `c`:
/// exact integers, so equal to the value stepped there pixel by pixel.
#[inline(always)]
fn edge_value(px: &[i64; 3], py: &[i64; 3], k: usize, (ex, ey): (i64, i64), c: (i64, i64)) -> i64 {
    let a = (k + 1) % 3;
    (c.0 - px[a]) * ex + (c.1 - py[a]) * ey
}

/// Steps three edge values by their increments.
#[inline(always)]
pub(crate) fn step(e: &mut [i64; 3], by: [i64; 3]) {
    e[0] += by[0];
    e[1] += by[1];
    e[2] += by[2];
}

/// The top-left bias of an edge whose function `E` (positive inside, y down) grows by
/// `ex` per pixel along x and `ey` per pixel down y: 0 for a *top* or *left* edge,
/// whose centres with `E = 0` are inside, else -1. For the directed edge `a -> b`,
/// `ex = by - ay` and `ey = ax - bx`. A horizontal edge (`ex = 0`) has the interior
/// below it, a top edge, exactly when `ey > 0`; otherwise `E` grows with x when
/// `ex > 0`: the interior is to the edge's right, a left edge. Of an edge and its
/// reverse (`-ex, -ey`) exactly one qualifies, which is what makes a shared edge's
/// pixels belong to exactly one triangle.
///
/// So the bias is -1 exactly when `(ex, ey) <= (0, 0)` in lexicographic order, that is
/// when `ex * 2^26 + ey <= 0`: vertices within the guard band are less than 2^24
/// sub-pixel steps from the origin, so `|ey| < 2^25` never outweighs a non-zero `ex`
/// term, and the sum stays far inside `i64`. Three instructions, where the comparisons
/// compiled to 17 per edge.
#[inline(always)]
fn top_left_bias(ex: i64, ey: i64) -> i64 {
    ((ex << 26) + ey - 1) >> 63
}

#[cfg(test)]
/// Calls `emit` for every pixel covered by one triangle (no depth test).
pub(crate) fn rasterize_triangle(
    v: [ScreenVertex; 3],
    width: u32,
    height: u32,
    emit: impl FnMut(Fragment),
) {
    if let Some(setup) = TriangleSetup::new(v, width, height, Culling::None) {
        setup.for_each_covered(emit);
    }
}

/// Every vertex snapped to the fixed-point grid, `None` where it cannot be drawn.
fn fixed_vertices(vertices: &[ScreenVertex]) -> Vec<Option<FixedVertex>> {
    vertices.iter().map(|&p| FixedVertex::new(p)).collect()
}

/// Calls `draw(index, setup)` for each triangle of `triangles` that can be drawn in a
/// `width x height` viewport with `culling`, in order: each vertex snapped and checked
/// once (not once per triangle using it), then each triangle set up where it is drawn.
/// A plain loop, inlined into its callers: through an iterator of setups, each came
/// back from a call of its own, by a copy. The indices must have been checked
/// ([`check_indices`]).
#[inline(always)]
pub(crate) fn for_each_drawable(
    vertices: &[ScreenVertex],
    triangles: &[[u32; 3]],
    width: u32,
    height: u32,
    culling: Culling,
    mut draw: impl FnMut(u32, TriangleSetup),
) {
    let fixed = fixed_vertices(vertices);
    for (ti, t) in triangles.iter().enumerate() {
        if let [Some(a), Some(b), Some(c)] = t.map(|v| fixed[v as usize])
            && let Some(setup) = TriangleSetup::from_fixed([a, b, c], width, height, culling)
        {
            draw(ti as u32, setup);
        }
    }
}

/// The first triangle that refers to a vertex `>= vertex_count`, as an error.
fn check_indices(vertex_count: usize, triangles: &[[u32; 3]]) -> Result<(), BadTriangle> {
    match triangles
        .iter()
        .enumerate()
        .find(|(_, t)| t.iter().any(|&v| v as usize >= vertex_count))
    {
        Some((i, t)) => Err(BadTriangle {
            triangle: i,
            indices: *t,
            vertex_count,
        }),
        None => Ok(()),
    }
}

/// A triangle that refers to a vertex that does not exist.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BadTriangle {
    /// Index of the triangle in the list.
    pub triangle: usize,
    /// Its vertex indices.
    pub indices: [u32; 3],
    /// Number of vertices given.
    pub vertex_count: usize,
}

impl std::fmt::Display for BadTriangle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "triangle {} {:?} refers to a vertex >= {}",
            self.triangle, self.indices, self.vertex_count
        )
    }
}

impl std::error::Error for BadTriangle {}

/// Per-pixel visibility: which triangle is nearest, where in it, how deep.
/// Flat row-major arrays of `width * height` entries.
#[derive(Clone, Debug)]
pub struct VisibilityBuffer {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Nearest triangle's index, or [`VisibilityBuffer::EMPTY`].
    pub triangle: Vec<u32>,
    /// Perspective-correct barycentrics in the nearest triangle; meaningful only where
    /// `triangle` is set (not reset by [`VisibilityBuffer::clear`]).
    pub bary: Vec<[f32; 3]>,
    /// Depth key (`1/w`, larger is nearer); 0 where empty.
    pub inv_w: Vec<f32>,
    /// Which orientation to drop.
    pub culling: Culling,
}

impl VisibilityBuffer {
    /// Marks a pixel no triangle covers.
    pub const EMPTY: u32 = u32::MAX;

    /// An empty buffer. Panics if a side exceeds [`MAX_VIEWPORT`] (a programming error:
    /// image sizes are checked where they are read).
    pub fn new(width: u32, height: u32) -> Self {
        assert!(
            width <= MAX_VIEWPORT && height <= MAX_VIEWPORT,
            "viewport {width}x{height} exceeds {MAX_VIEWPORT}"
        );
        let n = width as usize * height as usize;
        VisibilityBuffer {
            width,
            height,
            triangle: vec![Self::EMPTY; n],
            bary: vec![[0.0; 3]; n],
            inv_w: vec![0.0; n],
            culling: Culling::None,
        }
    }

    /// Empties the buffer for reuse. The barycentrics are left as they are: they mean
    /// something only where `triangle` is set (not clearing them saves 60% of the bytes a
    /// clear writes, a tenth of a 192x192 crop's visibility stage).
    pub fn clear(&mut self) {
        self.triangle.fill(Self::EMPTY);
        self.inv_w.fill(0.0);
    }

    /// Resizes the buffer to `width x height`, keeping its allocation (a buffer reused
    /// for windows of varying sizes reallocates only when one outgrows it), and empties
    /// it as [`VisibilityBuffer::clear`] does. Panics as [`VisibilityBuffer::new`] does.
    pub fn reset(&mut self, width: u32, height: u32) {
        self.resize(width, height);
        self.clear();
    }

    /// [`VisibilityBuffer::reset`] without the clear: the caller writes every
    /// `triangle` and `inv_w` value next.
    fn resize(&mut self, width: u32, height: u32) {
        assert!(
            width <= MAX_VIEWPORT && height <= MAX_VIEWPORT,
            "viewport {width}x{height} exceeds {MAX_VIEWPORT}"
        );
        let n = width as usize * height as usize;
        (self.width, self.height) = (width, height);
        self.triangle.resize(n, Self::EMPTY);
        self.bary.resize(n, [0.0; 3]);
        self.inv_w.resize(n, 0.0);
    }

    /// Index of pixel `(x, y)` in the flat arrays.
    pub fn index(&self, x: u32, y: u32) -> usize {
        y as usize * self.width as usize + x as usize
    }

    /// Number of covered pixels.
    pub fn covered_pixels(&self) -> usize {
        self.triangle.iter().filter(|&&t| t != Self::EMPTY).count()
    }

    /// [`VisibilityBuffer::rasterize_mesh`] without the weights: fills `triangle` and
    /// `inv_w` with the same values and leaves `bary` as it was (not this mesh's
    /// weights). Computing and storing a fragment's weights is most of a visible
    /// pixel's cost, and a caller that needs them at a few pixels computes those with
    /// [`VisibilityBuffer::fragment_at`].
    pub fn rasterize_visibility(
        &mut self,
        vertices: &[ScreenVertex],
        triangles: &[[u32; 3]],
    ) -> Result<(), BadTriangle> {
        self.visibility_with(vertices, triangles, crate::lanes::level())
            .map(|_| ())
    }

    /// [`VisibilityBuffer::rasterize_visibility`] at SIMD `level` (lowered to the CPU's;
    /// [`lanes::visibility`]): the same buffer at every level (tested).
    /// Returns whether the AVX-512 lanes drew.
    fn visibility_with(
        &mut self,
        vertices: &[ScreenVertex],
        triangles: &[[u32; 3]],
        level: Level,
    ) -> Result<bool, BadTriangle> {
        check_indices(vertices.len(), triangles)?;
        if !viewport_ok(self.width, self.height) {
            return Ok(false);
        }
        let n = self.triangle.len();
        let (depth, triangle) = (&mut self.inv_w[..n], &mut self.triangle[..n]);
        let (w, h, culling) = (self.width, self.height, self.culling);
        Ok(lanes::visibility(
            level,
            vertices,
            triangles,
            (w, h),
            culling,
            depth,
            triangle,
        ))
    }

    /// The fragment [`VisibilityBuffer::rasterize_mesh`] gives pixel `(x, y)`, after
    /// either it or [`VisibilityBuffer::rasterize_visibility`] filled the buffer from
    /// `vertices` and `triangles`: the same operations on the triangle recorded there,
    /// so the same bits (`inv_w` is the depth key the buffer holds). `None` where no
    /// triangle covers the pixel or `(x, y)` is outside the buffer.
    #[inline]
    pub fn fragment_at(
        &self,
        vertices: &[ScreenVertex],
        triangles: &[[u32; 3]],
        x: u32,
        y: u32,
    ) -> Option<Fragment> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let idx = self.index(x, y);
        let t = triangles.get(self.triangle[idx] as usize)?;
        // Three calls written out: through `map`, the snapping was a call of its own
        // per pixel (a sampled point's fragment is 1,024 per item in the loader).
        let fixed = |i: u32| vertices.get(i as usize).and_then(|&p| FixedVertex::new(p));
        let (Some(a), Some(b), Some(c)) = (fixed(t[0]), fixed(t[1]), fixed(t[2])) else {
            return None;
        };
        let (px, py) = ([a.x, b.x, c.x], [a.y, b.y, c.y]);
        // As [`TriangleSetup::from_fixed`]: the orientation's sign, the edges' values
        // (exact integers, as stepped to this pixel) and the area's reciprocal.
        let area = (b.x - a.x) * (c.y - a.y) - (c.x - a.x) * (b.y - a.y);
        let sign = if area > 0 { -1 } else { 1 };
        let centre = (x as i64 * ONE + HALF, y as i64 * ONE + HALF);
        let e = [0, 1, 2].map(|k| edge_value(&px, &py, k, edge_slopes(&px, &py, k, sign), centre));
        let mut f = fragment_of(
            [a.inv_w, b.inv_w, c.inv_w],
            x,
            y,
            e,
            1.0 / area.abs() as f64,
        );
        f.inv_w = self.inv_w[idx];
        Some(f)
    }

    /// Rasterizes a mesh with the depth test, recording the nearest triangle per pixel.
    pub fn rasterize_mesh(
        &mut self,
        vertices: &[ScreenVertex],
        triangles: &[[u32; 3]],
    ) -> Result<(), BadTriangle> {
        self.rasterize_mesh_with(vertices, triangles, |_, _, _| {})
    }

    /// As [`VisibilityBuffer::rasterize_mesh`], also calling `on_visible(pixel_index,
    /// triangle, fragment)` whenever a fragment passes the depth test (a later, nearer
    /// fragment overwrites it), so callers can fill their own buffers in the same pass.
    pub fn rasterize_mesh_with(
        &mut self,
        vertices: &[ScreenVertex],
        triangles: &[[u32; 3]],
        mut on_visible: impl FnMut(usize, u32, &Fragment),
    ) -> Result<(), BadTriangle> {
        check_indices(vertices.len(), triangles)?;
        if !viewport_ok(self.width, self.height) {
            return Ok(());
        }
        let width = self.width as usize;
        // All three cut to the same length, so that the depth test's bounds check
        // covers the two stores (LLVM drops theirs).
        let n = self.triangle.len();
        let (depth, triangle, bary) = (
            &mut self.inv_w[..n],
            &mut self.triangle[..n],
            &mut self.bary[..n],
        );
        let (w, h, culling) = (self.width, self.height, self.culling);
        for_each_drawable(vertices, triangles, w, h, culling, |ti, setup| {
            setup.for_each_nearer(depth, width, |idx, f| {
                triangle[idx] = ti;
                bary[idx] = f.bary;
                on_visible(idx, ti, &f);
            });
        });
        Ok(())
    }
}

/// A rectangle of image pixels, `[x0, x0 + width) x [y0, y0 + height)`: the part of an
/// image a windowed buffer holds ([`rasterize_mesh_official_in`]), row-major.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PixelWindow {
    /// First column.
    pub x0: u32,
    /// First row.
    pub y0: u32,
    /// Columns (0 for an empty window).
    pub width: u32,
    /// Rows (0 for an empty window).
    pub height: u32,
}

impl PixelWindow {
    /// The whole `width x height` image.
    pub fn whole(width: u32, height: u32) -> Self {
        PixelWindow {
            x0: 0,
            y0: 0,
            width,
            height,
        }
    }

    /// The pixels [`rasterize_mesh_official`] can write for `vertices` in a `width x
    /// height` image: the integer points from the ceiling of the smallest to the floor
    /// of the largest coordinate of the vertices it draws (`official_vertex_ok`),
    /// clamped to the image. Each triangle's clamped box is its box clamped to the
    /// image, so rasterizing into this window writes exactly what the whole image gets.
    /// Empty (zero-sized) when no pixel can be written.
    pub fn official_extent(vertices: &[ScreenVertex], width: u32, height: u32) -> Self {
        let drawn = vertices.iter().filter(|p| official_vertex_ok(p));
        let (mut x_lo, mut x_hi, mut y_lo, mut y_hi) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
        for p in drawn {
            (x_lo, x_hi) = (x_lo.min(p.x), x_hi.max(p.x));
            (y_lo, y_hi) = (y_lo.min(p.y), y_hi.max(p.y));
        }
        let span = |lo: f32, hi: f32, n: u32| {
            let first = (lo.ceil() as i64).max(0);
            let last = (hi.floor() as i64).min(n as i64 - 1);
            if last < first {
                (0, 0)
            } else {
                (first as u32, (last - first + 1) as u32)
            }
        };
        let ((x0, width), (y0, height)) = (span(x_lo, x_hi, width), span(y_lo, y_hi, height));
        PixelWindow {
            x0,
            y0,
            width,
            height,
        }
    }

    /// The row-major index in the window of image pixel `(x, y)`, `None` outside it.
    #[inline]
    pub fn index(&self, x: i64, y: i64) -> Option<usize> {
        let (dx, dy) = (x - self.x0 as i64, y - self.y0 as i64);
        let inside = (0..self.width as i64).contains(&dx) && (0..self.height as i64).contains(&dy);
        inside.then(|| dy as usize * self.width as usize + dx as usize)
    }

    /// Number of pixels.
    pub fn len(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Whether the window holds no pixel.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Whether [`rasterize_mesh_official`] draws triangles using vertex `p`: finite
/// coordinates in front of the camera (`inv_w > 0`).
pub(crate) fn official_vertex_ok(p: &ScreenVertex) -> bool {
    p.x.is_finite() && p.y.is_finite() && p.inv_w > 0.0
}

/// The official loader's rasterizer, reproduced for comparison (`face3d`'s
/// `render_colors` as the release's code uses it): pixel `(i, j)` is sampled at the
/// integer point `(i, j)` (our pixel's top-left corner, half a pixel from our sample
/// point), a point is inside when its float32 barycentrics `u >= 0, v >= 0, u + v < 1`
/// (no consistent rule on shared edges: a centre on one can be drawn twice or not at
/// all), weights and depth are interpolated linearly in screen space (no perspective
/// correction), depth is `-w` with larger nearer, and on a tie the earlier triangle keeps
/// the pixel. Fills the same buffers as [`VisibilityBuffer::rasterize_mesh`]; `inv_w`
/// then holds that screen-space depth key.
pub fn rasterize_mesh_official(
    buffer: &mut VisibilityBuffer,
    vertices: &[ScreenVertex],
    triangles: &[[u32; 3]],
) -> Result<(), BadTriangle> {
    let whole = PixelWindow::whole(buffer.width, buffer.height);
    rasterize_mesh_official_in(buffer, whole, vertices, triangles)
}

/// [`rasterize_mesh_official`] of an image into a buffer holding only `window` of it
/// (`buffer` is resized to `window.width x window.height`, keeping its allocation, and
/// every pixel written; vertices are in image coordinates).
/// Every sample point, weight and depth is computed in image coordinates as over the
/// whole image and only the box each triangle walks is clamped to the window, so the
/// buffer holds the whole image's values over the window; with
/// [`PixelWindow::official_extent`] that is every pixel the whole image gets.
pub fn rasterize_mesh_official_in(
    buffer: &mut VisibilityBuffer,
    window: PixelWindow,
    vertices: &[ScreenVertex],
    triangles: &[[u32; 3]],
) -> Result<(), BadTriangle> {
    official_in(
        buffer,
        window,
        vertices,
        triangles,
        crate::lanes::level(),
        true,
    )
}

/// [`rasterize_mesh_official_in`] for a mask: fills `triangle` and `inv_w` with the
/// same values and leaves `bary` as it was (not this mesh's weights). The weights are
/// most of a pixel's writes, and a mask needs only which triangle each pixel shows.
pub fn rasterize_official_visibility_in(
    buffer: &mut VisibilityBuffer,
    window: PixelWindow,
    vertices: &[ScreenVertex],
    triangles: &[[u32; 3]],
) -> Result<(), BadTriangle> {
    official_in(
        buffer,
        window,
        vertices,
        triangles,
        crate::lanes::level(),
        false,
    )
}

/// [`rasterize_mesh_official_in`] at SIMD `level` (lowered to the CPU's;
/// [`lanes::OfficialTriangles`]): the same buffer at every level
/// (tested); the weights written or not
/// (`weights`, [`rasterize_official_visibility_in`]).
fn official_in(
    buffer: &mut VisibilityBuffer,
    window: PixelWindow,
    vertices: &[ScreenVertex],
    triangles: &[[u32; 3]],
    level: Level,
    weights: bool,
) -> Result<(), BadTriangle> {
    check_indices(vertices.len(), triangles)?;
    buffer.resize(window.width, window.height);
    buffer.triangle.fill(VisibilityBuffer::EMPTY);
    buffer.inv_w.fill(f32::NEG_INFINITY);
    let (ox, oy) = (window.x0 as i64, window.y0 as i64);
    let (w, h) = (window.width as i64, window.height as i64);
    let kernel = lanes::OfficialTriangles::new(level, weights);
    // Each vertex's depth once (`-1 / inv_w`), NaN where it is not drawn.
    let depths: Vec<f32> = vertices
        .iter()
        .map(|p| {
            if official_vertex_ok(p) {
                -1.0 / p.inv_w
            } else {
                f32::NAN
            }
        })
        .collect();
    for (ti, t) in triangles.iter().enumerate() {
        let [p0, p1, p2] = t.map(|v| vertices[v as usize]);
        let depth = t.map(|v| depths[v as usize]);
        if depth.iter().any(|d| d.is_nan()) {
            continue;
        }
        let x_min = ceil_to_i64(p0.x.min(p1.x).min(p2.x)).max(ox);
        let x_max = floor_to_i64(p0.x.max(p1.x).max(p2.x)).min(ox + w - 1);
        let y_min = ceil_to_i64(p0.y.min(p1.y).min(p2.y)).max(oy);
        let y_max = floor_to_i64(p0.y.max(p1.y).max(p2.y)).min(oy + h - 1);
        if x_max < x_min || y_max < y_min {
            continue;
        }
        let tri = OfficialTriangle::new(ti as u32, [p0, p1, p2], depth);
        let area = OfficialSpan {
            xs: x_min..x_max + 1,
            ys: y_min..y_max + 1,
            origin: (ox, oy),
            width: w,
        };
        kernel.draw(buffer, &tri, area);
    }
    Ok(())
}

/// One triangle of [`rasterize_mesh_official_in`]: what every pixel's test needs.
pub(crate) struct OfficialTriangle {
    pub(crate) index: u32,
    pub(crate) p0: (f32, f32),
    /// `p2 - p0` and `p1 - p0`.
    pub(crate) v0: (f32, f32),
    pub(crate) v1: (f32, f32),
    /// `v0.v0`, `v0.v1`, `v1.v1`.
    pub(crate) dots: (f32, f32, f32),
    pub(crate) inv_deno: f32,
    pub(crate) depth: [f32; 3],
}

/// `v.ceil() as i64` for a finite `v`, without the library call `ceil` is on the x86-64
/// baseline: the truncation, one up where it lies below `v` (for `|v| >= 2^23` every
/// float is an integer and the truncation is `v`; beyond `i64` both saturate).
#[inline]
fn ceil_to_i64(v: f32) -> i64 {
    let t = v as i64;
    if (t as f32) < v {
        t.saturating_add(1)
    } else {
        t
    }
}

/// `v.floor() as i64` for a finite `v`, as [`ceil_to_i64`].
#[inline]
fn floor_to_i64(v: f32) -> i64 {
    let t = v as i64;
    if (t as f32) > v {
        t.saturating_sub(1)
    } else {
        t
    }
}

impl OfficialTriangle {
    /// The triangle `index` with these corners and their depths (`-1 / inv_w`): the
    /// official code's per-triangle values, in its float32 operations.
    fn new(index: u32, [p0, p1, p2]: [ScreenVertex; 3], depth: [f32; 3]) -> Self {
        let (v0x, v0y, v1x, v1y) = (p2.x - p0.x, p2.y - p0.y, p1.x - p0.x, p1.y - p0.y);
        let (dot00, dot01, dot11) = (
            v0x * v0x + v0y * v0y,
            v0x * v1x + v0y * v1y,
            v1x * v1x + v1y * v1y,
        );
        let deno = dot00 * dot11 - dot01 * dot01;
        let inv_deno = if deno == 0.0 { 0.0 } else { 1.0 / deno };
        OfficialTriangle {
            index,
            p0: (p0.x, p0.y),
            v0: (v0x, v0y),
            v1: (v1x, v1y),
            dots: (dot00, dot01, dot11),
            inv_deno,
            depth,
        }
    }

    /// The official barycentrics `(u, v)` of integer point `(x, y)`: the point is inside
    /// when `u >= 0, v >= 0, u + v < 1`, and its weights are `[1 - u - v, v, u]`.
    #[inline]
    pub(crate) fn uv_at(&self, x: i64, y: i64) -> (f32, f32) {
        let ((p0x, p0y), (v0x, v0y), (v1x, v1y)) = (self.p0, self.v0, self.v1);
        let (dot00, dot01, dot11) = self.dots;
        let (v2x, v2y) = (x as f32 - p0x, y as f32 - p0y);
        let (dot02, dot12) = (v0x * v2x + v0y * v2y, v1x * v2x + v1y * v2y);
        let u = (dot11 * dot02 - dot01 * dot12) * self.inv_deno;
        let v = (dot00 * dot12 - dot01 * dot02) * self.inv_deno;
        (u, v)
    }
}

/// The weights [`rasterize_mesh_official`] writes at image pixel `(x, y)` when
/// `triangle` (vertex indices into `vertices`) is the one it shows there: the same
/// float32 operations, so the same bits. With [`rasterize_official_visibility_in`],
/// which leaves the weights out, a caller computes them only where it needs them.
pub fn official_weights(vertices: &[ScreenVertex], triangle: [u32; 3], x: i64, y: i64) -> [f32; 3] {
    let corners = triangle.map(|v| vertices[v as usize]);
    let depth = corners.map(|p| -1.0 / p.inv_w);
    let (u, v) = OfficialTriangle::new(0, corners, depth).uv_at(x, y);
    [1.0 - u - v, v, u]
}

/// The pixels a triangle's box covers (image coordinates, the window's clamp applied)
/// and where the window lies.
pub(crate) struct OfficialSpan {
    pub(crate) xs: std::ops::Range<i64>,
    pub(crate) ys: std::ops::Range<i64>,
    pub(crate) origin: (i64, i64),
    pub(crate) width: i64,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn sv(x: f32, y: f32) -> ScreenVertex {
        ScreenVertex { x, y, inv_w: 1.0 }
    }

    fn coverage(tris: &[[ScreenVertex; 3]], w: u32, h: u32) -> Vec<u32> {
        let mut count = vec![0u32; (w * h) as usize];
        for t in tris {
            rasterize_triangle(*t, w, h, |f| count[(f.y * w + f.x) as usize] += 1);
        }
        count
    }

    #[test]
    fn square_of_two_triangles_covers_each_pixel_once() {
        // Square (2,2)-(18,18); the diagonal x = y passes through every pixel centre
        // (i + 0.5, i + 0.5)... no: through corners. Use a square offset by 0.5 so the
        // diagonal and all four sides pass exactly through pixel centres.
        let (a, b, c, d) = (sv(2.5, 2.5), sv(18.5, 2.5), sv(18.5, 18.5), sv(2.5, 18.5));
        for (t1, t2) in [
            ([a, b, c], [a, c, d]),
            ([a, c, b], [a, d, c]),
            ([a, b, d], [b, c, d]),
            ([d, b, a], [c, b, d]),
        ] {
            let cov = coverage(&[t1, t2], 24, 24);
            assert!(cov.iter().all(|&c| c <= 1), "a pixel drawn twice");
            // Pixel centres inside [2.5, 18.5) on both axes by the top-left rule: the top
            // and left sides are in, the bottom and right sides out: 16 x 16.
            assert_eq!(cov.iter().sum::<u32>(), 256);
            for y in 0..24 {
                for x in 0..24 {
                    let inside = (2..18).contains(&x) && (2..18).contains(&y);
                    assert_eq!(cov[(y * 24 + x) as usize] == 1, inside, "pixel ({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn hand_derived_right_triangle() {
        // Vertices (0.5,0.5), (4.5,0.5), (0.5,4.5): centres (i+.5, j+.5) with i + j <= 4
        // lie in the closed triangle. The top edge (y = 0.5) and the left edge (x = 0.5)
        // are in; the hypotenuse i + j = 4 is neither top nor left: out.
        let cov = coverage(&[[sv(0.5, 0.5), sv(4.5, 0.5), sv(0.5, 4.5)]], 6, 6);
        let expected: Vec<(u32, u32)> = (0..6)
            .flat_map(|j| (0..6).map(move |i| (i, j)))
            .filter(|(i, j)| i + j < 4)
            .collect();
        for y in 0..6 {
            for x in 0..6 {
                assert_eq!(
                    cov[(y * 6 + x) as usize] == 1,
                    expected.contains(&(x, y)),
                    "({x}, {y})"
                );
            }
        }
        assert_eq!(expected.len(), 10);
        // The mirror image across the hypotenuse takes the hypotenuse's centres (a left
        // edge for it) and the bottom/right sides are out.
        let cov2 = coverage(&[[sv(4.5, 0.5), sv(4.5, 4.5), sv(0.5, 4.5)]], 6, 6);
        let both: Vec<u32> = cov.iter().zip(&cov2).map(|(a, b)| a + b).collect();
        assert!(both.iter().all(|&c| c <= 1));
        assert_eq!(both.iter().sum::<u32>(), 16);
    }

    #[test]
    fn row_coverage_equals_the_scalar_reference() {
        // The SSE2 masks (on x86-64) against one pixel at a time, for random edge
        // values around zero (where the signs change), steps, biases and widths 1-64.
        let mut r = Rng::new(11);
        for _ in 0..2000 {
            let width = 1 + r.below(64) as u32;
            let scale = 1i64 << r.below(40);
            let mut rand = |s: i64| (r.uniform(-1.0, 1.0) * s as f64) as i64;
            let dx = [rand(scale), rand(scale), rand(scale)];
            let dy = [rand(scale), rand(scale), rand(scale)];
            let e = [0, 1, 2].map(|k| rand(scale) - dx[k] * (width as i64 / 2));
            let bias = [0, 1, 2].map(|k| -((e[k] ^ dx[k]) & 1));
            let mut fast = RowCoverage::new(e, dx, dy, bias, width);
            let mut slow = ScalarRowCoverage::new(e, dx, dy, bias, width);
            for _ in 0..4 {
                assert_eq!(fast.next_row(), slow.next_row(), "{e:?} {dx:?} {width}");
            }
        }
    }

    #[test]
    fn row_walk_visits_what_the_pixel_walk_visits() {
        // Random triangles with boxes up to 64 pixels wide, some with vertices off the
        // viewport: the same pixels, in the same order, with the same edge values.
        let mut r = Rng::new(12);
        let mut narrow = 0;
        for _ in 0..3000 {
            let size = r.uniform(0.5, 70.0);
            let (cx, cy) = (r.uniform(-20.0, 120.0), r.uniform(-20.0, 120.0));
            let mut v = || {
                sv(
                    (cx + r.uniform(0.0, size)) as f32,
                    (cy + r.uniform(0.0, size)) as f32,
                )
            };
            let Some(t) = TriangleSetup::new([v(), v(), v()], 100, 100, Culling::None) else {
                continue;
            };
            if t.x1 - t.x0 >= 64 {
                continue;
            }
            narrow += 1;
            let (mut rows, mut pixels) = (Vec::new(), Vec::new());
            t.walk_rows(|x, y, e| rows.push((x, y, e)));
            t.walk_pixels(|x, y, e| pixels.push((x, y, e)));
            assert_eq!(rows, pixels);
        }
        assert!(narrow > 1500, "{narrow} triangles tested");
    }

    #[test]
    fn top_left_bias_follows_the_rule() {
        // Hand cases, y down: a horizontal edge running left (ey > 0) has the interior
        // below it (top: 0), running right it is a bottom edge (-1); an edge going down
        // (ex > 0) has the interior to its right (left: 0), going up it is a right edge.
        assert_eq!(top_left_bias(0, 5), 0);
        assert_eq!(top_left_bias(0, -5), -1);
        assert_eq!(top_left_bias(3, -7), 0);
        assert_eq!(top_left_bias(-3, 7), -1);
        // Exactly one of an edge and its reverse qualifies, up to the guard band's
        // extremes (|ex|, |ey| < 2^25), including the steps next to zero.
        let mut r = Rng::new(14);
        let big = 1i64 << 25;
        for _ in 0..20000 {
            let pick = |r: &mut Rng| match r.below(4) {
                0 => 0,
                1 => r.below(3) as i64 - 1,
                2 => big - 1 - r.below(2) as i64,
                _ => (r.uniform(-1.0, 1.0) * (big - 1) as f64) as i64,
            };
            let (ex, ey) = (pick(&mut r), pick(&mut r));
            if (ex, ey) == (0, 0) {
                continue;
            }
            let expected = if ex > 0 || (ex == 0 && ey > 0) { 0 } else { -1 };
            assert_eq!(top_left_bias(ex, ey), expected, "{ex} {ey}");
            assert_eq!(top_left_bias(-ex, -ey), -1 - expected, "{ex} {ey}");
        }
    }

    #[test]
    fn box_walk_visits_what_the_pixel_walk_visits() {
        // Small triangles (boxes up to 8x8 and a little beyond), half of them with
        // vertices on the half-pixel grid so that edges pass through pixel centres
        // (where the top-left bias decides), some cut by the viewport's border: the
        // box walk (`walk` for a small triangle) gives the same pixels, in the same
        // order, with the same edge values as the pixel walk.
        let mut r = Rng::new(13);
        let mut boxes = [0usize; 3];
        for i in 0..6000 {
            let size = r.uniform(0.3, 10.0);
            let (cx, cy) = (r.uniform(-6.0, 40.0), r.uniform(-6.0, 40.0));
            let mut v = || {
                let (mut x, mut y) = (cx + r.uniform(0.0, size), cy + r.uniform(0.0, size));
                if i % 2 == 0 {
                    (x, y) = ((x * 2.0).round() / 2.0, (y * 2.0).round() / 2.0);
                }
                sv(x as f32, y as f32)
            };
            let Some(t) = TriangleSetup::new([v(), v(), v()], 36, 36, Culling::None) else {
                continue;
            };
            assert!(t.small);
            match (t.x1 - t.x0, t.y1 - t.y0) {
                (0..=3, 0..=3) => boxes[0] += 1,
                (0..=3, 4..=7) => boxes[1] += 1,
                (4..=7, 0..=7) => boxes[2] += 1,
                _ => {}
            }
            let (mut walked, mut pixels) = (Vec::new(), Vec::new());
            t.walk(|x, y, e| walked.push((x, y, e)));
            t.walk_pixels(|x, y, e| pixels.push((x, y, e)));
            assert_eq!(walked, pixels);
        }
        assert!(
            boxes.iter().all(|&n| n > 300),
            "boxes of each kind: {boxes:?}"
        );
    }

    #[test]
    fn fan_and_jittered_grid_have_no_overlap_and_no_gap() {
        let mut r = Rng::new(3);
        // A 10x10 grid of quads with jittered shared vertices.
        let n = 10;
        let mut grid = vec![[0f32; 2]; (n + 1) * (n + 1)];
        for j in 0..=n {
            for i in 0..=n {
                let jitter = |r: &mut Rng| {
                    if i == 0 || j == 0 || i == n || j == n {
                        0.0
                    } else {
                        r.uniform(-1.2, 1.2) as f32
                    }
                };
                grid[j * (n + 1) + i] = [
                    4.0 + 5.0 * i as f32 + jitter(&mut r),
                    4.0 + 5.0 * j as f32 + jitter(&mut r),
                ];
            }
        }
        let p = |i: usize, j: usize| sv(grid[j * (n + 1) + i][0], grid[j * (n + 1) + i][1]);
        let mut tris = Vec::new();
        for j in 0..n {
            for i in 0..n {
                tris.push([p(i, j), p(i + 1, j), p(i + 1, j + 1)]);
                tris.push([p(i, j + 1), p(i + 1, j + 1), p(i, j)]); // other winding
            }
        }
        let cov = coverage(&tris, 60, 60);
        assert!(cov.iter().all(|&c| c <= 1));
        // The outer square is [4, 54): centres 4.5 .. 53.5 -> 50 x 50, every one covered.
        for y in 0..60u32 {
            for x in 0..60u32 {
                let inside = (4..54).contains(&x) && (4..54).contains(&y);
                assert_eq!(cov[(y * 60 + x) as usize] == 1, inside, "({x}, {y})");
            }
        }
        // A fan of 12 triangles around an interior point.
        let c = sv(20.3, 19.7);
        let ring: Vec<ScreenVertex> = (0..12)
            .map(|k| {
                let a = k as f32 * std::f32::consts::TAU / 12.0;
                sv(20.0 + 13.0 * a.cos(), 20.0 + 11.0 * a.sin())
            })
            .collect();
        let fan: Vec<[ScreenVertex; 3]> =
            (0..12).map(|k| [c, ring[k], ring[(k + 1) % 12]]).collect();
        assert!(coverage(&fan, 40, 40).iter().all(|&c| c <= 1));
    }

    #[test]
    fn covered_count_is_close_to_analytic_area() {
        // A pixel centre inside the triangle but counted out (or outside but in) must lie
        // within half a pixel diagonal of an edge, so |count - area| <= perimeter * 0.71 + 4.
        let mut r = Rng::new(11);
        for _ in 0..300 {
            let v: Vec<ScreenVertex> = (0..3)
                .map(|_| sv(r.uniform(0.0, 64.0) as f32, r.uniform(0.0, 64.0) as f32))
                .collect();
            let t = [v[0], v[1], v[2]];
            let area = 0.5
                * ((t[1].x - t[0].x) * (t[2].y - t[0].y) - (t[2].x - t[0].x) * (t[1].y - t[0].y))
                    .abs() as f64;
            let d = |a: ScreenVertex, b: ScreenVertex| ((a.x - b.x).hypot(a.y - b.y)) as f64;
            let perimeter = d(t[0], t[1]) + d(t[1], t[2]) + d(t[2], t[0]);
            let count = coverage(&[t], 64, 64).iter().sum::<u32>() as f64;
            assert!(
                (count - area).abs() <= perimeter * 0.71 + 4.0,
                "count {count} area {area}"
            );
        }
    }

    #[test]
    fn perspective_correct_barycentrics() {
        // A slanted 3D triangle through a pinhole camera: the interpolated 3D point must
        // project back onto the pixel centre.
        let f = 300.0f64;
        let project = |p: [f64; 3]| ScreenVertex {
            x: (f * p[0] / p[2] + 50.0) as f32,
            y: (f * p[1] / p[2] + 50.0) as f32,
            inv_w: (1.0 / p[2]) as f32,
        };
        let pts = [[-0.1, -0.08, 0.4], [0.12, -0.05, 0.9], [0.0, 0.1, 0.6]];
        let v = pts.map(project);
        let mut n = 0;
        rasterize_triangle(v, 100, 100, |fr| {
            let p: Vec<f64> = (0..3)
                .map(|c| (0..3).map(|k| fr.bary[k] as f64 * pts[k][c]).sum())
                .collect();
            let (u, w) = (f * p[0] / p[2] + 50.0, f * p[1] / p[2] + 50.0);
            assert!(
                (u - (fr.x as f64 + 0.5)).abs() < 2e-3 && (w - (fr.y as f64 + 0.5)).abs() < 2e-3,
                "{u} {w} {fr:?}"
            );
            // Screen barycentrics interpolate the 2D vertices to the centre.
            let sx: f64 = (0..3)
                .map(|k| fr.screen_bary[k] as f64 * v[k].x as f64)
                .sum();
            assert!((sx - (fr.x as f64 + 0.5)).abs() < 1e-3);
            let sum: f32 = fr.bary.iter().sum();
            assert!(
                (sum - 1.0).abs() < 1e-5
                    && fr.bary.iter().all(|&b| (-1e-5..=1.0 + 1e-5).contains(&b))
            );
            // Depth key is 1 / z of the interpolated point.
            assert!((fr.inv_w as f64 - 1.0 / p[2]).abs() < 1e-4);
            n += 1;
        });
        assert!(n > 100);
    }

    #[test]
    fn depth_test_keeps_the_nearest_and_ties_keep_the_first() {
        let near = |x, y| ScreenVertex { x, y, inv_w: 2.0 };
        let far = |x, y| ScreenVertex { x, y, inv_w: 1.0 };
        let verts = vec![
            near(1.0, 1.0),
            near(15.0, 1.0),
            near(1.0, 15.0),
            far(2.0, 2.0),
            far(16.0, 2.0),
            far(2.0, 16.0),
        ];
        for tris in [vec![[0, 1, 2], [3, 4, 5]], vec![[3, 4, 5], [0, 1, 2]]] {
            let mut vb = VisibilityBuffer::new(20, 20);
            vb.rasterize_mesh(&verts, &tris).unwrap();
            let near_id = tris.iter().position(|t| t[0] == 0).unwrap() as u32;
            let idx = vb.index(5, 5);
            assert_eq!(vb.triangle[idx], near_id);
            assert!((vb.inv_w[idx] - 2.0).abs() < 1e-6);
        }
        // Equal depth: the earlier triangle keeps the pixel.
        let verts = vec![near(1.0, 1.0), near(15.0, 1.0), near(1.0, 15.0)];
        let mut vb = VisibilityBuffer::new(20, 20);
        vb.rasterize_mesh(&verts, &[[0, 1, 2], [0, 2, 1]]).unwrap();
        assert!(
            vb.triangle
                .iter()
                .all(|&t| t == VisibilityBuffer::EMPTY || t == 0)
        );
        assert!(vb.covered_pixels() > 50);
    }

    #[test]
    fn invalid_and_off_screen_triangles_are_skipped_safely() {
        let cases = [
            [sv(1.0, 1.0), sv(5.0, 5.0), sv(9.0, 9.0)], // collinear
            [sv(1.0, 1.0), sv(1.0, 1.0), sv(9.0, 2.0)], // repeated vertex
            [sv(f32::NAN, 1.0), sv(5.0, 5.0), sv(9.0, 1.0)], // NaN
            [sv(-50.0, -50.0), sv(-10.0, -50.0), sv(-30.0, -10.0)], // off-screen
            [sv(1e9, 1.0), sv(5.0, 5.0), sv(9.0, 1.0)], // outside the guard band
            [
                ScreenVertex {
                    x: 1.0,
                    y: 1.0,
                    inv_w: -1.0,
                },
                sv(9.0, 1.0),
                sv(1.0, 9.0),
            ], // behind
        ];
        for t in cases {
            assert_eq!(coverage(&[t], 16, 16).iter().sum::<u32>(), 0, "{t:?}");
        }
        // Partly off-screen: only in-bounds pixels, and all of them.
        let cov = coverage(
            &[[sv(-20.0, -20.0), sv(60.0, -20.0), sv(-20.0, 60.0)]],
            16,
            16,
        );
        assert_eq!(cov.iter().sum::<u32>(), 256);
        let mut vb = VisibilityBuffer::new(4, 4);
        let err = vb
            .rasterize_mesh(&[sv(0.0, 0.0)], &[[0, 1, 2]])
            .unwrap_err();
        assert_eq!(err.triangle, 0);
        assert!(err.to_string().contains("refers to a vertex"));
    }

    #[test]
    fn official_mode_samples_corners_and_interpolates_in_screen_space() {
        // A right triangle (0,0), (4,0), (0,4): integer points with i + j < 4 are in.
        let mut vb = VisibilityBuffer::new(6, 6);
        rasterize_mesh_official(
            &mut vb,
            &[sv(0.0, 0.0), sv(4.0, 0.0), sv(0.0, 4.0)],
            &[[0, 1, 2]],
        )
        .unwrap();
        for y in 0..6u32 {
            for x in 0..6u32 {
                assert_eq!(vb.triangle[vb.index(x, y)] == 0, x + y < 4, "({x}, {y})");
            }
        }
        // Weights are screen-space: at (1, 1) they are (0.5, 0.25, 0.25) whatever the depths.
        let far = ScreenVertex {
            x: 4.0,
            y: 0.0,
            inv_w: 0.1,
        };
        rasterize_mesh_official(&mut vb, &[sv(0.0, 0.0), far, sv(0.0, 4.0)], &[[0, 1, 2]]).unwrap();
        let b = vb.bary[vb.index(1, 1)];
        assert!(
            (b[0] - 0.5).abs() < 1e-6 && (b[1] - 0.25).abs() < 1e-6 && (b[2] - 0.25).abs() < 1e-6,
            "{b:?}"
        );
    }

    #[test]
    fn the_inline_ceil_and_floor_are_the_librarys() {
        let mut r = Rng::new(41);
        let mut values = vec![0.0f32, -0.0, 0.5, -0.5, 1.0, -1.0, 8388607.5, -8388607.5];
        values.extend([8388608.0, 1e20, -1e20, 0.99999994, -0.99999994, 2.5, -2.5]);
        for _ in 0..100_000 {
            values.push(r.uniform(-2000.0, 2000.0) as f32);
            values.push(r.below(4000) as f32 - 2000.0);
        }
        for v in values {
            assert_eq!(ceil_to_i64(v), v.ceil() as i64, "{v}");
            assert_eq!(floor_to_i64(v), v.floor() as i64, "{v}");
        }
    }

    /// A random mesh over a `w x h` viewport: `vertex_count` vertices up to `spread`
    /// pixels past its edges (each coordinate through `snap`), `1 / w` drawn from
    /// `inv_w`, vertex 1 a copy of vertex 0 (so `last`, drawn after `triangle_count`
    /// random triangles, may be degenerate).
    fn random_mesh(
        r: &mut Rng,
        (w, h): (u32, u32),
        spread: f64,
        snap: impl Fn(f64) -> f64,
        inv_w: (f64, f64),
        (vertex_count, triangle_count): (usize, usize),
        last: [u32; 3],
    ) -> (Vec<ScreenVertex>, Vec<[u32; 3]>) {
        let mut vertices: Vec<ScreenVertex> = (0..vertex_count)
            .map(|_| ScreenVertex {
                x: snap(r.uniform(-spread, w as f64 + spread)) as f32,
                y: snap(r.uniform(-spread, h as f64 + spread)) as f32,
                inv_w: r.uniform(inv_w.0, inv_w.1) as f32,
            })
            .collect();
        vertices[1] = vertices[0];
        let mut triangles: Vec<[u32; 3]> = (0..triangle_count)
            .map(|_| [0; 3].map(|_| r.below(vertex_count as u64) as u32))
            .collect();
        triangles.push(last);
        (vertices, triangles)
    }

    #[test]
    fn visibility_lanes_give_the_pixel_walks_buffer_for_small_triangles() {
        // Crowds of small triangles (each within a few pixels of its own centre, as a
        // face crop's are: boxes from one pixel to past sixteen wide, up to 30 tall),
        // overlapping, of both windings, some cut by the viewport's edges, vertices at
        // fractional and pixel-centre positions (edge values exactly 0), depths drawn
        // from a few values (exact ties: the earlier triangle keeps the pixel): the
        // widest lanes give the pixel walk's triangles and depths bit for bit.
        let mut r = Rng::new(47);
        let (mut widths, mut drawn) = ([0usize; 3], 0usize);
        for case in 0..400 {
            let (w, h) = (1 + r.below(60) as u32, 1 + r.below(60) as u32);
            let snap = |v: f64| if case % 3 == 0 { v.round() + 0.5 } else { v };
            let mut vertices = Vec::new();
            let mut triangles = Vec::new();
            for t in 0..60u32 {
                let (cx, cy) = (
                    r.uniform(-4.0, w as f64 + 4.0),
                    r.uniform(-4.0, h as f64 + 4.0),
                );
                let (sx, sy) = if t % 4 == 0 {
                    (r.uniform(3.5, 9.0), r.uniform(0.5, 30.0))
                } else {
                    (r.uniform(0.3, 5.0), r.uniform(0.3, 5.0))
                };
                for _ in 0..3 {
                    vertices.push(ScreenVertex {
                        x: snap(cx + r.uniform(-sx, sx)) as f32,
                        y: snap(cy + r.uniform(-sy, sy)) as f32,
                        inv_w: [0.5, 0.75, 1.0][r.below(3) as usize] as f32
                            + if case % 2 == 0 {
                                r.uniform(0.0, 0.01) as f32
                            } else {
                                0.0
                            },
                    });
                }
                triangles.push([3 * t, 3 * t + 1, 3 * t + 2]);
            }
            for culling in [Culling::None, Culling::BackFaces] {
                let mut scalar = VisibilityBuffer::new(w, h);
                scalar.culling = culling;
                scalar
                    .visibility_with(&vertices, &triangles, Level::Scalar)
                    .unwrap();
                for level in crate::lanes::available() {
                    let mut wide = VisibilityBuffer::new(w, h);
                    wide.culling = culling;
                    let used = wide.visibility_with(&vertices, &triangles, level).unwrap();
                    assert_eq!(used, level == Level::Avx512);
                    assert_eq!(
                        wide.triangle, scalar.triangle,
                        "case {case} {culling:?} {level}"
                    );
                    let bits = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                    assert_eq!(
                        bits(&wide.inv_w),
                        bits(&scalar.inv_w),
                        "case {case} {level}"
                    );
                }
                drawn += scalar.covered_pixels();
            }
            for t in &triangles {
                let v = t.map(|i| vertices[i as usize]);
                if let Some(s) = TriangleSetup::new(v, w, h, Culling::None)
                    && s.small
                {
                    // Boxes up to 4, 8 and 16 pixels wide: each a path of its own.
                    match s.x1 - s.x0 {
                        0..4 => widths[0] += 1,
                        4..8 => widths[1] += 1,
                        8..16 => widths[2] += 1,
                        _ => {}
                    }
                }
            }
        }
        assert!(drawn > 50_000, "{drawn} pixels drawn");
        assert!(
            widths.iter().all(|&n| n > 500),
            "{widths:?} triangles by width"
        );
    }

    #[test]
    fn official_lanes_give_the_scalar_paths_buffer_bit_for_bit() {
        // Meshes of small and large, thin, degenerate (zero area: the official test
        // then takes every pixel of the box) and overlapping triangles, vertices at
        // fractional, integer and half-integer positions (weights exactly 0 and sums
        // exactly 1 on the edges), over windows of every width modulo 8 and offset:
        // the SIMD lanes and the scalar path give the same triangle, depth and weights
        // (bits) in every pixel. Without AVX2 (or AVX-512) the calls fall back to the
        // widest path the CPU has.
        let mut r = Rng::new(29);
        let mut drawn = 0usize;
        for case in 0..400 {
            let (w, h) = (8 + r.below(57) as u32, 8 + r.below(40) as u32);
            let spread = [2.0, 6.0, 30.0][case % 3];
            let snap = |v: f64| match case % 4 {
                0 => v.round(),
                1 => v.round() + 0.5,
                _ => v,
            };
            let (vertices, triangles) = random_mesh(
                &mut r,
                (w, h),
                spread,
                snap,
                (0.5, 2.0),
                (16, 24),
                [0, 1, 2],
            );
            let window = PixelWindow {
                x0: r.below(4) as u32,
                y0: r.below(4) as u32,
                width: w - 3,
                height: h - 3,
            };
            let run = |level: Level, weights: bool| {
                let mut b = VisibilityBuffer::new(1, 1);
                b.reset(window.width, window.height);
                official_in(&mut b, window, &vertices, &triangles, level, weights).unwrap();
                b
            };
            let (scalar, widest) = (
                run(Level::Scalar, true),
                run(crate::lanes::detected(), true),
            );
            // Without the weights, each level the CPU has (AVX-512's two rows where it
            // has them) gives the same triangles and depths.
            for visibility in crate::lanes::available().map(|level| run(level, false)) {
                assert_eq!(visibility.triangle, scalar.triangle, "case {case}");
                let bits =
                    |b: &VisibilityBuffer| b.inv_w.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&visibility), bits(&scalar), "case {case}");
            }
            assert_eq!(scalar.triangle, widest.triangle, "case {case}");
            for i in 0..scalar.triangle.len() {
                assert_eq!(
                    scalar.inv_w[i].to_bits(),
                    widest.inv_w[i].to_bits(),
                    "case {case} pixel {i}"
                );
                if scalar.triangle[i] != VisibilityBuffer::EMPTY {
                    drawn += 1;
                    assert_eq!(
                        scalar.bary[i].map(f32::to_bits),
                        widest.bary[i].map(f32::to_bits),
                        "case {case} pixel {i}"
                    );
                    // The weights computed alone for the triangle shown there.
                    let (x, y) = (
                        window.x0 as i64 + (i % window.width as usize) as i64,
                        window.y0 as i64 + (i / window.width as usize) as i64,
                    );
                    let t = triangles[scalar.triangle[i] as usize];
                    assert_eq!(
                        official_weights(&vertices, t, x, y).map(f32::to_bits),
                        scalar.bary[i].map(f32::to_bits),
                        "case {case} pixel {i}"
                    );
                }
            }
        }
        assert!(
            drawn > 10_000,
            "{drawn} pixels drawn: the cases must cover pixels"
        );
    }

    #[test]
    fn visibility_raster_and_fragments_at_pixels_give_the_full_rasters_bits() {
        // Random overlapping meshes of small, large, thin and degenerate triangles of
        // both windings, vertices at fractional and pixel-centre positions (edge values
        // exactly 0, the top-left rule deciding), some behind the camera or off the
        // viewport, with and without culling: the visibility raster holds the full
        // raster's triangles and depths, leaves the weights alone, and the fragment
        // computed at each covered pixel has the full raster's weights, bit for bit.
        let mut r = Rng::new(31);
        let mut drawn = 0usize;
        for case in 0..300 {
            let (w, h) = (4 + r.below(90) as u32, 4 + r.below(90) as u32);
            let spread = [2.0, 8.0, 40.0][case % 3];
            let snap = |v: f64| if case % 4 == 0 { v.round() + 0.5 } else { v };
            let (mut vertices, triangles) = random_mesh(
                &mut r,
                (w, h),
                spread,
                snap,
                (0.2, 3.0),
                (20, 40),
                [0, 1, 3],
            );
            vertices[2].inv_w = if case % 5 == 0 {
                -1.0
            } else {
                vertices[2].inv_w
            };
            let culling = if case % 2 == 0 {
                Culling::None
            } else {
                Culling::BackFaces
            };
            let mut full = VisibilityBuffer::new(w, h);
            full.culling = culling;
            full.rasterize_mesh(&vertices, &triangles).unwrap();
            let bits = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            // One pixel at a time, then the CPU's widest lanes (AVX-512 rows, where
            // the CPU has them).
            let mut visible = VisibilityBuffer::new(w, h);
            for level in crate::lanes::available() {
                visible.clear();
                visible.culling = culling;
                visible.bary.fill([7.0; 3]);
                let wide = visible
                    .visibility_with(&vertices, &triangles, level)
                    .unwrap();
                assert_eq!(wide, level == Level::Avx512, "{level:?}");
                assert_eq!(visible.triangle, full.triangle, "case {case} {level:?}");
                assert_eq!(
                    bits(&visible.inv_w),
                    bits(&full.inv_w),
                    "case {case} {level:?}"
                );
                assert!(visible.bary.iter().all(|b| *b == [7.0; 3]), "case {case}");
            }
            for y in 0..h {
                for x in 0..w {
                    let i = full.index(x, y);
                    let f = visible.fragment_at(&vertices, &triangles, x, y);
                    if full.triangle[i] == VisibilityBuffer::EMPTY {
                        assert!(f.is_none(), "case {case} pixel {x},{y}");
                        continue;
                    }
                    drawn += 1;
                    let f = f.expect("a covered pixel has a fragment");
                    assert_eq!((f.x, f.y), (x, y));
                    assert_eq!(f.bary.map(f32::to_bits), full.bary[i].map(f32::to_bits));
                    assert_eq!(f.inv_w.to_bits(), full.inv_w[i].to_bits());
                }
            }
            assert!(visible.fragment_at(&vertices, &triangles, w, 0).is_none());
        }
        assert!(
            drawn > 50_000,
            "{drawn} pixels drawn: the cases must cover pixels"
        );
    }

    #[test]
    fn official_raster_in_a_window_is_the_whole_images_over_it() {
        // Random overlapping meshes, some vertices off the image or behind the camera:
        // a buffer over any window holds the whole image's values there, and the
        // official extent holds every pixel the whole image gets.
        let mut r = Rng::new(13);
        let (w, h) = (48u32, 40u32);
        let mut part = VisibilityBuffer::new(3, 5);
        for case in 0..300 {
            let (cx, cy, spread) = (
                r.uniform(-20.0, 70.0),
                r.uniform(-20.0, 60.0),
                r.uniform(1.0, 40.0),
            );
            let vertices: Vec<ScreenVertex> = (0..12)
                .map(|_| ScreenVertex {
                    x: (cx + r.uniform(-spread, spread)) as f32,
                    y: (cy + r.uniform(-spread, spread)) as f32,
                    inv_w: if r.below(40) == 0 {
                        -1.0
                    } else {
                        r.uniform(0.5, 2.0) as f32
                    },
                })
                .collect();
            let triangles: Vec<[u32; 3]> = (0..10)
                .map(|_| [0; 3].map(|_| r.below(12) as u32))
                .collect();
            let mut whole = VisibilityBuffer::new(w, h);
            rasterize_mesh_official(&mut whole, &vertices, &triangles).unwrap();
            let extent = PixelWindow::official_extent(&vertices, w, h);
            let x0 = r.below(w as u64) as u32;
            let y0 = r.below(h as u64) as u32;
            let other = PixelWindow {
                x0,
                y0,
                width: r.below((w - x0) as u64 + 1) as u32,
                height: r.below((h - y0) as u64 + 1) as u32,
            };
            // One buffer for both windows and every case, of whatever size and content
            // the last call left: the rasterizer sizes it and writes every pixel.
            for window in [extent, other] {
                rasterize_mesh_official_in(&mut part, window, &vertices, &triangles).unwrap();
                assert_eq!((part.width, part.height), (window.width, window.height));
                for (y, x) in (0..h as i64).flat_map(|y| (0..w as i64).map(move |x| (y, x))) {
                    let i = whole.index(x as u32, y as u32);
                    let Some(j) = window.index(x, y) else {
                        if window == extent {
                            assert_eq!(whole.triangle[i], VisibilityBuffer::EMPTY, "{case}");
                        }
                        continue;
                    };
                    assert_eq!(part.triangle[j], whole.triangle[i], "{case} ({x}, {y})");
                    assert_eq!(part.inv_w[j].to_bits(), whole.inv_w[i].to_bits());
                    if whole.triangle[i] != VisibilityBuffer::EMPTY {
                        assert_eq!(
                            part.bary[j].map(f32::to_bits),
                            whole.bary[i].map(f32::to_bits)
                        );
                    }
                }
            }
        }
        // No vertex to draw: an empty window.
        let behind = [ScreenVertex {
            x: 1.0,
            y: 1.0,
            inv_w: 0.0,
        }; 3];
        assert!(PixelWindow::official_extent(&behind, w, h).is_empty());
    }

    #[test]
    fn back_face_culling_drops_one_winding() {
        let ccw_on_screen = [sv(1.0, 1.0), sv(1.0, 9.0), sv(9.0, 1.0)]; // y down: counter-clockwise as displayed
        let cw_on_screen = [sv(1.0, 1.0), sv(9.0, 1.0), sv(1.0, 9.0)];
        let count = |t: [ScreenVertex; 3]| {
            let mut n = 0;
            if let Some(s) = TriangleSetup::new(t, 16, 16, Culling::BackFaces) {
                s.for_each_covered(|_| n += 1);
            }
            n
        };
        assert!(count(ccw_on_screen) > 0);
        assert_eq!(count(cw_on_screen), 0);
    }
}
