//! `loader::FaceLoader` (what the Python `ARKitFaceDataset` serves) against the other
//! paths of the library: `render`'s stored targets, the crop and the official crop
//! computed independently, and the official rules derived by hand.

#![allow(clippy::needless_range_loop)] // index loops over x, y, z read plainest here

use arkit_core::conventions::Camera;
use arkit_core::conventions::Pose;
use arkit_data::crop::RuleSet;
use arkit_data::crop::{self, CropTransform};
use arkit_data::loader::{FaceLoader, ItemPlanes, LoaderMode, LoaderOptions};
use arkit_data::render::FaceRenderer;
use arkit_data::render::RenderOptions;

use arkit_data::store;
use nalgebra::Point3;
use std::collections::HashMap;
use std::path::Path;

const S: u32 = 192;

/// Synthetic release in `release`, converted into `dir` (images not embedded, so the
/// loader reads the release's files as the official loader does).
fn converted(release: &Path, dir: &Path) {
    crate::support::converted::converted_synthetic(release, dir, 3, 3, 400, 23);
}

fn loader(dir: &Path, mode: LoaderMode, compat: RuleSet, n_pts: usize) -> FaceLoader {
    let options = LoaderOptions {
        split: None,
        mode,
        rules: compat,
        img_size: S,
        n_pts,
        seed: 4,
    };
    let topology = arkit_data::mesh::builtin().topology.clone();
    FaceLoader::open(dir, topology, None, options).unwrap()
}

