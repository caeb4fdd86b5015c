//! `render`: PerspNet's geometric training targets for one sample, rendered once.
//!
//! Stages, each a function of its own:
//! 1. **Crop** ([`CropTransform`]): the official square box (centre of the 68 projected
//!    landmarks' bounding box, half-side 0.75 x its larger side) mapped onto a
//!    `size x size` crop. The box edge `[x0, x0 + side]` maps to `[0, size]` in the
//!    crop's continuous coordinates, so crop pixel `(i, j)` (centre `(i + 0.5, j + 0.5)`)
//!    looks at image point `x0 + (i + 0.5) side / size` (the crate's pixel-centre rule,
//!    `conventions::camera`).
//! 2. **Visibility** ([`FaceRenderer::render`]): the mesh plus the fans that close the
//!    eyes and mouth, projected with the release camera, mapped into the crop and
//!    rasterized ([`arkit_core::VisibilityBuffer`]) with the depth test. The fans take part in the
//!    depth test (a cheek seen through an eye opening at large yaw stays hidden) but are
//!    not face pixels.
//! 3. **Targets** ([`FaceTargets`]): the mask (visible mesh triangles), and per mask pixel
//!    the visible triangle's three vertex ids and perspective-correct barycentric
//!    weights: the ground-truth row of the correspondence matrix M. The coordinate map
//!    is not stored: it is `sum_k w_k V_k` (`FaceTargets::coordinate_map`).
//! 4. **UV position map** ([`UvMapper`]): the canonical face drawn in UV space: each
//!    texel holds the 3D position interpolated over the UV triangles, including the
//!    ring outside the contour and the three hole centroids (1,279 UV vertices for
//!    ARKit). It depends only on the mesh, so callers cache it per distinct mesh.
//! 5. **Points** ([`sample_points`]): `M` mask pixels drawn from a seed, repeated
//!    cyclically when the face has fewer than `M` pixels, as the official training does.
//!
//! The face mask over the whole image ([`FaceRenderer::render_full_mask`]) also comes
//! held over a window (`FaceRenderer::render_window_mask`, `WindowMask`): in
//! official mode only the pixels the face's vertices can cover are rasterized, with the
//! whole image's values there (tested against the whole-image raster on a face cut by
//! the image's edges and one in the middle).

use crate::mesh::topology::{FaceTopology, HoleFill};
use arkit_core::Rng;
use arkit_core::conventions::{Camera, Pose};
use arkit_core::{Error, Result};
use arkit_core::{PixelWindow, ScreenVertex, VisibilityBuffer};

use crate::crop::rules::MaskRule;
use crate::crop::{CropTransform, RuleSet};
use crate::store::face_targets::{FaceTargets, for_each_set_run};
use nalgebra::Point3;
use std::ops::Range;
/// Renders masks and correspondences for one topology (see module docs).
#[derive(Clone, Debug)]
pub struct FaceRenderer {
    topology: FaceTopology,
    hole_fill: HoleFill,
    triangles: Vec<[u32; 3]>,
    camera_projection: nalgebra::Matrix4<f64>,
    /// Whose rasterization rules [`FaceRenderer::render`] follows:
    /// [`RuleSet::Exact`] (pixel centres, the top-left fill rule, perspective-correct
    /// weights) or [`RuleSet::Official`] (the official loader's pipeline,
    /// [`crate::crop::official_crop`]: its crop box and `cv2` affine map (corner sampling),
    /// its rasterizer over the whole image
    /// ([`arkit_core::rasterize_mesh_official`]: integer sample points, its
    /// inside test, screen-space weights, earlier triangle on ties), its mask warped
    /// into the crop as `cv2.warpAffine` does, and each crop mask pixel's
    /// correspondence from the full-resolution buffer at its heaviest face tap).
    /// Set by [`FaceRenderer::with_rules`].
    rules: RuleSet,
}

impl FaceRenderer {
    /// A renderer for `topology`, projecting with `projection` (row-vector OpenGL form).
    pub fn new(topology: FaceTopology, projection: nalgebra::Matrix4<f64>) -> Result<Self> {
        if topology.vertex_count > u16::MAX as usize {
            return Err(Error::invalid(
                "topology",
                "more than 65,535 vertices do not fit the u16 correspondence ids",
            ));
        }
        let hole_fill = topology.hole_fill()?;
        let mut triangles = topology.triangles.clone();
        triangles.extend_from_slice(&hole_fill.triangles);
        Ok(FaceRenderer {
            topology,
            hole_fill,
            triangles,
            camera_projection: projection,
            rules: RuleSet::Exact,
        })
    }

    /// Closes the eye and mouth holes with `holes` (triangles over the mesh's own
    /// vertices, drawn after the mesh) instead of the centroid fans: in
    /// [`RuleSet::Official`], the official loader's organ triangles
    /// ([`crate::loader::item::official_organ_triangles`]). Which fill is drawn decides, where
    /// a fill triangle overlaps the mesh on screen, which pixels are face: the fans and
    /// the official strips cover a non-convex hole outline differently.
    pub fn set_hole_triangles(&mut self, holes: &[[u32; 3]]) -> Result<()> {
        if let Some(t) = holes
            .iter()
            .find(|t| t.iter().any(|&v| v as usize >= self.topology.vertex_count))
        {
            return Err(Error::invalid(
                "hole triangles",
                format!(
                    "{t:?} refers to a vertex beyond the mesh's {}",
                    self.topology.vertex_count
                ),
            ));
        }
        self.triangles.truncate(self.topology.triangles.len());
        self.triangles.extend_from_slice(holes);
        Ok(())
    }

    /// This renderer following `rules` (a new renderer follows [`RuleSet::Exact`]).
    pub fn with_rules(mut self, rules: RuleSet) -> Self {
        self.rules = rules;
        self
    }

    /// Whose rasterization rules the renderer follows ([`FaceRenderer::with_rules`]).
    pub fn rules(&self) -> RuleSet {
        self.rules
    }

    /// The topology.
    pub fn topology(&self) -> &FaceTopology {
        &self.topology
    }

    /// Renders the targets of `verts` at `pose` in an image of `width` x `height`, into
    /// the crop `crop`. `buffer` is reused between calls (it is resized if needed).
    pub fn render(
        &self,
        verts: &[Point3<f32>],
        pose: &Pose,
        width: u32,
        height: u32,
        crop: &CropTransform,
        buffer: &mut VisibilityBuffer,
    ) -> Result<FaceTargets> {
        if self.rules.book().mask() == MaskRule::WarpedFromImage {
            return self.render_official(verts, pose, width, height, crop, buffer);
        }
        self.rasterize(verts, pose, width, height, Some(crop), buffer, true)?;
        let n_mesh = self.topology.triangles.len() as u32;
        let mask = face_mask(&buffer.triangle, n_mesh);
        let (corr_vertices, corr_weights) = self.correspondences(buffer, &mask);
        Ok(FaceTargets {
            crop: *crop,
            mask,
            corr_vertices,
            corr_weights,
        })
    }

