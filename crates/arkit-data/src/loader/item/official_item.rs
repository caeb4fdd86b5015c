//! `official_item`: [`FaceLoader`]'s item by the official loader's rules (the
//! official rule set's mask rule, `MaskRule::WarpedFromImage`): the face rasterized
//! over the window of the image it can cover, then `ARKitDataset.get_item`'s steps in
//! its order. Tested with the loader (`tests/loader.rs`, and the Python package's
//! numpy re-implementation of the official formulas).

use super::*;

impl FaceLoader {
    #[allow(clippy::too_many_arguments)]
    pub(super) fn official(
        &self,
        row: &IndexRow,
        verts: &[Point3<f32>],
        pose: &Pose,
        source: &PixelSource,
        landmarks: &[(f64, f64)],
        train: bool,
        rng: &mut Rng,
        planes: Planes<'_>,
    ) -> Result<LoaderItem> {
        let mut buffer = self.take_buffer();
        // Only the window of the image the face can cover is rasterized and kept: the
        // slice, the lookups and the warp below read through it.
        let face = self.renderer.render_window_mask(
            verts,
            pose,
            row.sample.image_width,
            row.sample.image_height,
            &mut buffer,
        )?;
        self.official_from(
            row, verts, source, landmarks, train, rng, &buffer, &face, planes,
        )
    }