#[test]
fn exact_items_agree_with_the_targets_render_stores() {
    let (release, dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    converted(release.path(), dir.path());
    let topology = arkit_data::mesh::builtin().topology.clone();
    let renderer = FaceRenderer::new(topology, Camera::release_projection()).unwrap();
    let ro = RenderOptions {
        size: S,
        uv_size: S,
        points: 64,
        seed: 2,
        shard: (0, 1),
        full_mask: false,
        output: dir.path().to_path_buf(),
    };
    arkit_data::render::render_dataset(dir.path(), &renderer, &ro, &|_| {}).unwrap();
    let data = arkit_data::store::Dataset::open(dir.path()).unwrap();
    let samples = data.read_all_samples().unwrap();
    let mut targets = HashMap::new();
    for shard in data.shards() {
        let path = store::shard_path(dir.path(), shard.index);
        for t in store::read_targets(&path).unwrap() {
            targets.insert(t.key.clone(), t);
        }
    }
    let l = loader(dir.path(), LoaderMode::Eval, RuleSet::Exact, 300);
    assert_eq!(l.len(), samples.len());
    for (i, sample) in samples.iter().enumerate() {
        let item = l.item(i, 0).unwrap();
        assert_eq!(item.key, sample.key);
        assert_eq!(item.model, sample.verts);
        let t = &targets[&sample.key];
        // The crop mask, bit for bit.
        let mask: Vec<u8> = t.mask().unwrap().iter().map(|&m| m as u8).collect();
        assert_eq!(item.mask, mask, "{}", sample.key);
        // Each point: a mask pixel, with render's vertex ids and weights (stored to
        // 1/65535) and a canonical position 4.5 sum w V.
        let pixels = arkit_data::store::mask_pixel_indices(&t.mask().unwrap());
        let row_of: HashMap<u32, usize> = pixels.iter().enumerate().map(|(r, &p)| (p, r)).collect();
        let weights = t.weights();
        assert_eq!(item.choose.len(), 300);
        for (k, &c) in item.choose.iter().enumerate() {
            let r = row_of[&(c as u32)];
            let ids = t.corr_vertices[r];
            assert_eq!(item.corr_vertices[k], ids.map(|v| v as u32));
            for j in 0..3 {
                assert!((item.corr_weights[k][j] - weights[r][j]).abs() <= 2.5 / 65535.0);
            }
            let w = item.corr_weights[k];
            for a in 0..3 {
                let p: f32 = (0..3)
                    .map(|j| w[j] * sample.verts[3 * ids[j] as usize + a])
                    .sum();
                assert!((item.nocs[3 * k + a] - 4.5 * p).abs() < 1e-5);
            }
        }
        // The UV map: render's (float16, metres) times 9, clipped; -1 where uncovered.
        let uv = t.uv_positions();
        let n = (S * S) as usize;
        for (i, p) in uv.iter().enumerate() {
            for a in 0..3 {
                let got = item.uvmap[a * n + i];
                if p[a].is_nan() {
                    assert_eq!(got, -1.0);
                } else {
                    assert!((got - (9.0 * p[a]).clamp(-1.0, 1.0)).abs() < 4e-3);
                }
            }
        }
        // The image: the table's crop of the decoded image, normalised.
        let crop = CropTransform::around_landmarks(&sample.landmarks_2d, S);
        let rgb = crop.crop_image(&data.image(sample).unwrap());
        assert_eq!(item.img, arkit_data::loader::normalise(rgb.as_raw()));
        // tform_inv takes a crop pixel to the image point it samples.
        let [a, b, c, d, e, f] = item.tform_inv;
        for (col, row) in [(0u32, 0u32), (191, 5), (77, 150)] {
            let (u, v) = crop.pixel_to_image(col, row);
            let (x, y) = (col as f64, row as f64);
            assert!((a * x + b * y + c - u).abs() < 1e-9 && (d * x + e * y + f - v).abs() < 1e-9);
        }
    }
}

#[test]
fn official_items_follow_the_official_rules() {
    let (release, dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    converted(release.path(), dir.path());
    let data = arkit_data::store::Dataset::open(dir.path()).unwrap();
    let samples = data.read_all_samples().unwrap();
    let topology = arkit_data::mesh::builtin().topology.clone();
    let mut renderer = FaceRenderer::new(topology.clone(), Camera::release_projection())
        .unwrap()
        .with_rules(RuleSet::Official);
    // The holes closed as the official mask closes them: eyes first, then the mouth.
    let loops = arkit_data::render::UvMapper::derive(&topology)
        .unwrap()
        .centroid_loops;
    let organs = arkit_data::loader::official_organ_triangles(
        [&loops[1], &loops[2], &loops[0]],
        &topology.uv,
    );
    renderer.set_hole_triangles(&organs).unwrap();
    for n_pts in [256, 20_000] {
        let l = loader(dir.path(), LoaderMode::Eval, RuleSet::Official, n_pts);
        for (i, sample) in samples.iter().enumerate() {
            let item = l.item(i, 0).unwrap();
            let verts: Vec<Point3<f32>> = sample
                .verts
                .chunks(3)
                .map(|c| Point3::new(c[0], c[1], c[2]))
                .collect();
            let pose = Pose::from_release_rt(&sample.rt).unwrap();
            let (w, h) = (sample.image_width, sample.image_height);
            // The box: the library's official crop, whose corners are the box's.
            let crop = renderer.official_crop(&verts, &pose, w, h, S).unwrap();
            let [left, top, right, bottom] = item.official_box.unwrap();
            assert_eq!((left as f64, top as f64), (crop.x0, crop.y0));
            let right_of = crop.x0 + crop.side * (S - 1) as f64 / S as f64;
            assert!((right as f64 - right_of).abs() < 1e-9 && bottom > top);
            assert_eq!(item.crop, crop);
            // The mask: the official full-resolution mask warped as cv2 does.
            let mut buffer = arkit_core::VisibilityBuffer::new(1, 1);
            let full = renderer
                .render_full_mask(&verts, &pose, w, h, &mut buffer)
                .unwrap();
            let warped = crop::warp_mask(&full, w, h, &crop);
            assert_eq!(
                item.mask,
                warped.iter().map(|&m| m as u8).collect::<Vec<_>>()
            );
            // The points: face pixels of mask[top:bottom+1, left:right+1] (inside the
            // image here), mapped by the affine map and floor.
            assert!(!item.box_clipped);
            let crop_w = right - left + 1;
            let face_in_box: Vec<i64> = (top..=bottom)
                .flat_map(|y| (left..=right).map(move |x| (y, x)))
                .enumerate()
                .filter(|&(_, (y, x))| full[(y * w as i64 + x) as usize])
                .map(|(k, _)| k as i64)
                .collect();
            assert_eq!(item.choose_box.len(), n_pts);
            if face_in_box.len() >= n_pts {
                // Drawn without repetition, in pixel order.
                assert!(item.choose_box.windows(2).all(|p| p[0] < p[1]));
            } else {
                // All of them, repeated cyclically (np.pad 'wrap').
                for (k, &c) in item.choose_box.iter().enumerate() {
                    assert_eq!(c, face_in_box[k % face_in_box.len()]);
                }
            }
            // cv2.getAffineTransform of the box corners onto the crop's.
            let (l, t, r, b) = (left as f32, top as f32, right as f32, bottom as f32);
            let last = (S - 1) as f32;
            let m = crop::affine_transform(
                [[l, t], [l, b], [r, t]],
                [[0.0, 0.0], [0.0, last], [last, 0.0]],
            )
            .unwrap();
            // An axis-aligned scale by (S - 1) / (right - left), to rounding.
            let sx = (S - 1) as f64 / (right - left) as f64;
            assert!(
                (m[0] - sx).abs() < 1e-12
                    && m[1].abs() < 1e-12
                    && (m[2] + left as f64 * sx).abs() < 1e-9
            );
            for (k, &cb) in item.choose_box.iter().enumerate() {
                assert!(face_in_box.binary_search(&cb).is_ok());
                let (col, row) = (cb % crop_w, cb / crop_w);
                let (x, y) = ((col + left) as f64, (row + top) as f64);
                let px = ((x * m[0] + y * m[1]) + m[2]).floor() as i64;
                let py = ((x * m[3] + y * m[4]) + m[5]).floor() as i64;
                assert_eq!(item.choose[k], py * S as i64 + px, "point {k}");
                // Screen-space weights of a triangle holding the pixel: sum 1.
                let ws: f32 = item.corr_weights[k].iter().sum();
                assert!((ws - 1.0).abs() < 1e-5);
                let ids = item.corr_vertices[k];
                for a in 0..3 {
                    let p: f32 = (0..3)
                        .map(|j| item.corr_weights[k][j] * sample.verts[3 * ids[j] as usize + a])
                        .sum();
                    assert!((item.nocs[3 * k + a] - 4.5 * p).abs() < 2e-4);
                }
            }
            // The image: cv2.warpAffine of the decoded image, normalised.
            let img = data.image(sample).unwrap();
            let rgb = crop::warp_affine(img.as_raw(), w, h, 3, &crop);
            assert_eq!(item.img, arkit_data::loader::normalise(&rgb));
            // tform_inv: cv2.getAffineTransform of the crop corners onto the box.
            let s1 = (S - 1) as f64;
            let hand = [
                (right - left) as f64 / s1,
                0.0,
                left as f64,
                0.0,
                (bottom - top) as f64 / s1,
                top as f64,
            ];
            for (a, b) in item.tform_inv.iter().zip(hand) {
                assert!((a - b).abs() < 1e-9, "{:?} vs {hand:?}", item.tform_inv);
            }
            // The UV map is in [-1, 1] and covers most of the square.
            assert!(item.uvmap.iter().all(|v| (-1.0..=1.0).contains(v)));
        }
    }
}

#[test]
fn training_items_are_a_function_of_seed_epoch_and_index() {
    let (release, dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    converted(release.path(), dir.path());
    for compat in [RuleSet::Exact, RuleSet::Official] {
        let a = loader(dir.path(), LoaderMode::Train, compat, 128);
        let b = loader(dir.path(), LoaderMode::Train, compat, 128);
        // Order of calls does not matter: item (3, epoch 1) is the same either way.
        let x = a.item(3, 1).unwrap();
        let _ = b.item(0, 0).unwrap();
        assert_eq!(b.item(3, 1).unwrap(), x);
        // Another epoch: another box and colour jitter.
        let y = a.item(3, 2).unwrap();
        assert_ne!(x.crop, y.crop);
        assert_ne!(x.img, y.img);
        // Evaluation ignores the epoch.
        let e = loader(dir.path(), LoaderMode::Eval, compat, 128);
        assert_eq!(e.item(3, 1).unwrap(), e.item(3, 7).unwrap());
    }
}

#[test]
fn items_written_into_planes_equal_items_allocated() {
    let (release, dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    converted(release.path(), dir.path());
    for compat in [RuleSet::Exact, RuleSet::Official] {
        for mode in [LoaderMode::Eval, LoaderMode::Train] {
            let l = loader(dir.path(), mode, compat, 64);
            let (s, u) = (S as usize, l.uvmap_size() as usize);
            assert_eq!(u, s);
            // Planes holding other values first: every value must be written.
            let mut img = vec![f32::NAN; 3 * s * s];
            let mut uvmap = vec![7.0f32; 3 * u * u];
            for index in [0, 4, 8] {
                let whole = l.item(index, 2).unwrap();
                let planes = ItemPlanes {
                    img: &mut img,
                    uvmap: &mut uvmap,
                };
                let mut into = l.item_into(index, 2, planes).unwrap();
                assert!(into.img.is_empty() && into.uvmap.is_empty());
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&img), bits(&whole.img), "{compat:?} {mode:?} {index}");
                assert_eq!(
                    bits(&uvmap),
                    bits(&whole.uvmap),
                    "{compat:?} {mode:?} {index}"
                );
                assert!(uvmap.contains(&-1.0) && uvmap.iter().any(|&v| v != -1.0));
                (into.img, into.uvmap) = (whole.img.clone(), whole.uvmap.clone());
                assert_eq!(into, whole);
            }
            // Planes of the wrong size are refused, not written past.
            let mut short = vec![0f32; 3 * s * s - 1];
            let planes = ItemPlanes {
                img: &mut short,
                uvmap: &mut uvmap,
            };
            let err = l.item_into(0, 0, planes).unwrap_err().to_string();
            assert!(err.contains("expected"), "{err}");
        }
    }
}

#[test]
fn a_missing_image_or_annotation_is_an_error_naming_the_file() {
    let (release, dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    converted(release.path(), dir.path());
    let l = loader(dir.path(), LoaderMode::Eval, RuleSet::Exact, 64);
    let item = l.item(0, 0).unwrap();
    std::fs::remove_file(&item.image_path).unwrap();
    let e = l.item(0, 0).unwrap_err().to_string();
    assert!(e.contains(&item.image_path.display().to_string()), "{e}");
    // Another sample is unaffected.
    l.item(1, 0).unwrap();
    let one = l.item(1, 0).unwrap();
    let npz = walk(release.path())
        .into_iter()
        .find(|p| {
            p.to_string_lossy()
                .ends_with(&format!("{}_info.npz", one.key.img_id))
        })
        .unwrap();
    std::fs::write(&npz, b"not a zip").unwrap();
    let e = l.item(1, 0).unwrap_err().to_string();
    assert!(e.contains(&npz.display().to_string()), "{e}");
}

fn walk(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}