    /// [`FaceRenderer::render`]'s mask in [`RuleSet::Exact`], with the
    /// correspondences left to be computed at the pixels a caller needs
    /// ([`CropVisibility::correspondence_at`]): the rasterizer records which triangle
    /// each pixel shows and not its weights
    /// ([`VisibilityBuffer::rasterize_visibility`]), which saves most of a visible
    /// pixel's work when a few of the mask's pixels are used (the loader's sampled
    /// points). The mask, and the correspondences wherever they are asked for, are
    /// [`FaceRenderer::render`]'s, bit for bit (tested). `buffer` is reused between
    /// calls and borrowed by the result. In [`RuleSet::Official`], whose targets go
    /// through the whole image and a warp ([`FaceRenderer::render`]), an error.
    pub(crate) fn render_visibility<'a>(
        &'a self,
        verts: &[Point3<f32>],
        pose: &Pose,
        width: u32,
        height: u32,
        crop: &CropTransform,
        buffer: &'a mut VisibilityBuffer,
    ) -> Result<CropVisibility<'a>> {
        if self.rules.book().mask() != MaskRule::Crop {
            return Err(Error::invalid(
                "raster mode",
                "render_visibility follows the exact rules; the official rules' targets come from render",
            ));
        }
        let screen = self.rasterize(verts, pose, width, height, Some(crop), buffer, false)?;
        let mask = self.face_pixels(buffer);
        Ok(CropVisibility {
            mask,
            screen,
            triangles: &self.triangles,
            buffer,
        })
    }

    /// The official loader's crop ([`crate::crop::official::official_crop`]) of `verts`
    /// at `pose` in a `width x height` image: its box around the landmarks projected in
    /// `f64`, as the official loader projects them.
    pub fn official_crop(
        &self,
        verts: &[Point3<f32>],
        pose: &Pose,
        width: u32,
        height: u32,
        size: u32,
    ) -> Result<CropTransform> {
        let projected = self.landmarks_in_f64(verts, pose, width, height)?;
        crate::crop::official::official_crop(projected, size)
            .ok_or_else(|| Error::invalid("landmarks", "the official crop box is empty"))
    }

    /// The crop of a sample under the renderer's rules: its box around the landmarks,
    /// at side `size`. Under [`MaskRule::Crop`] the landmarks are the samples table's
    /// (`landmarks_2d`, float32); under [`MaskRule::WarpedFromImage`] they are `verts`'
    /// projected at `pose` in `f64`, as the official loader projects them
    /// ([`FaceRenderer::official_crop`]).
    pub(crate) fn crop_of(
        &self,
        verts: &[Point3<f32>],
        pose: &Pose,
        (width, height): (u32, u32),
        landmarks_2d: &[f32],
        size: u32,
    ) -> Result<CropTransform> {
        let empty = || {
            Error::invalid(
                "landmarks",
                format!("the {} crop box is empty", self.rules.name()),
            )
        };
        match self.rules.book().mask() {
            MaskRule::Crop => self
                .rules
                .crop_around_landmarks(landmarks_2d, size)
                .ok_or_else(empty),
            MaskRule::WarpedFromImage => {
                let projected: Vec<(f64, f64)> =
                    self.landmarks_in_f64(verts, pose, width, height)?.collect();
                self.rules
                    .book()
                    .crop_around(&projected, size)
                    .map_err(|_| empty())
            }
        }
    }

    /// Whether [`FaceRenderer::render`] rasterizes the whole image (its buffer then
    /// holds the full-image raster: [`FaceRenderer::face_pixels`]).
    pub(crate) fn renders_whole_image(&self) -> bool {
        self.rules.book().mask() == MaskRule::WarpedFromImage
    }

    /// The topology's landmarks of `verts` at `pose` projected in `f64` to image pixels
    /// of a `width x height` image.
    fn landmarks_in_f64(
        &self,
        verts: &[Point3<f32>],
        pose: &Pose,
        width: u32,
        height: u32,
    ) -> Result<impl Iterator<Item = (f64, f64)>> {
        let camera = Camera::new(self.camera_projection, width, height)?;
        let points: Vec<Point3<f64>> = self
            .topology
            .landmarks
            .iter()
            .map(|&i| {
                verts
                    .get(i as usize)
                    .map(|p| p.cast())
                    .ok_or_else(|| Error::invalid("verts", format!("no landmark vertex {i}")))
            })
            .collect::<Result<_>>()?;
        let projected = camera.project_all(pose, &points);
        Ok(projected.into_iter().map(|p| (p.u, p.v)))
    }

    /// [`FaceRenderer::render`] in [`RuleSet::Official`]: the official loader's
    /// pipeline ([`crate::crop::official_crop`]): rasterize over the whole image with its
    /// rules, warp the mask into the crop as `cv2.warpAffine` does, and take each crop
    /// mask pixel's correspondence from the heaviest face pixel among its bilinear taps.
    fn render_official(
        &self,
        verts: &[Point3<f32>],
        pose: &Pose,
        width: u32,
        height: u32,
        crop: &CropTransform,
        buffer: &mut VisibilityBuffer,
    ) -> Result<FaceTargets> {
        if crop.rules != self.rules {
            return Err(Error::invalid(
                "crop",
                "the official pipeline needs the official crop (corner sampling)",
            ));
        }
        self.rasterize(verts, pose, width, height, None, buffer, true)?;
        let n_mesh = self.topology.triangles.len() as u32;
        let (w, h) = (width as i64, height as i64);
        let face_at = |x: i64, y: i64| -> Option<usize> {
            let inside = (0..w).contains(&x) && (0..h).contains(&y);
            let i = (y * w + x) as usize;
            (inside && buffer.triangle[i] < n_mesh).then_some(i)
        };
        let taps = crate::crop::official::warp_taps(crop);
        let mut mask = vec![false; taps.len()];
        let mut corr_vertices = Vec::new();
        let mut corr_weights = Vec::new();
        for (m, t) in mask.iter_mut().zip(&taps) {
            let (x, y) = (t.x as i64, t.y as i64);
            let corners = [(x, y), (x + 1, y), (x, y + 1), (x + 1, y + 1)];
            let face_weight: u32 = corners
                .iter()
                .zip(t.weights())
                .filter(|&(&(cx, cy), _)| face_at(cx, cy).is_some())
                .map(|(_, wt)| wt)
                .sum();
            // cv2's rounding of the warped 0/1 mask: face from one half up.
            if face_weight < crate::crop::official::HALF_WEIGHT {
                continue;
            }
            let (cx, cy) =
                crate::crop::official::nearest_face_tap(*t, |cx, cy| face_at(cx, cy).is_some())
                    .expect("a tap weighs at least one half");
            let i = face_at(cx, cy).expect("a face pixel");
            let tri = self.triangles[buffer.triangle[i] as usize];
            *m = true;
            corr_vertices.push([tri[0] as u16, tri[1] as u16, tri[2] as u16]);
            corr_weights.push(buffer.bary[i]);
        }
        Ok(FaceTargets {
            crop: *crop,
            mask,
            corr_vertices,
            corr_weights,
        })
    }

    /// Per mask pixel, in row-major order: the visible triangle's vertex ids and the
    /// barycentrics from `buffer`. Blocks of 16 pixels without a face pixel are
    /// skipped (about 60% of a crop is background), the mesh triangle is looked up with
    /// `get` (which is also the mask test), and the outputs are sized up front: growing
    /// them by doubling copied up to 160 KiB per sample. The earlier loop over every
    /// pixel index (bounds checks, values spilled to the stack: 55 instructions per face
    /// pixel) was a fifth of the visibility stage's instructions.
    #[inline(never)]
    fn correspondences(
        &self,
        buffer: &VisibilityBuffer,
        mask: &[bool],
    ) -> (Vec<[u16; 3]>, Vec<[f32; 3]>) {
        const BLOCK: usize = 16;
        let mesh = &self.triangles[..self.topology.triangles.len()];
        // Counted in u8 per block, which vectorises (a `usize` count per pixel did not).
        let block_count = |m: &[bool]| m.iter().map(|&m| m as u8).sum::<u8>();
        let faces: usize = mask.chunks(BLOCK).map(|m| block_count(m) as usize).sum();
        let mut vertices = vec![[0u16; 3]; faces];
        let mut weights = vec![[0f32; 3]; faces];
        let mut k = 0;
        let blocks = mask
            .chunks(BLOCK)
            .zip(buffer.triangle.chunks(BLOCK))
            .zip(buffer.bary.chunks(BLOCK));
        for ((m, triangle), bary) in blocks {
            if block_count(m) == 0 {
                continue;
            }
            for (&t, &b) in triangle.iter().zip(bary) {
                if let Some(v) = mesh.get(t as usize) {
                    vertices[k] = [v[0] as u16, v[1] as u16, v[2] as u16];
                    weights[k] = b;
                    k += 1;
                }
            }
        }
        (vertices, weights)
    }

    /// The face mask of `verts` at `pose` over the whole `width x height` image (row-major),
    /// with the same rules as [`FaceRenderer::render`]'s crop mask (the hole fans hide
    /// but are not face). `buffer` is reused between calls.
    pub fn render_full_mask(
        &self,
        verts: &[Point3<f32>],
        pose: &Pose,
        width: u32,
        height: u32,
        buffer: &mut VisibilityBuffer,
    ) -> Result<Vec<bool>> {
        self.rasterize(verts, pose, width, height, None, buffer, true)?;
        Ok(self.face_pixels(buffer))
    }

    /// [`FaceRenderer::render_full_mask`] held over a window of the image: in
    /// [`RuleSet::Official`] the official rasterizer fills `buffer` only over the
    /// window of every pixel the face's vertices can cover
    /// ([`PixelWindow::official_extent`]), so the cost follows the face's extent, not
    /// the image's; the mask is the whole-image one over the window and no face
    /// outside it. In [`RuleSet::Exact`] the window is the whole image. `buffer`
    /// (reused between calls, keeping its allocation) is left holding the window's
    /// raster, pixel `(x, y)` at `window.index(x, y)`: in official mode its triangles
    /// and depths only, the weights computed where needed by
    /// [`WindowMask::official_weights`] (most of the raster's writes saved).
    pub(crate) fn render_window_mask(
        &self,
        verts: &[Point3<f32>],
        pose: &Pose,
        width: u32,
        height: u32,
        buffer: &mut VisibilityBuffer,
    ) -> Result<WindowMask> {
        if self.rules.book().mask() == MaskRule::Crop {
            let mask = self.render_full_mask(verts, pose, width, height, buffer)?;
            let window = PixelWindow::whole(width, height);
            let screen = Vec::new();
            return Ok(WindowMask {
                window,
                mask,
                screen,
            });
        }
        let screen = self.project(verts, pose, width, height)?;
        check_viewport(width, height, "image size")?;
        let window = PixelWindow::official_extent(&screen, width, height);
        arkit_core::rasterize_official_visibility_in(buffer, window, &screen, &self.triangles)
            .map_err(|e| Error::invalid("mesh", e.to_string()))?;
        let mask = self.face_pixels(buffer);
        Ok(WindowMask {
            window,
            mask,
            screen,
        })
    }

    /// The face mask of a buffer this renderer filled (row-major): pixels whose
    /// visible triangle is a mesh triangle, not a hole fan. After
    /// [`FaceRenderer::render`] in [`RuleSet::Official`] the buffer holds the whole
    /// image, so this is the full-image mask without rendering it again.
    pub fn face_pixels(&self, buffer: &VisibilityBuffer) -> Vec<bool> {
        face_mask(&buffer.triangle, self.topology.triangles.len() as u32)
    }

    /// The mesh's vertices and its hole centroids projected to image pixels with the
    /// release camera for a `width x height` image.
    fn project(
        &self,
        verts: &[Point3<f32>],
        pose: &Pose,
        width: u32,
        height: u32,
    ) -> Result<Vec<ScreenVertex>> {
        if verts.len() != self.topology.vertex_count {
            return Err(Error::invalid(
                "verts",
                format!(
                    "{} vertices, the topology has {}",
                    verts.len(),
                    self.topology.vertex_count
                ),
            ));
        }
        let camera = Camera::new(self.camera_projection, width, height)?;
        let mut all = verts.to_vec();
        all.extend(self.hole_fill.centroid_positions(verts));
        Ok(camera.project_to_screen(pose, &all))
    }

    /// Projects the mesh and its hole fans and rasterizes them into `buffer` (resized to
    /// the crop, or to the whole image when `crop` is `None`) with the renderer's rules:
    /// with the weights, or in [`RuleSet::Exact`] without them (`weights`,
    /// [`VisibilityBuffer::rasterize_visibility`]). Returns the vertices as drawn.
    #[allow(clippy::too_many_arguments)]
    fn rasterize(
        &self,
        verts: &[Point3<f32>],
        pose: &Pose,
        width: u32,
        height: u32,
        crop: Option<&CropTransform>,
        buffer: &mut VisibilityBuffer,
        weights: bool,
    ) -> Result<Vec<ScreenVertex>> {
        let mut screen = self.project(verts, pose, width, height)?;
        let (bw, bh) = match crop {
            Some(crop) => {
                let (sx, sy) = crop.scales();
                let (sx, sy) = (sx as f32, sy as f32);
                let (x0, y0) = (crop.x0 as f32, crop.y0 as f32);
                // A corner-sampled crop's pixel i sits at i, where our rules sample
                // i + 0.5: shift the mesh by half a crop pixel to sample there.
                let o = 0.5 - crop.rules.sample_offset() as f32;
                for p in &mut screen {
                    p.x = (p.x - x0) * sx + o;
                    p.y = (p.y - y0) * sy + o;
                }
                (crop.size, crop.size)
            }
            None => (width, height),
        };
        check_viewport(
            bw,
            bh,
            if crop.is_some() {
                "crop size"
            } else {
                "image size"
            },
        )?;
        if buffer.width != bw || buffer.height != bh {
            *buffer = VisibilityBuffer::new(bw, bh);
        } else {
            buffer.clear();
        }
        self.rules
            .book()
            .rasterize(buffer, &screen, &self.triangles, weights)
            .map_err(|e| Error::invalid("mesh", e))?;
        Ok(screen)
    }
}

