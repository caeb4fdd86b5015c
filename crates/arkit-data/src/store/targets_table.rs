//! The `targets` table that `render` writes, and the reader that turns one row back
//! into dense tensors for the network.
//!
//! Compact by construction (layouts in `schemas/targets.json`):
//! - `mask_rle`: run lengths (u32 LE) over the row-major crop, starting with a
//!   background run.
//! - `corr_vertices`: for each mask pixel in row-major order, 3 vertex ids (u16 LE).
//! - `corr_weights`: for each mask pixel, the first two barycentric weights quantised
//!   to u16 (`round(w * 65535)`); the third is `1 - w0 - w1`. The error this costs is at
//!   most `0.5 / 65535 = 7.6e-6` on `w0`, `w1` and `1.5e-5` on `w2`
//!   ([`WEIGHT_QUANTUM`]); a test checks it.
//! - `points`: the sampled rows (u32 LE indices into the mask pixels).
//! - `full_mask_rle`: with `render --full-mask`, the face mask over the whole
//!   `image_width x image_height` image, run lengths as `mask_rle`; empty otherwise.
//! - `uv_map_delta`: the `uv_size^2 x 3` canonical positions in metres as IEEE float16
//!   (NaN where no UV triangle covers a texel), stored losslessly in a form zstd
//!   compresses well ([`encode_uv_map`]): per channel, each row's first texel and then
//!   the wrapping differences of neighbouring texels' float16 bits, low bytes of the
//!   whole channel first, then high bytes. A smooth map makes the differences small, so
//!   the high-byte plane is mostly zeros: 14 KiB per 192x192 map in the Parquet file
//!   instead of 48 KiB for plain float16 (measured on `synth` faces, zstd). float16
//!   keeps about 3 significant digits: a relative error of at most 2^-11, 0.031 mm for
//!   |x| < 0.125 m.
//!
//! The byte codecs live in `arkit_core` ([`arkit_core::rle_encode`] and the others,
//! re-exported here) so they can
//! be fuzzed without polars. Reading never trusts a size from the file: `crop_size`,
//! `uv_size`, `image_width` and `image_height` are checked against [`arkit_core::limits`]
//! (a null is an error naming the column and row) before anything is sized from them;
//! blobs must hold whole elements; run lengths are summed before a mask is allocated;
//! [`dense`] checks every point and the matrix size before allocating. Tested below with
//! crafted files and records.

use crate::crop::{CropTransform, RuleSet};
use crate::store::face_targets::FaceTargets;
use arkit_core::SampleKey;
use arkit_core::limits;
use arkit_core::{Error, Result};
use half::f16;
use polars::prelude::*;
use std::path::Path;

use arkit_core::{
    decode_uv_map, encode_uv_map, mask_len, pack_u16_le, pack_u32_le, rle_decode, rle_encode,
    unpack_u32_le,
};

/// Largest error of a stored barycentric weight.
pub const WEIGHT_QUANTUM: f32 = 1.0 / 65535.0;

/// One row of the `targets` table.
#[derive(Clone, Debug, PartialEq)]
pub struct TargetsRecord {
    /// The sample's key.
    pub key: SampleKey,
    /// The crop.
    pub crop: CropTransform,
    /// Run lengths of the mask (background first).
    pub mask_rle: Vec<u32>,
    /// Vertex ids per mask pixel.
    pub corr_vertices: Vec<[u16; 3]>,
    /// Quantised first two weights per mask pixel.
    pub corr_weights_q: Vec<[u16; 2]>,
    /// Sampled rows.
    pub points: Vec<u32>,
    /// UV map side.
    pub uv_size: u32,
    /// UV map as float16 bits.
    pub uv_map: Vec<u16>,
    /// Width of the sample's full image.
    pub image_width: u32,
    /// Height of the sample's full image.
    pub image_height: u32,
    /// Run lengths of the full-image mask, or empty when it was not rendered.
    pub full_mask_rle: Vec<u32>,
}

fn quantise(w: f32) -> u16 {
    (w.clamp(0.0, 1.0) * 65535.0).round() as u16
}

