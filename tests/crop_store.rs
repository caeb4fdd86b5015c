//! The crop store (`arkit-tool crops`, `crop_store`, `crops_dataset`): the loader's
//! items read from it against the same items decoded from the release, and every way a
//! store can be wrong refused with the file named.

mod support;

use arkit_tool::crop_store::{self, CropStore};
use arkit_tool::crops_dataset::write_crop_store;
use arkit_tool::dataset::Dataset;
use arkit_tool::loader::{Compat, FaceLoader, LoaderMode, LoaderOptions};
use std::path::Path;

const S: u32 = 96;

fn loader(dir: &Path, mode: LoaderMode, compat: Compat) -> FaceLoader {
    let options = LoaderOptions {
        split: None,
        mode,
        compat,
        img_size: S,
        n_pts: 128,
        seed: 9,
    };
    let topology = arkit_tool::synthetic_face::builtin().topology.clone();
    FaceLoader::open(dir, topology, None, options).unwrap()
}

/// The store of `dir` for `compat`, in its default folder.
fn store(dir: &Path, compat: Compat) -> std::path::PathBuf {
    let out = FaceLoader::default_crop_store(dir, compat, S);
    let summary = write_crop_store(&loader(dir, LoaderMode::Eval, compat), &out, &|_| {}).unwrap();
    assert_eq!(summary.missing, 0, "{:?}", summary.missing_examples);
    assert_eq!(
        summary.bytes,
        summary.samples as u64 * summary.bytes_per_sample
            + (dir_shards(dir) as u64) * crop_store::HEADER_BYTES
    );
    out
}

fn dir_shards(dir: &Path) -> usize {
    Dataset::open(dir).unwrap().shards().len()
}

#[test]
fn items_from_the_store_equal_items_from_the_release() {
    let (release, dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    support::converted::converted_synthetic(release.path(), dir.path(), 3, 3, 320, 41);
    for compat in [Compat::Exact, Compat::Official] {
        let out = store(dir.path(), compat);
        for mode in [LoaderMode::Eval, LoaderMode::Train] {
            let plain = loader(dir.path(), mode, compat);
            let mut stored = loader(dir.path(), mode, compat);
            stored.open_crop_store(&out).unwrap();
            assert!(stored.len() == 9 && plain.len() == 9);
            let mut served = 0;
            for i in 0..plain.len() {
                for epoch in [0, 3] {
                    let a = plain.item(i, epoch);
                    let b = stored.item(i, epoch);
                    let (a, b) = match (a, b) {
                        (Ok(a), Ok(b)) => (a, b),
                        (Err(x), Err(y)) => {
                            assert_eq!(x.to_string(), y.to_string());
                            continue;
                        }
                        (a, b) => panic!("{compat:?} {mode:?} {i}: {a:?} vs {b:?}"),
                    };
                    served += 1;
                    if mode == LoaderMode::Eval {
                        // Bit for bit, every field, the crop included.
                        assert_eq!(a, b, "{compat:?} eval item {i}");
                        continue;
                    }
                    // Training: the same box, mask, points, correspondences and mesh; the
                    // crop resampled from the window, within a grey level or two.
                    let img = a.img.clone();
                    let (mut a2, mut b2) = (a.clone(), b.clone());
                    a2.img.clear();
                    b2.img.clear();
                    assert_eq!(a2, b2, "{compat:?} train item {i} epoch {epoch}");
                    let grey = 1.0 / 255.0 / 0.229; // one grey level, normalised (largest std)
                    let mean = img
                        .iter()
                        .zip(&b.img)
                        .map(|(x, y)| (x - y).abs())
                        .sum::<f32>()
                        / img.len() as f32;
                    assert!(
                        mean < 2.0 * grey,
                        "{compat:?} item {i}: mean difference {mean}"
                    );
                    assert!(mean > 0.0, "the training crop is resampled from the window");
                }
            }
            assert!(served >= 12, "{compat:?} {mode:?}: {served} items served");
        }
    }
}

#[test]
fn a_damaged_stale_or_foreign_store_is_refused_naming_the_file() {
    let (release, dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    support::converted::converted_synthetic(release.path(), dir.path(), 2, 3, 256, 5);
    let out = store(dir.path(), Compat::Exact);
    let mut l = loader(dir.path(), LoaderMode::Eval, Compat::Exact);

    // Other rules or another size than the store's.
    let mut official = loader(dir.path(), LoaderMode::Eval, Compat::Official);
    let e = official.open_crop_store(&out).unwrap_err().to_string();
    assert!(
        e.contains("crops.json") && e.contains("compat is exact"),
        "{e}"
    );

    // Another dataset.
    let (release2, dir2) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    support::converted::converted_synthetic(release2.path(), dir2.path(), 2, 3, 256, 6);
    let mut other = loader(dir2.path(), LoaderMode::Eval, Compat::Exact);
    let e = other.open_crop_store(&out).unwrap_err().to_string();
    assert!(
        e.contains("crops.json") && e.contains("another dataset"),
        "{e}"
    );

    // A flipped byte: the record's CRC, naming the file, and only that sample.
    let part = out.join("part-0.bin");
    let mut bytes = std::fs::read(&part).unwrap();
    let record = crop_store::record_bytes(S, l.mesh_vertex_count());
    let at = (crop_store::HEADER_BYTES + record + 5000) as usize;
    bytes[at] ^= 0x10;
    std::fs::write(&part, &bytes).unwrap();
    l.open_crop_store(&out).unwrap();
    let e = l.item(1, 0).unwrap_err().to_string();
    assert!(e.contains("part-0.bin") && e.contains("CRC"), "{e}");
    assert!(l.item(0, 0).is_ok() && l.item(2, 0).is_ok());

    // A truncated file: refused when the store is opened.
    bytes.truncate(bytes.len() - 10);
    std::fs::write(&part, &bytes).unwrap();
    let e = CropStore::open(
        &out,
        &Dataset::open(dir.path()).unwrap(),
        "exact",
        S,
        l.mesh_vertex_count(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("part-0.bin") && e.contains("truncated"), "{e}");

    // No manifest: not a store.
    let e = l.open_crop_store(dir.path()).unwrap_err().to_string();
    assert!(e.contains("not a crop store"), "{e}");
}

#[test]
fn a_sample_without_an_image_is_stored_without_pixels_and_named() {
    let (release, dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    support::converted::converted_synthetic(release.path(), dir.path(), 2, 2, 256, 8);
    let plain = loader(dir.path(), LoaderMode::Eval, Compat::Exact);
    let gone = plain.item(2, 0).unwrap().image_path;
    std::fs::remove_file(&gone).unwrap();
    let out = FaceLoader::default_crop_store(dir.path(), Compat::Exact, S);
    let summary = write_crop_store(&plain, &out, &|_| {}).unwrap();
    assert_eq!((summary.samples, summary.missing), (4, 1));
    let name = gone.file_name().unwrap().to_string_lossy().into_owned();
    assert!(
        summary.missing_examples[0].contains(&name),
        "{:?}",
        summary.missing_examples
    );
    let mut l = loader(dir.path(), LoaderMode::Eval, Compat::Exact);
    l.open_crop_store(&out).unwrap();
    let e = l.item(2, 0).unwrap_err().to_string();
    assert!(e.contains("no pixels") && e.contains(&name), "{e}");
    for i in [0, 1, 3] {
        assert_eq!(l.item(i, 0).unwrap(), plain.item(i, 0).unwrap());
    }
}