/// A `width x height` viewport's sides as an error naming `what` unless each is
/// `1..=MAX_VIEWPORT`: the rasterizer's buffer panics beyond its limit, and a crop size
/// or an image size read from a file must fail instead.
fn check_viewport(width: u32, height: u32, what: &str) -> Result<()> {
    let max = arkit_core::MAX_VIEWPORT;
    if !(1..=max).contains(&width) || !(1..=max).contains(&height) {
        return Err(Error::invalid(
            what,
            format!("{width}x{height}: each side must be 1..={max} pixels"),
        ));
    }
    Ok(())
}

/// A face's visibility in a crop ([`FaceRenderer::render_visibility`]): the mask of
/// [`FaceRenderer::render`]'s targets, and its correspondences at the pixels asked for.
#[derive(Debug)]
pub(crate) struct CropVisibility<'a> {
    /// Face mask, row-major `size * size` ([`FaceTargets::mask`]).
    pub mask: Vec<bool>,
    /// The vertices (and hole centroids) as drawn, in crop pixels.
    screen: Vec<ScreenVertex>,
    /// The renderer's triangles (mesh, then hole fill), as the buffer indexes them.
    triangles: &'a [[u32; 3]],
    /// The raster: triangles and depths, no weights.
    buffer: &'a VisibilityBuffer,
}