impl TargetsRecord {
    /// Packs rendered targets, sampled points and a UV map.
    pub fn new(
        key: SampleKey,
        t: &FaceTargets,
        points: Vec<u32>,
        uv_size: u32,
        uv_map: &[[f32; 3]],
    ) -> Self {
        TargetsRecord {
            key,
            crop: t.crop,
            mask_rle: rle_encode(&t.mask),
            corr_vertices: t.corr_vertices.clone(),
            corr_weights_q: t
                .corr_weights
                .iter()
                .map(|w| [quantise(w[0]), quantise(w[1])])
                .collect(),
            points,
            uv_size,
            uv_map: uv_map
                .iter()
                .flat_map(|p| p.map(|c| f16::from_f32(c).to_bits()))
                .collect(),
            image_width: 0,
            image_height: 0,
            full_mask_rle: Vec::new(),
        }
    }

    /// Records the sample's image size and, when rendered, its full-image mask.
    pub(crate) fn with_image(
        mut self,
        width: u32,
        height: u32,
        full_mask: Option<&[bool]>,
    ) -> Self {
        self.image_width = width;
        self.image_height = height;
        self.full_mask_rle = full_mask.map(rle_encode).unwrap_or_default();
        self
    }

    /// The full-image mask (`image_width * image_height`, row-major), or `None` when
    /// `render` was not asked for it.
    pub fn full_mask(&self) -> Result<Option<Vec<bool>>> {
        if self.full_mask_rle.is_empty() {
            return Ok(None);
        }
        let len = mask_len(self.image_width, self.image_height, "full mask")?;
        rle_decode(&self.full_mask_rle, len).map(Some)
    }

    /// The stored weights, third recovered as `1 - w0 - w1`.
    pub fn weights(&self) -> Vec<[f32; 3]> {
        self.corr_weights_q
            .iter()
            .map(|q| {
                let (a, b) = (q[0] as f32 / 65535.0, q[1] as f32 / 65535.0);
                [a, b, 1.0 - a - b]
            })
            .collect()
    }

    /// The mask, decoded.
    pub fn mask(&self) -> Result<Vec<bool>> {
        let len = mask_len(self.crop.size, self.crop.size, "crop mask")?;
        rle_decode(&self.mask_rle, len)
    }

    /// The UV map as f32 positions.
    pub fn uv_positions(&self) -> Vec<[f32; 3]> {
        self.uv_map
            .chunks_exact(3)
            .map(|c| [0, 1, 2].map(|k| f16::from_bits(c[k]).to_f32()))
            .collect()
    }
}

/// The rows as a DataFrame (columns as `schemas/targets.json`).
pub(crate) fn targets_frame(rows: &[TargetsRecord]) -> Result<DataFrame> {
    let s = |name: &str, f: &dyn Fn(&TargetsRecord) -> String| {
        Column::new(name.into(), rows.iter().map(f).collect::<Vec<String>>())
    };
    let f = |name: &str, g: &dyn Fn(&TargetsRecord) -> f64| {
        Column::new(name.into(), rows.iter().map(g).collect::<Vec<f64>>())
    };
    let u = |name: &str, g: &dyn Fn(&TargetsRecord) -> u32| {
        Column::new(name.into(), rows.iter().map(g).collect::<Vec<u32>>())
    };
    let b = |name: &str, g: &dyn Fn(&TargetsRecord) -> Vec<u8>| {
        let blobs: Vec<Vec<u8>> = rows.iter().map(g).collect();
        let refs: Vec<&[u8]> = blobs.iter().map(|v| v.as_slice()).collect();
        if rows.is_empty() {
            Column::new_empty(name.into(), &DataType::Binary)
        } else {
            Column::new(name.into(), refs)
        }
    };
    let columns = vec![
        s("subject_id", &|r| r.key.subject_id.clone()),
        s("facial_action", &|r| r.key.facial_action.clone()),
        s("img_id", &|r| r.key.img_id.clone()),
        f("crop_x0", &|r| r.crop.x0),
        f("crop_y0", &|r| r.crop.y0),
        f("crop_side", &|r| r.crop.side),
        f("crop_side_y", &|r| r.crop.side_y),
        u("crop_size", &|r| r.crop.size),
        s("crop_sampling", &|r| {
            r.crop.rules.sampling_name().to_string()
        }),
        b("mask_rle", &|r| pack_u32_le(&r.mask_rle)),
        b("corr_vertices", &|r| {
            pack_u16_le(r.corr_vertices.iter().flatten().copied())
        }),
        b("corr_weights", &|r| {
            pack_u16_le(r.corr_weights_q.iter().flatten().copied())
        }),
        b("points", &|r| pack_u32_le(&r.points)),
        u("uv_size", &|r| r.uv_size),
        b("uv_map_delta", &|r| encode_uv_map(&r.uv_map, r.uv_size)),
        u("image_width", &|r| r.image_width),
        u("image_height", &|r| r.image_height),
        b("full_mask_rle", &|r| pack_u32_le(&r.full_mask_rle)),
    ];
    DataFrame::new(rows.len(), columns).map_err(|e| Error::invalid("targets table", e.to_string()))
}