    /// An item by the official loader's rules. Long (over 150 lines) on purpose: it
    /// follows `ARKitDataset.get_item` step by step, in its order, so that the two can
    /// be read side by side; each step calls a function of its own.
    #[allow(clippy::too_many_arguments)]
    fn official_from(
        &self,
        row: &IndexRow,
        verts: &[Point3<f32>],
        source: &PixelSource,
        landmarks: &[(f64, f64)],
        train: bool,
        rng: &mut Rng,
        buffer: &VisibilityBuffer,
        face: &WindowMask,
        mut planes: Planes<'_>,
    ) -> Result<LoaderItem> {
        let s = self.options.img_size;
        let (w, h) = (
            row.sample.image_width as i64,
            row.sample.image_height as i64,
        );
        let extent = LandmarkExtent::of(landmarks.iter().copied());
        let box_of = |jitter| official_box(extent, jitter).map(|v| v as i64);
        // The face pixels of the official slice of the full mask, or why there are none.
        let choose_in = |b: [i64; 4]| -> std::result::Result<(Vec<i64>, i64, i64, i64), String> {
            let [left, top, right, bottom] = b;
            if right <= left || bottom <= top {
                return Err(format!("the official box {b:?} is empty"));
            }
            let rows = python_slice(top, bottom + 1, h);
            let cols = python_slice(left, right + 1, w);
            let width = cols.end - cols.start;
            let nz = face.face_offsets(rows.clone(), cols.clone());
            if nz.is_empty() {
                return Err(format!(
                    "the official box {b:?} (left, top, right, bottom) of a {w}x{h} image holds no face pixel of mask[top:bottom+1, left:right+1]{}: the official loader raises on this sample and trains on a random other one",
                    if top < 0 || left < 0 {
                        " (a negative start indexes from the end in Python)"
                    } else {
                        ""
                    }
                ));
            }
            Ok((nz, rows.start, cols.start, width))
        };
        let mut chosen_box = box_of(None);
        let mut found = None;
        if train {
            for _ in 0..JITTER_DRAWS {
                let b = box_of(Some(Self::draw_jitter(rng, extent.size)));
                if let Ok(c) = choose_in(b) {
                    chosen_box = b;
                    found = Some(c);
                    break;
                }
            }
        }
        let (nz, row0, col0, slice_w) = match found {
            Some(c) => c,
            None => choose_in(chosen_box).map_err(|why| {
                Error::invalid("official box", format!("{}: {why}", row.sample.key))
            })?,
        };
        let [left, top, right, bottom] = chosen_box;
        let crop = box_crop(left as f64, top as f64, right as f64, bottom as f64, s);
        let picks = sample_points(nz.len(), self.options.n_pts, rng.next_u64());
        let choose_box: Vec<i64> = picks.iter().map(|&p| nz[p as usize]).collect();
        // The official mapping: columns of the unclipped box width, then the affine map
        // cv2.getAffineTransform solves (its bits, see `official_crop::affine_transform`).
        let crop_w = right - left + 1;
        let (l, t, r, b) = (left as f32, top as f32, right as f32, bottom as f32);
        let last = (s - 1) as f32;
        let corners = [[0.0, 0.0], [0.0, last], [last, 0.0]];
        let box_corners = [[l, t], [l, b], [r, t]];
        let singular = || {
            Error::invalid(
                "official box",
                format!("{}: the box {chosen_box:?} is degenerate", row.sample.key),
            )
        };
        let tform = affine_transform(box_corners, corners).ok_or_else(singular)?;
        let tform_inv = affine_transform(corners, box_corners).ok_or_else(singular)?;
        let n = (s * s) as i64;
        let n_mesh = self.renderer.topology().triangles.len() as u32;
        let triangles = &self.renderer.topology().triangles;
        let mut choose = Vec::with_capacity(choose_box.len());
        let mut nocs = Vec::with_capacity(3 * choose_box.len());
        let mut corr_vertices = Vec::with_capacity(choose_box.len());
        let mut corr_weights = Vec::with_capacity(choose_box.len());
        for &cb in &choose_box {
            let col = (cb % crop_w + left) as f64;
            let rw = (cb / crop_w + top) as f64;
            // numpy's `point2d @ W + b`.
            let px = (col * tform[0] + rw * tform[1]) + tform[2];
            let py = (col * tform[3] + rw * tform[4]) + tform[5];
            let k = py.floor() as i64 * s as i64 + px.floor() as i64;
            choose.push(k);
            // The full-resolution pixel the slice index names.
            let (y, x) = (row0 + cb / slice_w, col0 + cb % slice_w);
            let i = face
                .window
                .index(x, y)
                .expect("a face pixel is in the window");
            let t = buffer.triangle[i];
            debug_assert!(t < n_mesh);
            let tri = triangles[t as usize];
            let wt = face.official_weights(tri, x, y);
            let attr = tri.map(|v| {
                let p = verts[v as usize];
                [p.x, p.y, p.z].map(|q| ((q as f64 * 4.5 + 0.5) * 255.0) as f32)
            });
            let [a0, a1, a2] = attr;
            for ((x0, x1), x2) in a0.iter().zip(a1).zip(a2) {
                let v = wt[0] * x0 + wt[1] * x1 + wt[2] * x2;
                nocs.push(v / 255.0 - 0.5);
            }
            corr_vertices.push(tri);
            corr_weights.push(wt);
        }
        // The official rule for points mapped outside the crop (only where the box leaves
        // the image and the slice is clipped or wrapped): every index past the end becomes
        // one random pixel, every negative index another (arkit_dataset.py:226-230).
        let replaced = choose.iter().any(|k| !(0..n).contains(k));
        if replaced {
            let (high, low) = (rng.below(n as u64) as i64, rng.below(n as u64) as i64);
            for k in &mut choose {
                if *k >= n {
                    *k = high;
                } else if *k < 0 {
                    *k = low;
                }
            }
        }
        let mut rgb = source.crop(&crop, train, &row.sample.key)?;
        if train {
            jitter_colour(&mut rgb, rng);
        }
        let mask = warp_mask_in(&crop, face.window, &face.mask);
        let box_clipped = left < 0 || top < 0 || right >= w || bottom >= h || replaced;
        Ok(LoaderItem {
            key: row.sample.key.clone(),
            image_path: self.image_path(row),
            img: planes.img(&rgb),
            choose,
            model: Vec::new(),
            uvmap: planes.uvmap(3 * (self.uvmap_size() as usize).pow(2), |out| {
                self.official_uv.uv_map_into(verts, out)
            }),
            nocs,
            mask: mask.iter().map(|&m| m as u8).collect(),
            corr_vertices,
            corr_weights,
            tform_inv,
            rt: row.sample.rt,
            crop,
            official_box: Some(chosen_box),
            choose_box,
            box_clipped,
        })
    }
}