impl CropVisibility<'_> {
    /// The correspondence at crop pixel `pixel` (row-major): the visible triangle's
    /// three vertex ids and perspective-correct weights, the row
    /// [`FaceRenderer::render`] gives that pixel in [`FaceTargets::corr_vertices`] and
    /// [`FaceTargets::corr_weights`] (same bits). `None` where the pixel is not face
    /// (or outside the crop).
    #[inline]
    pub(crate) fn correspondence_at(&self, pixel: u32) -> Option<([u16; 3], [f32; 3])> {
        if !*self.mask.get(pixel as usize)? {
            return None;
        }
        let width = self.buffer.width;
        let (x, y) = (pixel % width, pixel / width);
        let f = self
            .buffer
            .fragment_at(&self.screen, self.triangles, x, y)?;
        let t = self.triangles[self.buffer.triangle[pixel as usize] as usize];
        Some((t.map(|v| v as u16), f.bary))
    }
}

/// A face mask over a window of a `width x height` image
/// ([`FaceRenderer::render_window_mask`]): row-major over `window`; every pixel outside
/// the window is not face.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct WindowMask {
    /// The image pixels held.
    pub window: PixelWindow,
    /// Per window pixel, whether it shows the face.
    pub mask: Vec<bool>,
    /// In [`RuleSet::Official`], the vertices (and hole centroids) projected to
    /// image pixels that the mask was drawn from, for [`WindowMask::official_weights`];
    /// empty in [`RuleSet::Exact`].
    pub screen: Vec<ScreenVertex>,
}

impl WindowMask {
    /// In [`RuleSet::Official`], the weights the official rasterizer gives image
    /// pixel `(x, y)` when `triangle` (the renderer's, as the buffer's triangle index
    /// names it) is the one shown there: the buffer's weights are left out of the
    /// window raster, and computed here with the same float32 operations
    /// ([`arkit_core::official_weights`]).
    pub fn official_weights(&self, triangle: [u32; 3], x: i64, y: i64) -> [f32; 3] {
        arkit_core::official_weights(&self.screen, triangle, x, y)
    }

    /// Whether image pixel `(x, y)` shows the face (never outside the window, nor
    /// outside the image).
    #[cfg(test)]
    #[inline]
    pub(crate) fn is_face(&self, x: i64, y: i64) -> bool {
        self.window.index(x, y).is_some_and(|i| self.mask[i])
    }

    /// The mask over the whole `width x height` image (row-major), as
    /// [`FaceRenderer::render_full_mask`] returns it.
    #[cfg(test)]
    pub(crate) fn to_full(&self, width: u32, height: u32) -> Vec<bool> {
        let w = width as i64;
        (0..width as usize * height as usize)
            .map(|i| self.is_face(i as i64 % w, i as i64 / w))
            .collect()
    }

    /// The face pixels of the image rectangle `rows x cols` (image pixels, within the
    /// image), as row-major offsets in the rectangle: numpy's
    /// `np.nonzero(mask[rows, cols].ravel())`. Only the rectangle's part inside the
    /// window is visited.
    pub(crate) fn face_offsets(&self, rows: Range<i64>, cols: Range<i64>) -> Vec<i64> {
        let w = &self.window;
        let clip = |r: &Range<i64>, start: u32, len: u32| {
            r.start.max(start as i64)..r.end.min(start as i64 + len as i64)
        };
        let (inner_rows, inner_cols) = (clip(&rows, w.y0, w.height), clip(&cols, w.x0, w.width));
        let width = cols.end - cols.start;
        let mut offsets = Vec::new();
        if inner_cols.is_empty() {
            return offsets;
        }
        let (from, to) = (
            (inner_cols.start - w.x0 as i64) as usize,
            (inner_cols.end - w.x0 as i64) as usize,
        );
        for y in inner_rows {
            let at = (y - w.y0 as i64) as usize * w.width as usize;
            let first = (y - rows.start) * width + (inner_cols.start - cols.start);
            push_face_offsets(&self.mask[at + from..at + to], first, &mut offsets);
        }
        offsets
    }
}

/// Appends to `out` the offsets `first + k` of the face pixels `row[k]`, sixteen pixels
/// at a time ([`for_each_set_run`]).
fn push_face_offsets(row: &[bool], first: i64, out: &mut Vec<i64>) {
    for_each_set_run(row, |start, len| {
        out.extend(first + start as i64..first + (start + len) as i64)
    });
}

/// Which pixels of a visibility buffer's `triangle` array show one of the first
/// `n_mesh` triangles (the mesh, not the hole fans, and not empty).
fn face_mask(triangle: &[u32], n_mesh: u32) -> Vec<bool> {
    triangle.iter().map(|&t| t < n_mesh).collect()
}

/// How far the official loader's rasterizer (corner sampling, screen-space weights,
/// [`arkit_core::rasterize_mesh_official`]) and ours (centre sampling, perspective-
/// correct weights) differ on one face in a full `width x height` image.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct ModeDifference {
    /// Face pixels in our mask.
    pub face_pixels: usize,
    /// Pixels that are face in one mode and not the other.
    pub mask_pixels_changed: usize,
    /// Face pixels in both whose visible triangle differs.
    pub triangle_changed: usize,
    /// Largest weight difference where both see the same triangle.
    pub max_weight_difference: f32,
}

