//! `exact_item`: [`FaceLoader`]'s item by our rules (the mask rule
//! `MaskRule::Crop`, ours and any rule set that rasterizes at the crop's resolution):
//! the rule set's box (jittered in training), the mask at the crop's resolution and
//! the correspondences at the sampled points only, our UV map. Tested with the loader
//! (`tests/loader.rs`: every field against the library's render path).

use super::*;

impl FaceLoader {
    #[allow(clippy::too_many_arguments)]
    pub(super) fn exact(
        &self,
        row: &IndexRow,
        verts: &[Point3<f32>],
        pose: &Pose,
        source: &PixelSource,
        landmarks: &[(f64, f64)],
        train: bool,
        rng: &mut Rng,
        mut planes: Planes<'_>,
    ) -> Result<LoaderItem> {
        let s = self.options.img_size;
        let mut crop = self.eval_crop(row, landmarks)?;
        if train {
            // The landmarks' box size is 2/3 of the crop's side (half-side 0.75 size).
            let size = crop.side / 1.5;
            let (dx, dy, scale) = Self::draw_jitter(rng, size);
            let (cx, cy) = (
                crop.x0 + crop.side / 2.0 + dx,
                crop.y0 + crop.side / 2.0 + dy,
            );
            let side = crop.side * scale;
            crop = CropTransform {
                x0: cx - side / 2.0,
                y0: cy - side / 2.0,
                side,
                side_y: side,
                size: s,
                rules: crop.rules,
            };
        }
        let mut buffer = self.take_buffer();
        // The mask, then the correspondences at the sampled points only (the raster
        // leaves the weights out): `render`'s targets there, bit for bit.
        let t = self.renderer.render_visibility(
            verts,
            pose,
            row.sample.image_width,
            row.sample.image_height,
            &crop,
            &mut buffer,
        )?;
        let pixels = mask_pixel_indices(&t.mask);
        if pixels.is_empty() {
            return Err(Error::invalid(
                "crop",
                format!("no face pixel in the crop of {}", row.sample.key),
            ));
        }
        let chosen = sample_points(pixels.len(), self.options.n_pts, rng.next_u64());
        // A plain loop: collected through `Result`, the iterator's adapters were calls
        // of their own per point.
        let mut correspondences = Vec::with_capacity(chosen.len());
        for &c in &chosen {
            let Some(found) = t.correspondence_at(pixels[c as usize]) else {
                return Err(Error::invalid(
                    "crop",
                    format!("a mask pixel of {} has no triangle", row.sample.key),
                ));
            };
            correspondences.push(found);
        }
        let mut rgb = source.crop(&crop, train, &row.sample.key)?;
        if train {
            jitter_colour(&mut rgb, rng);
        }
        let extended = self.uv.extended_positions(verts);
        let n = (s * s) as usize;
        // Positions times 9 clamped to [-1, 1], uncovered texels -1.
        let uvmap = planes.uvmap(3 * n, |uvmap| {
            self.uv_texels.clamped_planes_into(&extended, 9.0, uvmap)
        });
        Ok(LoaderItem {
            key: row.sample.key.clone(),
            image_path: self.image_path(row),
            img: planes.img(&rgb),
            choose: chosen.iter().map(|&c| pixels[c as usize] as i64).collect(),
            model: Vec::new(),
            uvmap,
            nocs: correspondences
                .iter()
                .flat_map(|&(v, w)| {
                    let p = canonical_position(verts, v, w);
                    [p.x * 4.5, p.y * 4.5, p.z * 4.5]
                })
                .collect(),
            mask: t.mask.iter().map(|&m| m as u8).collect(),
            corr_vertices: correspondences
                .iter()
                .map(|(v, _)| v.map(|v| v as u32))
                .collect(),
            corr_weights: correspondences.iter().map(|&(_, w)| w).collect(),
            tform_inv: tform_inv(&crop),
            rt: row.sample.rt,
            crop,
            official_box: None,
            choose_box: Vec::new(),
            box_clipped: false,
        })
    }
}