/// Reads a `targets` Parquet file back into records.
pub fn read_targets(path: &Path) -> Result<Vec<TargetsRecord>> {
    targets_from_frame(&crate::store::parquet::read_parquet(path)?, path)
}

/// The rows of a `targets` table read as `df` from `path` (which errors name).
pub(crate) fn targets_from_frame(df: &DataFrame, path: &Path) -> Result<Vec<TargetsRecord>> {
    let st = |n: &str| crate::store::parquet::str_values(df, n, path);
    let fl = |n: &str| crate::store::parquet::f64_values(df, n, path);
    let bad = |n: &str, e: PolarsError| Error::format(path, format!("column {n}: {e}"));
    // A u32 column, each value at most `max` (checked before anything is sized from it);
    // a null is an error naming the column and the row.
    let u32s = |n: &str, max: u32| -> Result<Vec<u32>> {
        let c = df.column(n).map_err(|e| bad(n, e))?;
        c.u32()
            .map_err(|e| bad(n, e))?
            .iter()
            .enumerate()
            .map(|(i, v)| match v {
                None => Err(Error::format(path, format!("row {i}: {n} is null"))),
                Some(v) if v > max => Err(Error::format(
                    path,
                    format!("row {i}: {n} {v} is more than the {max} allowed"),
                )),
                Some(v) => Ok(v),
            })
            .collect()
    };
    let bins = |n: &str| -> Result<Vec<Vec<u8>>> {
        let c = df.column(n).map_err(|e| bad(n, e))?;
        Ok(c.binary()
            .map_err(|e| bad(n, e))?
            .iter()
            .map(|v| v.unwrap_or_default().to_vec())
            .collect())
    };
    let (subj, act, img) = (st("subject_id")?, st("facial_action")?, st("img_id")?);
    let (x0, y0, side) = (fl("crop_x0")?, fl("crop_y0")?, fl("crop_side")?);
    // Files written before the official crop (2026-11-30) have a square box sampled
    // at pixel centres.
    let has = |n: &str| df.get_column_names().iter().any(|c| c.as_str() == n);
    let side_y = if has("crop_side_y") {
        fl("crop_side_y")?
    } else {
        side.clone()
    };
    let sampling = if has("crop_sampling") {
        st("crop_sampling")?
            .iter()
            .map(|name| {
                RuleSet::from_sampling_name(name).ok_or_else(|| {
                    Error::format(
                        path,
                        format!("crop_sampling {name:?} is neither \"centre\" nor \"corner\""),
                    )
                })
            })
            .collect::<Result<Vec<_>>>()?
    } else {
        vec![RuleSet::Exact; df.height()]
    };
    let size = u32s("crop_size", limits::MAX_CROP_SIZE)?;
    let uv_size = u32s("uv_size", limits::MAX_UV_SIZE)?;
    let image_width = u32s("image_width", limits::MAX_IMAGE_SIDE)?;
    let image_height = u32s("image_height", limits::MAX_IMAGE_SIDE)?;
    let full_mask = bins("full_mask_rle")?;
    let (mask, cv, cw, pts, uv) = (
        bins("mask_rle")?,
        bins("corr_vertices")?,
        bins("corr_weights")?,
        bins("points")?,
        bins("uv_map_delta")?,
    );
    let at = |i: usize| move |e: Error| Error::format(path, format!("row {i}: {e}"));
    let mut out = Vec::with_capacity(df.height());
    for i in 0..df.height() {
        let (corr_vertices, corr_weights_q) =
            arkit_core::decode_correspondences(&cv[i], &cw[i]).map_err(at(i))?;
        out.push(TargetsRecord {
            key: SampleKey {
                subject_id: subj[i].clone(),
                facial_action: act[i].clone(),
                img_id: img[i].clone(),
            },
            crop: CropTransform {
                x0: x0[i],
                y0: y0[i],
                side: side[i],
                side_y: side_y[i],
                size: size[i],
                rules: sampling[i],
            },
            mask_rle: unpack_u32_le(&mask[i], "mask_rle").map_err(at(i))?,
            corr_vertices,
            corr_weights_q,
            points: unpack_u32_le(&pts[i], "points").map_err(at(i))?,
            uv_size: uv_size[i],
            uv_map: decode_uv_map(&uv[i], uv_size[i]).map_err(at(i))?,
            image_width: image_width[i],
            image_height: image_height[i],
            full_mask_rle: unpack_u32_le(&full_mask[i], "full_mask_rle").map_err(at(i))?,
        });
    }
    Ok(out)
}