impl FaceRenderer {
    /// Renders `verts` at `pose` in the full image both ways and compares. With
    /// `aligned`, the official sampling is moved onto our pixel centres (vertices shifted
    /// by half a pixel), which isolates the interpolation and edge rules from the
    /// half-pixel offset between the two sampling conventions.
    pub fn compare_with_official(
        &self,
        verts: &[Point3<f32>],
        pose: &Pose,
        width: u32,
        height: u32,
        aligned: bool,
    ) -> Result<ModeDifference> {
        let screen = self.project(verts, pose, width, height)?;
        let mut ours = VisibilityBuffer::new(width, height);
        ours.rasterize_mesh(&screen, &self.triangles)
            .map_err(|e| Error::invalid("mesh", e.to_string()))?;
        let shift = if aligned { 0.5 } else { 0.0 };
        let shifted: Vec<ScreenVertex> = screen
            .iter()
            .map(|p| ScreenVertex {
                x: p.x - shift,
                y: p.y - shift,
                inv_w: p.inv_w,
            })
            .collect();
        let mut theirs = VisibilityBuffer::new(width, height);
        arkit_core::rasterize_mesh_official(&mut theirs, &shifted, &self.triangles)
            .map_err(|e| Error::invalid("mesh", e.to_string()))?;
        let n_mesh = self.topology.triangles.len() as u32;
        let mut d = ModeDifference {
            face_pixels: 0,
            mask_pixels_changed: 0,
            triangle_changed: 0,
            max_weight_difference: 0.0,
        };
        for i in 0..ours.triangle.len() {
            let (a, b) = (ours.triangle[i], theirs.triangle[i]);
            let (fa, fb) = (a < n_mesh, b < n_mesh);
            d.face_pixels += fa as usize;
            if fa != fb {
                d.mask_pixels_changed += 1;
            } else if fa && a != b {
                d.triangle_changed += 1;
            } else if fa {
                let w = (0..3)
                    .map(|k| (ours.bary[i][k] - theirs.bary[i][k]).abs())
                    .fold(0.0, f32::max);
                d.max_weight_difference = d.max_weight_difference.max(w);
            }
        }
        Ok(d)
    }
}

/// `M` of `n` mask pixels (indices into the mask pixel list), drawn from `seed`: a
/// random subset without repetition when `n >= M`, else all `n` repeated cyclically
/// (numpy's `np.pad(choose, (0, M - n), 'wrap')`, as the official loader does).
pub fn sample_points(n: usize, m: usize, seed: u64) -> Vec<u32> {
    if n == 0 {
        return Vec::new();
    }
    if n <= m {
        return (0..m).map(|k| (k % n) as u32).collect();
    }
    // Partial Fisher-Yates, then in increasing order so the rows keep the pixel order:
    // the drawn indices are distinct, so marking them in a bitmap of the `n` and
    // reading its set bits in order sorts them (in a pass over `n / 64` words rather
    // than a comparison sort of the `m`).
    let mut idx: Vec<u32> = (0..n as u32).collect();
    let mut rng = Rng::new(seed);
    for k in 0..m {
        let j = k + rng.below((n - k) as u64) as usize;
        idx.swap(k, j);
    }
    let mut drawn = vec![0u64; n.div_ceil(64)];
    for &i in &idx[..m] {
        drawn[i as usize / 64] |= 1 << (i % 64);
    }
    let mut chosen = Vec::with_capacity(m);
    for (w, &word) in drawn.iter().enumerate() {
        let mut bits = word;
        while bits != 0 {
            chosen.push((64 * w) as u32 + bits.trailing_zeros());
            bits &= bits - 1;
        }
    }
    chosen
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lanes::texels::clamp_planes_from;
    use crate::render::uv_map::{UvMapper, UvTexels};

    #[test]
    fn face_offsets_of_a_row_sixteen_at_a_time_are_the_pixel_by_pixel_ones() {
        let mut r = Rng::new(21);
        for case in 0..400 {
            let len = r.below(90) as usize;
            // Runs of face and background of random lengths, as a face's rows have.
            let mut row = Vec::with_capacity(len);
            let mut face = r.below(2) == 0;
            while row.len() < len {
                let run = 1 + r.below(if case % 2 == 0 { 40 } else { 4 }) as usize;
                row.extend(std::iter::repeat_n(face, run.min(len - row.len())));
                face = !face;
            }
            let first = r.below(1000) as i64 - 500;
            let want: Vec<i64> = (0..len)
                .filter(|&k| row[k])
                .map(|k| first + k as i64)
                .collect();
            let mut got = vec![-7];
            push_face_offsets(&row, first, &mut got);
            assert_eq!(got[0], -7, "appends");
            assert_eq!(got[1..], want[..], "case {case}: {row:?}");
        }
    }
    use arkit_core::conventions::EulerAngles;
    use nalgebra::Vector3;

    fn face() -> (FaceRenderer, Vec<Point3<f32>>) {
        let topo = crate::mesh::synthetic_face::builtin().topology.clone();
        let verts = topo.template.clone().unwrap();
        (
            FaceRenderer::new(topo, Camera::release_projection()).unwrap(),
            verts,
        )
    }

    fn landmarks(r: &FaceRenderer, verts: &[Point3<f32>], pose: &Pose, w: u32, h: u32) -> Vec<f32> {
        let cam = Camera::release(w, h);
        r.topology()
            .landmarks
            .iter()
            .flat_map(|&i| {
                let p = cam.project(pose, &verts[i as usize].cast());
                [p.u as f32, p.v as f32]
            })
            .collect()
    }

    #[test]
    fn every_correspondence_lands_in_its_pixel() {
        let (r, verts) = face();
        let mut vb = VisibilityBuffer::new(1, 1);
        for (yaw, pitch, roll) in [(0.0, 0.0, 0.0), (35.0, -10.0, 20.0), (-70.0, 15.0, -40.0)] {
            let pose = Pose::from_euler(
                EulerAngles::new(yaw, pitch, roll),
                Vector3::new(0.02, -0.01, -0.5),
            );
            let crop =
                CropTransform::around_landmarks(&landmarks(&r, &verts, &pose, 800, 800), 192);
            let t = r.render(&verts, &pose, 800, 800, &crop, &mut vb).unwrap();
            let cam = Camera::release(800, 800);
            let pixels = t.mask_pixels();
            assert!(pixels.len() > 3000, "{}", pixels.len());
            for (k, p) in t.coordinate_map(&verts).iter().enumerate() {
                let q = cam.project(&pose, &p.cast());
                let (cu, cv) = crop.to_crop(q.u, q.v);
                let (i, j) = (pixels[k] % 192, pixels[k] / 192);
                assert!(
                    (cu - (i as f64 + 0.5)).abs() < 2e-3 && (cv - (j as f64 + 0.5)).abs() < 2e-3,
                    "pixel ({i}, {j}) -> ({cu}, {cv})"
                );
                let w = t.corr_weights[k];
                assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn visibility_gives_renders_mask_and_correspondences_bit_for_bit() {
        // Two paths: `render`'s targets (the raster's weights at every pixel), and the
        // visibility raster with each correspondence computed at its pixel alone. Poses
        // from frontal to a profile where the hole fans hide part of the cheek, crops of
        // two sizes: the same mask, and at every mask pixel the same vertex ids and
        // weight bits; nothing off the mask or the crop.
        let (r, verts) = face();
        let (mut full, mut visible) = (VisibilityBuffer::new(1, 1), VisibilityBuffer::new(1, 1));
        let mut compared = 0;
        for (yaw, pitch, roll, size) in [
            (0.0, 0.0, 0.0, 192),
            (35.0, -10.0, 20.0, 128),
            (-70.0, 15.0, -40.0, 192),
            (85.0, 5.0, 0.0, 96),
        ] {
            let pose = Pose::from_euler(
                EulerAngles::new(yaw, pitch, roll),
                Vector3::new(0.02, -0.01, -0.5),
            );
            let crop =
                CropTransform::around_landmarks(&landmarks(&r, &verts, &pose, 800, 800), size);
            let t = r.render(&verts, &pose, 800, 800, &crop, &mut full).unwrap();
            let v = r
                .render_visibility(&verts, &pose, 800, 800, &crop, &mut visible)
                .unwrap();
            assert_eq!(v.mask, t.mask, "yaw {yaw}");
            for (k, &pixel) in t.mask_pixels().iter().enumerate() {
                let (ids, weights) = v.correspondence_at(pixel).expect("a mask pixel");
                assert_eq!(ids, t.corr_vertices[k], "yaw {yaw} pixel {pixel}");
                assert_eq!(
                    weights.map(f32::to_bits),
                    t.corr_weights[k].map(f32::to_bits)
                );
                compared += 1;
            }
            let off = t.mask.iter().position(|&m| !m).unwrap() as u32;
            assert_eq!(v.correspondence_at(off), None);
            assert_eq!(v.correspondence_at(size * size), None);
        }
        assert!(compared > 20_000, "{compared}");
        // The official rules' targets come only from `render`.
        let mut official = r.clone();
        official.rules = RuleSet::Official;
        let pose = Pose::from_euler(
            EulerAngles::new(0.0, 0.0, 0.0),
            Vector3::new(0.0, 0.0, -0.5),
        );
        let crop = CropTransform::around_landmarks(&landmarks(&r, &verts, &pose, 800, 800), 64);
        assert!(
            official
                .render_visibility(&verts, &pose, 800, 800, &crop, &mut visible)
                .is_err()
        );
    }

    #[test]
    fn a_roll_about_the_camera_axis_rotates_the_mask() {
        let (r, verts) = face();
        let mut vb = VisibilityBuffer::new(1, 1);
        let base = Pose::from_euler(
            EulerAngles::new(25.0, 10.0, 0.0),
            Vector3::new(0.0, 0.0, -0.5),
        );
        // Roll the whole camera-space scene by 90 degrees about the optical axis.
        let rz =
            nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2);
        let rolled = Pose::new(rz * base.rotation(), rz * base.translation_m());
        // One crop centred on the principal point for both.
        let crop = CropTransform {
            x0: 400.0 - 150.0,
            y0: 400.0 - 150.0,
            side: 300.0,
            side_y: 300.0,
            size: 128,
            rules: RuleSet::Exact,
        };
        let a = r
            .render(&verts, &base, 800, 800, &crop, &mut vb)
            .unwrap()
            .mask;
        let b = r
            .render(&verts, &rolled, 800, 800, &crop, &mut vb)
            .unwrap()
            .mask;
        let n = 128usize;
        // +90 degrees about +z (y up) is a quarter turn counter-clockwise on screen:
        // image pixel (i, j) goes to (j, n - 1 - i).
        let mut differ = 0;
        for j in 0..n {
            for i in 0..n {
                if a[j * n + i] != b[(n - 1 - i) * n + j] {
                    differ += 1;
                }
            }
        }
        let area = a.iter().filter(|&&m| m).count();
        assert!(area > 2000);
        // Only pixel centres exactly on an edge can differ (the fill rule is not
        // rotation-invariant there).
        assert!(differ * 200 < area, "{differ} of {area}");
    }

    #[test]
    fn uv_position_map_equals_the_scalar_sum() {
        // The SSE2 texel loop (on x86-64) against one coordinate at a time, bit for
        // bit, NaN where uncovered, on a non-square-friendly size and a bent face.
        let (r, verts) = face();
        let uv = UvMapper::derive(r.topology()).unwrap();
        let bent: Vec<Point3<f32>> = verts
            .iter()
            .map(|p| Point3::new(p.x * 1.1, p.y - 0.3 * p.x * p.x, p.z + 0.01))
            .collect();
        let ext = uv.extended_positions(&bent);
        for size in [17, 64, 193] {
            let t = uv.texels(size);
            let (fast, slow) = (t.position_map(&ext), t.position_map_scalar(&ext));
            assert_eq!(fast.len(), (size * size) as usize);
            let bits =
                |m: &[[f32; 3]]| -> Vec<u32> { m.iter().flatten().map(|v| v.to_bits()).collect() };
            assert_eq!(bits(&fast), bits(&slow), "size {size}");
            // Each level the CPU has on its own, whichever `position_map` took.
            for level in crate::lanes::available() {
                let mut lanes = vec![[f32::NAN; 3]; slow.len()];
                t.fill_covered_at(level, &ext, &mut lanes);
                assert_eq!(bits(&lanes), bits(&slow), "{level}, size {size}");
            }
            let covered = fast.iter().filter(|p| !p[0].is_nan()).count();
            assert_eq!(covered, t.covered());
            assert!(covered > (size * size) as usize / 3, "{covered}");
            // And against the layout's buffer, texel by texel, without the texel
            // table's grouping by triangle.
            let vb = uv.rasterize_layout(size);
            for (i, &tri) in vb.triangle.iter().enumerate() {
                let want = match uv.triangles.get(tri as usize) {
                    None => [f32::NAN; 3],
                    Some(v) => {
                        let b = vb.bary[i];
                        let p = ext[v[0] as usize].coords * b[0]
                            + ext[v[1] as usize].coords * b[1]
                            + ext[v[2] as usize].coords * b[2];
                        [p.x, p.y, p.z]
                    }
                };
                assert_eq!(
                    bits(&fast[i..i + 1]),
                    bits(&[want]),
                    "size {size} texel {i}"
                );
            }
        }
    }

    #[test]
    fn clamped_uv_planes_are_the_position_map_mapped() {
        // The planes (AVX lanes where the CPU has them, and the scalar path) against
        // mapping the position map texel by texel, bit for bit: positions scaled past the clamp on
        // both sides, -0.0, and NaN in x (the whole texel -1) or in y alone (NaN kept).
        let (r, verts) = face();
        let uv = UvMapper::derive(r.topology()).unwrap();
        let mut rng = Rng::new(11);
        let mut ext = uv.extended_positions(&verts);
        for p in ext.iter_mut().step_by(7) {
            *p = Point3::new(
                rng.uniform(-0.3, 0.3) as f32,
                rng.uniform(-0.3, 0.3) as f32,
                -0.0,
            );
        }
        ext[3].x = f32::NAN;
        ext[10].y = f32::NAN;
        for (size, scale) in [(64, 9.0), (17, 9.0), (96, 30.0)] {
            let t = uv.texels(size);
            let n = (size * size) as usize;
            let want: Vec<f32> = (0..3)
                .flat_map(|k| {
                    t.position_map_scalar(&ext).into_iter().map(move |p| {
                        if p[0].is_nan() {
                            -1.0
                        } else {
                            (p[k] * scale).clamp(-1.0, 1.0)
                        }
                    })
                })
                .collect();
            let bits = |m: &[f32]| -> Vec<u32> { m.iter().map(|v| v.to_bits()).collect() };
            let mut fast = vec![7.0; 3 * n];
            t.clamped_planes_into(&ext, scale, &mut fast);
            assert_eq!(bits(&fast), bits(&want), "size {size}");
            let mut slow = vec![7.0; 3 * n];
            let (u, rest) = slow.split_at_mut(n);
            let (v, w) = rest.split_at_mut(n);
            clamp_planes_from(&t.position_map_scalar(&ext), 0, scale, [u, v, w]);
            assert_eq!(bits(&slow), bits(&want), "scalar, size {size}");
            // Twice on one thread, its kept map reused (after a larger map, for 17).
            let mut again = vec![7.0; 3 * n];
            t.clamped_planes_into(&ext, scale, &mut again);
            assert_eq!(bits(&again), bits(&want), "again, size {size}");
            // The cases are there: clamped values, NaN texels, -1 from NaN x.
            assert!(want.contains(&1.0) && want.contains(&-1.0));
            assert!(want.iter().any(|v| v.is_nan()), "size {size}");
            assert!(want.iter().any(|&v| v != 0.0 && v.abs() < 1.0));
        }
        // Each level on its own, whichever `clamped_planes_into` took, the AVX-512 one
        // (streaming stores) into planes at every 4-byte offset of a 64-byte line, on
        // maps of every length up to 40 texels and a whole one: the definition's
        // bits, and nothing outside the planes written.
        {
            use crate::lanes::texels::clamp_planes_at;
            let t = uv.texels(64);
            let whole = t.position_map_scalar(&ext);
            let bits = |m: &[f32]| -> Vec<u32> { m.iter().map(|v| v.to_bits()).collect() };
            for n in (0..=40).chain([whole.len()]) {
                // A window of the map with covered and uncovered texels.
                let at = (whole.len() / 2 - n / 2).min(whole.len() - n);
                let map = &whole[at..at + n];
                let mut want = [0, 1, 2].map(|_| vec![7.0f32; n]);
                let [u, v, w] = &mut want;
                clamp_planes_from(map, 0, 9.0, [u, v, w]);
                for level in crate::lanes::available() {
                    for off in 0..16 {
                        let mut got = [0, 1, 2].map(|_| vec![7.0f32; n + 32]);
                        let [u, v, w] = &mut got;
                        let [u, v, w] = [u, v, w].map(|p| &mut p[off..off + n]);
                        clamp_planes_at(level, map, 9.0, [u, v, w]);
                        for (g, want) in got.iter().zip(&want) {
                            assert_eq!(
                                bits(&g[off..off + n]),
                                bits(want),
                                "{level}, {n} at +{off}"
                            );
                            assert!(g[..off].iter().chain(&g[off + n..]).all(|&v| v == 7.0));
                        }
                    }
                }
            }
        }
        // Two tables of one size covering different texels, taken in turn on one
        // thread: each gives its own map (a kept map drawn for the other table would
        // leave stale values where only the other covers), and a clone is its table.
        let mut shrunk = uv.clone();
        for c in &mut shrunk.uv {
            *c = c.map(|v| 0.5 + 0.7 * (v - 0.5));
        }
        let (a, b) = (uv.texels(48), shrunk.texels(48));
        let planes = |t: &UvTexels| {
            let mut out = vec![7.0; 3 * 48 * 48];
            t.clamped_planes_into(&ext, 9.0, &mut out);
            out.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        };
        let expected = |t: &UvTexels| {
            let map = t.position_map_scalar(&ext);
            let mut out = vec![7.0; 3 * 48 * 48];
            let (u, rest) = out.split_at_mut(48 * 48);
            let (v, w) = rest.split_at_mut(48 * 48);
            clamp_planes_from(&map, 0, 9.0, [u, v, w]);
            out.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        };
        assert_ne!(expected(&a), expected(&b));
        for t in [&a, &b, &a, &a.clone(), &b] {
            assert_eq!(planes(t), expected(t));
        }
    }

    #[test]
    fn uv_map_gives_back_the_vertices() {
        let topo = crate::mesh::synthetic_face::builtin().topology.clone();
        let verts = topo.template.clone().unwrap();
        let uv = UvMapper::derive(&topo).unwrap();
        let size = 256;
        let map = uv.position_map(&verts, size);
        let mut worst = 0.0f32;
        for (v, t) in verts.iter().zip(&topo.uv) {
            let s = UvMapper::sample(&map, size, *t);
            assert!(
                s.iter().all(|c| c.is_finite()),
                "vertex UV {t:?} not covered"
            );
            worst = worst.max((Point3::new(s[0], s[1], s[2]) - v).norm());
        }
        // A texel spans about 0.7 mm of face here; bilinear reads are within a texel.
        assert!(worst < 1.5e-3, "{worst}");
    }

    #[test]
    fn official_mode_differs_only_along_edges_and_by_half_a_pixel() {
        let (r, verts) = face();
        let pose = Pose::from_euler(
            EulerAngles::new(30.0, -10.0, 5.0),
            Vector3::new(0.0, 0.0, -0.5),
        );
        // As the two conventions sample: half a pixel apart, so the masks differ on a
        // band along the silhouette and openings, and small triangles change.
        let d = r
            .compare_with_official(&verts, &pose, 800, 800, false)
            .unwrap();
        assert!(d.face_pixels > 20_000);
        assert!(
            d.mask_pixels_changed > 0 && d.mask_pixels_changed * 20 < d.face_pixels,
            "{d:?}"
        );
        // At the same sample points, only pixel centres exactly on edges and the
        // perspective correction differ: an independent check of our rasterizer.
        let a = r
            .compare_with_official(&verts, &pose, 800, 800, true)
            .unwrap();
        assert!(a.mask_pixels_changed * 200 < a.face_pixels, "{a:?}");
        assert!(a.triangle_changed * 100 < a.face_pixels, "{a:?}");
        assert!(a.max_weight_difference < 0.02, "{a:?}");
    }

    #[test]
    fn official_mode_follows_the_official_crop_pipeline() {
        let (mut r, verts) = face();
        let pose = Pose::from_euler(
            EulerAngles::new(10.0, 5.0, 0.0),
            Vector3::new(0.0, 0.0, -0.5),
        );
        let lm = landmarks(&r, &verts, &pose, 800, 800);
        let ours = CropTransform::around_landmarks(&lm, 192);
        let crop = r.official_crop(&verts, &pose, 800, 800, 192).unwrap();
        let from_f32 = lm.chunks(2).map(|p| (p[0] as f64, p[1] as f64));
        assert_eq!(
            Some(crop),
            crate::crop::official::official_crop(from_f32, 192),
            "float32 landmarks give the same box here"
        );
        let mut vb = VisibilityBuffer::new(192, 192);
        let exact = r.render(&verts, &pose, 800, 800, &ours, &mut vb).unwrap();
        r.rules = RuleSet::Official;
        // The official pipeline needs the official (corner-sampled) crop.
        assert!(r.render(&verts, &pose, 800, 800, &ours, &mut vb).is_err());
        let official = r.render(&verts, &pose, 800, 800, &crop, &mut vb).unwrap();
        let kept = r.face_pixels(&vb);
        // Two paths to the crop mask: the render's fused loop, and the full-resolution
        // official mask through the cv2.warpAffine reproduction.
        let full = r
            .render_full_mask(&verts, &pose, 800, 800, &mut vb)
            .unwrap();
        assert_eq!(
            official.mask,
            crate::crop::official::warp_mask(&full, 800, 800, &crop)
        );
        // The official render leaves the full-image raster in the buffer.
        assert_eq!(kept, full);
        // Each correspondence, pushed through the camera, lands within a pixel of the
        // image point its crop pixel samples (the heaviest face tap is at most one
        // pixel away; the screen-space weights add a few hundredths).
        let cam = Camera::release(800, 800);
        let pixels = official.mask_pixels();
        let coords = official.coordinate_map(&verts);
        for (k, p) in coords.iter().enumerate() {
            let q = cam.project(&pose, &p.cast());
            let (u, v) = crop.pixel_to_image(pixels[k] % 192, pixels[k] / 192);
            assert!(
                (q.u - u).abs() < 1.1 && (q.v - v).abs() < 1.1,
                "pixel {} samples ({u}, {v}), its correspondence is at ({}, {})",
                pixels[k],
                q.u,
                q.v
            );
        }
        // The two modes see the same face: mask areas in image pixels agree.
        let area = |t: &FaceTargets| {
            let (sx, sy) = t.crop.scales();
            t.mask.iter().filter(|&&m| m).count() as f64 / (sx * sy)
        };
        let (a, b) = (area(&exact), area(&official));
        assert!((a - b).abs() < 0.03 * a, "{a} vs {b}");
    }

    #[test]
    fn the_windowed_full_mask_is_the_whole_images() {
        // Two paths: the official raster of the whole image, and of the window the
        // vertices can cover. A face cut by the image's left and top edges, and one in
        // the middle: the same mask, and the same triangle and weights on every pixel.
        let (mut r, verts) = face();
        r.rules = RuleSet::Official;
        let at = |x: f64, y: f64| {
            Pose::from_euler(EulerAngles::new(20.0, -5.0, 10.0), Vector3::new(x, y, -0.5))
        };
        let (w, h) = (800u32, 640u32);
        let (mut whole, mut part) = (VisibilityBuffer::new(1, 1), VisibilityBuffer::new(1, 1));
        for (name, pose) in [("edge", at(-0.27, 0.25)), ("middle", at(0.0, 0.0))] {
            let full = r.render_full_mask(&verts, &pose, w, h, &mut whole).unwrap();
            let face = r
                .render_window_mask(&verts, &pose, w, h, &mut part)
                .unwrap();
            assert_eq!(face.to_full(w, h), full, "{name}");
            let win = face.window;
            assert_eq!((part.width, part.height), (win.width, win.height));
            for (i, &t) in whole.triangle.iter().enumerate() {
                let (x, y) = ((i % w as usize) as i64, (i / w as usize) as i64);
                let Some(j) = win.index(x, y) else {
                    assert_eq!(t, VisibilityBuffer::EMPTY, "{name} ({x}, {y})");
                    continue;
                };
                assert_eq!(part.triangle[j], t, "{name} ({x}, {y})");
                if t != VisibilityBuffer::EMPTY {
                    let tri = r.triangles[t as usize];
                    let weights = face.official_weights(tri, x, y).map(f32::to_bits);
                    assert_eq!(
                        weights,
                        whole.bary[i].map(f32::to_bits),
                        "{name} ({x}, {y})"
                    );
                }
            }
            let face_on = |x: u32, y: u32| full[(y * w + x) as usize];
            let touches_edges = (0..h).any(|y| face_on(0, y)) && (0..w).any(|x| face_on(x, 0));
            match name {
                "edge" => assert!(touches_edges && (win.x0, win.y0) == (0, 0), "{win:?}"),
                _ => assert!(!touches_edges && win.x0 > 0 && win.len() * 4 < full.len()),
            }
            // A slice starting inside the window and ending past it: numpy's nonzero of
            // mask[rows, cols].
            // Then one starting before the window (where the window leaves room).
            for (dx, dy) in [(17i64, 23i64), (-5, -7)] {
                let (x0, y0) = ((win.x0 as i64 + dx).max(0), (win.y0 as i64 + dy).max(0));
                let (rows, cols) = (y0..(y0 + 300).min(h as i64), x0..(x0 + 400).min(w as i64));
                let want: Vec<i64> = rows
                    .clone()
                    .flat_map(|y| cols.clone().map(move |x| (y, x)))
                    .enumerate()
                    .filter(|&(_, (y, x))| face_on(x as u32, y as u32))
                    .map(|(k, _)| k as i64)
                    .collect();
                assert!(!want.is_empty());
                assert_eq!(face.face_offsets(rows, cols), want, "{name} {dx} {dy}");
            }
        }
        // In exact mode the window is the whole image.
        r.rules = RuleSet::Exact;
        let pose = at(0.0, 0.0);
        let face = r
            .render_window_mask(&verts, &pose, w, h, &mut part)
            .unwrap();
        assert_eq!(face.window, PixelWindow::whole(w, h));
        let full = r.render_full_mask(&verts, &pose, w, h, &mut whole).unwrap();
        assert_eq!(face.mask, full);
    }

    #[test]
    fn crop_rules_cut_our_box_or_the_official_one() {
        let lm = [10.0f32, -5.0, 30.0, 5.0];
        let ours = RuleSet::Exact.crop_around_landmarks(&lm, 192).unwrap();
        assert_eq!(ours, CropTransform::around_landmarks(&lm, 192));
        let official = RuleSet::Official.crop_around_landmarks(&lm, 192).unwrap();
        assert_eq!(official.rules, RuleSet::Official);
        // int(20 - 15) = 5 and int(0 - 15) = -15; ours starts at 20 - 15 = 5 and -15
        // too, but its box is 30 wide where the official one maps 30 pixels onto 191.
        assert_eq!((official.x0, official.y0), (5.0, -15.0));
        assert_eq!((ours.x0, ours.side), (5.0, 30.0));
        assert!((official.side - 30.0 * 192.0 / 191.0).abs() < 1e-12);
        assert!(
            RuleSet::Official
                .crop_around_landmarks(&[3.0, 3.0, 3.0, 3.0], 192)
                .is_none()
        );
    }

    #[test]
    fn points_are_sampled_as_the_official_training_does() {
        assert_eq!(sample_points(3, 7, 1), vec![0, 1, 2, 0, 1, 2, 0]);
        let p = sample_points(5000, 1024, 9);
        assert_eq!(p.len(), 1024);
        assert!(p.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(p, sample_points(5000, 1024, 9));
        assert_ne!(p, sample_points(5000, 1024, 10));
        assert!(sample_points(0, 10, 0).is_empty());
        // The same draws as the partial Fisher-Yates then a sort (the definition), at
        // sizes around the bitmap's 64-bit words and the point count.
        for (n, m) in [
            (1025usize, 1024usize),
            (1024 + 63, 1024),
            (1024 + 64, 1024),
            (20_000, 1024),
            (70, 64),
            (65, 1),
        ] {
            for seed in 0..5 {
                let mut idx: Vec<u32> = (0..n as u32).collect();
                let mut rng = Rng::new(seed);
                for k in 0..m {
                    let j = k + rng.below((n - k) as u64) as usize;
                    idx.swap(k, j);
                }
                let mut want = idx[..m].to_vec();
                want.sort_unstable();
                assert_eq!(sample_points(n, m, seed), want, "{m} of {n}, seed {seed}");
            }
        }
    }
}