/// Reads a `targets` Parquet file into a map from sample key to its row.
pub fn read_targets_by_key(
    path: &Path,
) -> Result<std::collections::HashMap<SampleKey, TargetsRecord>> {
    Ok(read_targets(path)?
        .into_iter()
        .map(|t| (t.key.clone(), t))
        .collect())
}

/// The targets file of shard `index` under `dir` (`dir/targets/part-KKKKK.parquet`).
pub fn shard_path(dir: &Path, index: usize) -> std::path::PathBuf {
    dir.join("targets").join(format!("part-{index:05}.parquet"))
}

/// The errors file of shard `index` under `dir`: the samples `render` could not render
/// (`dir/targets/errors/part-KKKKK.parquet`, the `errors` table of `convert`).
pub fn errors_path(dir: &Path, index: usize) -> std::path::PathBuf {
    dir.join("targets")
        .join("errors")
        .join(format!("part-{index:05}.parquet"))
}

/// The keys of the samples `render` skipped in shard `index` under `dir` (none when
/// the errors file is absent, as in targets written before it existed).
pub fn read_skipped_keys(dir: &Path, index: usize) -> Result<std::collections::HashSet<SampleKey>> {
    let p = errors_path(dir, index);
    if !p.exists() {
        return Ok(Default::default());
    }
    Ok(crate::store::samples_table::read_errors(&p)?
        .into_iter()
        .map(|e| e.key)
        .collect())
}

use crate::store::face_targets::mask_pixel_indices;

/// Dense tensors for one sample, ready for the network.
#[derive(Clone, Debug, PartialEq)]
pub struct DenseTargets {
    /// Crop side.
    pub size: u32,
    /// Face mask, `size * size`, 1 on face pixels.
    pub mask: Vec<u8>,
    /// The chosen pixels (row-major crop indices), one per point.
    pub chosen_pixels: Vec<u32>,
    /// The correspondence matrix rows of the chosen pixels: `points x vertex_count`,
    /// row-major, three non-zeros per row.
    pub corr_matrix: Vec<f32>,
    /// Canonical position under each chosen pixel (the coordinate map there).
    pub coords: Vec<[f32; 3]>,
    /// UV position map, `uv_size * uv_size * 3`.
    pub uv_map: Vec<f32>,
    /// UV map side.
    pub uv_size: u32,
}

/// Builds the dense tensors of a stored row for a face of `vertex_count` vertices with
/// canonical vertices `verts`.
pub fn dense(record: &TargetsRecord, verts: &[nalgebra::Point3<f32>]) -> Result<DenseTargets> {
    let mask = record.mask()?;
    let pixels = mask_pixel_indices(&mask);
    if pixels.len() != record.corr_vertices.len()
        || record.corr_weights_q.len() != record.corr_vertices.len()
    {
        return Err(Error::invalid(
            "targets",
            format!(
                "{} mask pixels but {} correspondences and {} weights",
                pixels.len(),
                record.corr_vertices.len(),
                record.corr_weights_q.len()
            ),
        ));
    }
    let n = verts.len();
    // Every size below comes from the stored row: check before allocating.
    if let Some((row, &p)) = record
        .points
        .iter()
        .enumerate()
        .find(|(_, p)| **p as usize >= pixels.len())
    {
        return Err(Error::invalid(
            "targets",
            format!("point {row} refers to mask pixel {p} of {}", pixels.len()),
        ));
    }
    let cells = (record.points.len() as u64)
        .checked_mul(n as u64)
        .filter(|&c| c.saturating_mul(4) <= limits::MAX_DENSE_BYTES)
        .ok_or_else(|| {
            Error::invalid(
                "targets",
                format!(
                    "{} points x {n} vertices is more than the {} bytes allowed for the \
                     correspondence matrix",
                    record.points.len(),
                    limits::MAX_DENSE_BYTES
                ),
            )
        })?;
    let weights = record.weights();
    let mut corr_matrix = vec![0f32; cells as usize];
    let mut coords = Vec::with_capacity(record.points.len());
    let mut chosen_pixels = Vec::with_capacity(record.points.len());
    for (row, &p) in record.points.iter().enumerate() {
        let p = p as usize;
        chosen_pixels.push(pixels[p]);
        let ids = record.corr_vertices[p];
        let mut c = nalgebra::Vector3::zeros();
        for k in 0..3 {
            let v = ids[k] as usize;
            if v >= n {
                return Err(Error::invalid("targets", format!("vertex id {v} >= {n}")));
            }
            corr_matrix[row * n + v] += weights[p][k];
            c += verts[v].coords * weights[p][k];
        }
        coords.push([c.x, c.y, c.z]);
    }
    Ok(DenseTargets {
        size: record.crop.size,
        mask: mask.iter().map(|&m| m as u8).collect(),
        chosen_pixels,
        corr_matrix,
        coords,
        uv_map: record.uv_positions().into_iter().flatten().collect(),
        uv_size: record.uv_size,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uv_map_encoding_is_lossless_and_compact_where_smooth() {
        // The built-in face's UV map: smooth, NaN outside the layout, signs changing.
        let topo = crate::mesh::synthetic_face::builtin().topology.clone();
        let verts = topo.template.clone().expect("template");
        let size = 96u32;
        let map = crate::render::uv_map::UvMapper::derive(&topo)
            .unwrap()
            .position_map(&verts, size);
        let bits: Vec<u16> = map
            .iter()
            .flat_map(|p| p.map(|c| f16::from_f32(c).to_bits()))
            .collect();
        let blob = encode_uv_map(&bits, size);
        assert_eq!(blob.len(), bits.len() * 2);
        assert_eq!(decode_uv_map(&blob, size).unwrap(), bits);
        // Smooth rows: most high bytes of the differences are 0 or 0xff.
        let texels = (size * size) as usize;
        let high = &blob[texels..2 * texels];
        let small = high.iter().filter(|&&b| b == 0 || b == 0xff).count();
        assert!(small * 10 > texels * 8, "{small} of {texels}");
        // A wrong length is an error, not a misread.
        assert!(decode_uv_map(&blob[1..], size).is_err());
        assert!(decode_uv_map(&blob, size + 1).is_err());
    }

    #[test]
    fn weight_quantisation_error_is_bounded() {
        let mut worst = 0.0f32;
        for i in 0..1000 {
            let a = (i as f32 * 0.618).fract() * 0.7;
            let b = (i as f32 * 0.377).fract() * (1.0 - a);
            let w = [a, b, 1.0 - a - b];
            let q = [quantise(w[0]), quantise(w[1])];
            let back = [q[0] as f32 / 65535.0, q[1] as f32 / 65535.0];
            let third = 1.0 - back[0] - back[1];
            worst = worst
                .max((back[0] - w[0]).abs())
                .max((back[1] - w[1]).abs())
                .max((third - w[2]).abs() / 2.0);
        }
        assert!(worst <= 0.5 * WEIGHT_QUANTUM + 1e-7, "{worst}");
    }

    fn tiny_record() -> TargetsRecord {
        TargetsRecord {
            key: SampleKey {
                subject_id: "1".into(),
                facial_action: "a".into(),
                img_id: "2".into(),
            },
            crop: CropTransform {
                x0: 0.0,
                y0: 0.0,
                side: 2.0,
                side_y: 2.0,
                size: 2,
                rules: RuleSet::Exact,
            },
            mask_rle: vec![3, 1],
            corr_vertices: vec![[0, 1, 2]],
            corr_weights_q: vec![[30000, 30000]],
            points: vec![0, 0],
            uv_size: 1,
            uv_map: vec![1, 2, 3],
            image_width: 4,
            image_height: 2,
            full_mask_rle: vec![7, 1],
        }
    }

    #[test]
    fn read_targets_checks_sizes_and_nulls_from_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.parquet");
        let rec = tiny_record();
        let write = |df: &mut DataFrame| crate::store::parquet::write_parquet(&path, df).unwrap();
        let mut df = targets_frame(std::slice::from_ref(&rec)).unwrap();
        write(&mut df);
        assert_eq!(read_targets(&path).unwrap(), vec![rec.clone()]);
        let expect_err = |col: Column, want: &str| {
            let mut df = targets_frame(std::slice::from_ref(&rec)).unwrap();
            df.with_column(col).unwrap();
            write(&mut df);
            let e = read_targets(&path).unwrap_err().to_string();
            assert!(e.contains("t.parquet: row 0: ") && e.contains(want), "{e}");
        };
        let u = |n: &str, v: Option<u32>| Column::new(n.into(), vec![v]);
        let b = |n: &str, v: &[u8]| Column::new(n.into(), vec![v]);
        expect_err(
            u("crop_size", Some(5000)),
            "crop_size 5000 is more than the 4096",
        );
        expect_err(u("crop_size", None), "crop_size is null");
        expect_err(
            u("uv_size", Some(u32::MAX)),
            "uv_size 4294967295 is more than",
        );
        expect_err(
            u("image_width", Some(70_000)),
            "image_width 70000 is more than",
        );
        expect_err(u("image_height", None), "image_height is null");
        expect_err(
            b("mask_rle", &[1, 0, 0]),
            "mask_rle: 3 bytes, not a whole number",
        );
        expect_err(b("points", &[1, 0, 0, 0, 0]), "points: 5 bytes");
        expect_err(b("full_mask_rle", &[9]), "full_mask_rle: 1 bytes");
        expect_err(
            b("corr_weights", &[1, 0]),
            "corr_vertices has 6 bytes and corr_weights 2",
        );
        expect_err(b("uv_map_delta", &[0; 5]), "uv_map_delta");
    }

    #[test]
    fn masks_and_dense_tensors_check_sizes_before_allocating() {
        let verts = vec![nalgebra::Point3::new(0.0f32, 0.0, 0.0); 3];
        let rec = tiny_record();
        assert_eq!(rec.mask().unwrap(), vec![false, false, false, true]);
        let full = rec.full_mask().unwrap().unwrap();
        assert_eq!(
            (full.len(), full.iter().filter(|&&m| m).count(), full[7]),
            (8, 1, true)
        );
        let d = dense(&rec, &verts).unwrap();
        assert_eq!((d.corr_matrix.len(), d.chosen_pixels), (6, vec![3, 3]));
        // 12 bytes of runs claiming 6 G pixels: refused from their sum.
        let mut r = rec.clone();
        r.mask_rle = vec![1 << 31, 1 << 31, 1 << 31];
        assert!(
            r.mask()
                .unwrap_err()
                .to_string()
                .contains("runs cover 6442450944")
        );
        // A huge crop side or image from a record: refused from the size.
        r.crop.size = u32::MAX;
        assert!(r.mask().unwrap_err().to_string().contains("more than"));
        let mut r = rec.clone();
        (r.image_width, r.image_height) = (65_535, 65_535);
        let e = r.full_mask().unwrap_err().to_string();
        assert!(e.contains("65535x65535") && e.contains("more than"), "{e}");
        // 100 000 points x 1220 vertices (488 MB of matrix): refused before allocating.
        let mut r = rec.clone();
        r.points = vec![0; 100_000];
        let many = vec![nalgebra::Point3::new(0.0f32, 0.0, 0.0); 1220];
        let e = dense(&r, &many).unwrap_err().to_string();
        assert!(e.contains("100000 points x 1220 vertices"), "{e}");
        // A point past the mask pixels, or weights not matching, are errors.
        let mut r = rec.clone();
        r.points = vec![0, 1];
        assert!(
            dense(&r, &verts)
                .unwrap_err()
                .to_string()
                .contains("mask pixel 1 of 1")
        );
        let mut r = rec.clone();
        r.corr_weights_q.clear();
        assert!(dense(&r, &verts).is_err());
    }
}
