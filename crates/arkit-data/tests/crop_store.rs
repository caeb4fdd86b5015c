//! The crop store (`arkit-tool crops`, `crop_store`, `crops_dataset`): the loader's
//! items read from it against the same items decoded from the release, and every way a
//! store can be wrong (damaged, stale, another dataset's, parts swapped or mixed, an
//! earlier format) refused with the file named, in training as in evaluation; one
//! writer per store, and no temporaries of killed runs left after a rerun.

use arkit_data::crop::RuleSet;
use arkit_data::loader::{FaceLoader, LoaderMode, LoaderOptions};
use arkit_data::loader::{write_crop_store, write_crop_store_with};
use arkit_data::store::Dataset;
use arkit_data::store::crop_store::{self, CropStore, WindowCodec};
use std::path::Path;

const S: u32 = 96;

fn loader(dir: &Path, mode: LoaderMode, compat: RuleSet) -> FaceLoader {
    let options = LoaderOptions {
        split: None,
        mode,
        rules: compat,
        img_size: S,
        n_pts: 128,
        seed: 9,
    };
    let topology = arkit_data::mesh::builtin().topology.clone();
    FaceLoader::open(dir, topology, None, options).unwrap()
}

/// The store of `dir` for `compat`, in its default folder.
fn store(dir: &Path, compat: RuleSet) -> std::path::PathBuf {
    let out = FaceLoader::default_crop_store(dir, compat, S);
    let summary = write_crop_store(&loader(dir, LoaderMode::Eval, compat), &out, &|_| {}).unwrap();
    assert_eq!(summary.missing, 0, "{:?}", summary.missing_examples);
    let on_disk: u64 = (0..dir_shards(dir))
        .map(|k| {
            std::fs::metadata(out.join(format!("part-{k}.bin")))
                .unwrap()
                .len()
        })
        .sum();
    assert_eq!(summary.bytes, on_disk);
    assert_eq!(
        summary.bytes_per_sample,
        on_disk as f64 / summary.samples as f64
    );
    out
}

fn dir_shards(dir: &Path) -> usize {
    Dataset::open(dir).unwrap().shards().len()
}

#[test]
fn items_from_the_store_equal_items_from_the_release() {
    let (release, dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    crate::support::converted::converted_synthetic(release.path(), dir.path(), 3, 3, 320, 41);
    for compat in [RuleSet::Exact, RuleSet::Official] {
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
    crate::support::converted::converted_synthetic(release.path(), dir.path(), 2, 3, 256, 5);
    let out = store(dir.path(), RuleSet::Exact);
    let mut l = loader(dir.path(), LoaderMode::Eval, RuleSet::Exact);

    // Other rules or another size than the store's.
    let mut official = loader(dir.path(), LoaderMode::Eval, RuleSet::Official);
    let e = official.open_crop_store(&out).unwrap_err().to_string();
    assert!(
        e.contains("crops.json") && e.contains("compat is exact"),
        "{e}"
    );

    // Another dataset.
    let (release2, dir2) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    crate::support::converted::converted_synthetic(release2.path(), dir2.path(), 2, 3, 256, 6);
    let mut other = loader(dir2.path(), LoaderMode::Eval, RuleSet::Exact);
    let e = other.open_crop_store(&out).unwrap_err().to_string();
    assert!(
        e.contains("crops.json") && e.contains("another dataset"),
        "{e}"
    );

    // A flipped byte: the record's CRC, naming the file, and only that sample.
    let part = out.join("part-0.bin");
    let mut bytes = std::fs::read(&part).unwrap();
    let opened = CropStore::open(
        &out,
        &Dataset::open(dir.path()).unwrap(),
        RuleSet::Exact,
        S,
        l.mesh_vertex_count(),
    )
    .unwrap();
    let (at, len) = opened.record_span(0, 1).unwrap();
    bytes[(at + len / 2) as usize] ^= 0x10;
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
        RuleSet::Exact,
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
    crate::support::converted::converted_synthetic(release.path(), dir.path(), 2, 2, 256, 8);
    let plain = loader(dir.path(), LoaderMode::Eval, RuleSet::Exact);
    let gone = plain.item(2, 0).unwrap().image_path;
    std::fs::remove_file(&gone).unwrap();
    let out = FaceLoader::default_crop_store(dir.path(), RuleSet::Exact, S);
    let summary = write_crop_store(&plain, &out, &|_| {}).unwrap();
    assert_eq!((summary.samples, summary.missing), (4, 1));
    let name = gone.file_name().unwrap().to_string_lossy().into_owned();
    assert!(
        summary.missing_examples[0].contains(&name),
        "{:?}",
        summary.missing_examples
    );
    let mut l = loader(dir.path(), LoaderMode::Eval, RuleSet::Exact);
    l.open_crop_store(&out).unwrap();
    let e = l.item(2, 0).unwrap_err().to_string();
    assert!(e.contains("no pixels") && e.contains(&name), "{e}");
    for i in [0, 1, 3] {
        assert_eq!(l.item(i, 0).unwrap(), plain.item(i, 0).unwrap());
    }
}

/// Every item of `dir`'s loader in `mode`, from the store `out`: `Err` when the store is
/// refused at open, else each item's result as text (the error's, or the item's debug
/// form minus the image for training items, whose pixels are resampled).
fn served(dir: &Path, out: &Path, mode: LoaderMode) -> Result<Vec<String>, String> {
    let mut l = loader(dir, mode, RuleSet::Exact);
    l.open_crop_store(out).map_err(|e| e.to_string())?;
    Ok((0..l.len())
        .map(|i| match l.item(i, 2) {
            Ok(mut item) => {
                item.img.clear();
                format!("{item:?}")
            }
            Err(e) => format!("error: {e}"),
        })
        .collect())
}

/// The items of `dir`'s loader without a store, as [`served`] gives them.
fn plain_items(dir: &Path, mode: LoaderMode) -> Vec<String> {
    let l = loader(dir, mode, RuleSet::Exact);
    (0..l.len())
        .map(|i| {
            let mut item = l.item(i, 2).unwrap();
            item.img.clear();
            format!("{item:?}")
        })
        .collect()
}

#[test]
fn part_files_swapped_by_hand_are_refused_in_training_and_evaluation() {
    let (release, dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    // Two shards of four rows: part files of one size.
    crate::support::converted::converted_synthetic(release.path(), dir.path(), 2, 4, 256, 12);
    assert_eq!(dir_shards(dir.path()), 2);
    let out = store(dir.path(), RuleSet::Exact);
    let (p0, p1) = (out.join("part-0.bin"), out.join("part-1.bin"));
    let (b0, b1) = (std::fs::read(&p0).unwrap(), std::fs::read(&p1).unwrap());
    // Whole files swapped: each names the shard it holds.
    std::fs::write(&p0, &b1).unwrap();
    std::fs::write(&p1, &b0).unwrap();
    for mode in [LoaderMode::Train, LoaderMode::Eval] {
        let e = served(dir.path(), &out, mode).unwrap_err();
        assert!(
            e.contains("part-0.bin")
                && e.contains(
                    "holds the records of samples shard 1, but crops.json names it for shard 0"
                ),
            "{e}"
        );
    }
    // Part 1's records under part 0's header (a header check alone would pass): every
    // item of shard 0 refused in both modes, naming the sample it holds; shard 1's
    // (restored) items served as without the store.
    let h = crop_store::HEADER_BYTES as usize;
    let mut hybrid = b0[..h].to_vec();
    hybrid.extend_from_slice(&b1[h..]);
    std::fs::write(&p0, &hybrid).unwrap();
    std::fs::write(&p1, &b1).unwrap();
    let l = loader(dir.path(), LoaderMode::Eval, RuleSet::Exact);
    for mode in [LoaderMode::Train, LoaderMode::Eval] {
        let items = served(dir.path(), &out, mode).unwrap();
        let plain = plain_items(dir.path(), mode);
        assert_eq!(items.len(), 8);
        for (i, (item, plain)) in items.iter().zip(&plain).enumerate() {
            if i < 4 {
                let (want, _) = l.key(i).unwrap();
                let (holds, _) = l.key(i + 4).unwrap();
                assert!(
                    item.contains("part-0.bin")
                        && item.contains(&format!(
                            "should be sample {want}, but it holds sample {holds} (row {i} of shard 1)"
                        )),
                    "{mode:?} {i}: {item}"
                );
            } else {
                assert_eq!(item, plain, "{mode:?} {i}");
            }
        }
    }
}

#[test]
fn two_crops_into_one_store_never_mix() {
    // Two datasets of the same shape.
    let (ra, a) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let (rb, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    crate::support::converted::converted_synthetic(ra.path(), a.path(), 2, 4, 256, 21);
    crate::support::converted::converted_synthetic(rb.path(), b.path(), 2, 4, 256, 22);
    let out = tempfile::tempdir().unwrap();
    let out = out.path().join("store");
    let la = loader(a.path(), LoaderMode::Eval, RuleSet::Exact);
    let lb = loader(b.path(), LoaderMode::Eval, RuleSet::Exact);

    // While one run holds the store, a second (of another dataset) is refused at once
    // and writes nothing.
    let held = arkit_core::atomic_file::FolderLock::acquire(&out, "crops", "crops").unwrap();
    let e = write_crop_store(&lb, &out, &|_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("another crops is writing"), "{e}");
    assert!(!out.join("crops.json").exists() && !out.join("part-0.bin").exists());
    drop(held);

    // Both at once: whichever order they take, the store ends as one dataset's whole
    // store, and the other dataset's loader refuses it.
    let (res_a, res_b) = std::thread::scope(|s| {
        let x = s.spawn(|| write_crop_store(&la, &out, &|_| {}).map(|_| ()));
        let y = s.spawn(|| write_crop_store(&lb, &out, &|_| {}).map(|_| ()));
        (x.join().unwrap(), y.join().unwrap())
    });
    assert!(res_a.is_ok() || res_b.is_ok(), "{res_a:?} {res_b:?}");
    for r in [&res_a, &res_b] {
        if let Err(e) = r {
            assert!(e.to_string().contains("another crops is writing"), "{e}");
        }
    }
    let mut owners = 0;
    for dir in [a.path(), b.path()] {
        for mode in [LoaderMode::Train, LoaderMode::Eval] {
            match served(dir, &out, mode) {
                Ok(items) => {
                    assert_eq!(items, plain_items(dir, mode), "{mode:?}");
                    owners += 1;
                }
                Err(e) => assert!(e.contains("another dataset"), "{e}"),
            }
        }
    }
    assert_eq!(owners, 2, "one dataset's store, served in both modes");

    // What the unlocked runs of before left: the same folder holding a's crops.json
    // and one of b's parts. The part is refused by its header; b's records under a's
    // header are refused record by record, in both modes.
    write_crop_store(&la, &out, &|_| {}).unwrap();
    let bstore = tempfile::tempdir().unwrap();
    write_crop_store(&lb, bstore.path(), &|_| {}).unwrap();
    let theirs = std::fs::read(bstore.path().join("part-1.bin")).unwrap();
    let ours = std::fs::read(out.join("part-1.bin")).unwrap();
    std::fs::write(out.join("part-1.bin"), &theirs).unwrap();
    let e = served(a.path(), &out, LoaderMode::Train).unwrap_err();
    assert!(
        e.contains("part-1.bin") && e.contains("made from another dataset than crops.json says"),
        "{e}"
    );
    let h = crop_store::HEADER_BYTES as usize;
    let mut hybrid = ours[..h].to_vec();
    hybrid.extend_from_slice(&theirs[h..]);
    std::fs::write(out.join("part-1.bin"), &hybrid).unwrap();
    for mode in [LoaderMode::Train, LoaderMode::Eval] {
        let items = served(a.path(), &out, mode).unwrap();
        let plain = plain_items(a.path(), mode);
        assert_eq!(items[..4], plain[..4]);
        for item in &items[4..] {
            assert!(
                item.contains("part-1.bin") && item.contains("of another dataset (fingerprint"),
                "{mode:?}: {item}"
            );
        }
    }
}

#[test]
fn a_rerun_removes_killed_runs_temporaries_and_an_old_store_is_refused() {
    let (release, dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    crate::support::converted::converted_synthetic(release.path(), dir.path(), 2, 4, 256, 31);
    let out = FaceLoader::default_crop_store(dir.path(), RuleSet::Exact, S);
    std::fs::create_dir_all(&out).unwrap();
    // What a killed run leaves: its part under the temporary name (nobody holds it),
    // and a part of a shard the dataset no longer has.
    let stale = out.join(".part-0.bin.tmp-4242");
    std::fs::write(&stale, vec![7u8; 100_000]).unwrap();
    std::fs::write(out.join("part-7.bin"), b"old").unwrap();
    let kept = out.join("notes.txt");
    std::fs::write(&kept, b"mine").unwrap();
    store(dir.path(), RuleSet::Exact);
    let mut left: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    assert_eq!(
        left,
        [
            ".crops.lock",
            "crops.json",
            "notes.txt",
            "part-0.bin",
            "part-1.bin"
        ]
    );
    // A store of an earlier format (its crops.json says format 1, 2 or 3; a part of
    // format 3 under this format's manifest): refused with what to do, in Rust as in
    // Python.
    let manifest = out.join("crops.json");
    let text = std::fs::read_to_string(&manifest).unwrap();
    for format in [1, 2, 3] {
        let old = text.replacen(
            &format!("\"format\": {}", crop_store::FORMAT),
            &format!("\"format\": {format}"),
            1,
        );
        assert_ne!(old, text);
        std::fs::write(&manifest, old).unwrap();
        let e = served(dir.path(), &out, LoaderMode::Train).unwrap_err();
        assert!(
            e.contains("crops.json")
                && e.contains(&format!("format {format}"))
                && e.contains("rerun `arkit-tool crops`"),
            "{e}"
        );
    }
    std::fs::write(&manifest, &text).unwrap();
    let part = out.join("part-0.bin");
    let mut bytes = std::fs::read(&part).unwrap();
    assert_eq!(&bytes[..8], b"ARKCROP4");
    bytes[7] = b'3';
    std::fs::write(&part, &bytes).unwrap();
    let e = served(dir.path(), &out, LoaderMode::Eval).unwrap_err();
    assert!(
        e.contains("part-0.bin")
            && e.contains("store of format 3")
            && e.contains("rerun `arkit-tool crops`"),
        "{e}"
    );
}

#[test]
fn pred_zstd_png_and_raw_stores_serve_the_same_items_and_pred_zstd_is_smallest() {
    let (release, dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    crate::support::converted::converted_synthetic(release.path(), dir.path(), 2, 3, 320, 44);
    for compat in [RuleSet::Exact, RuleSet::Official] {
        let base = tempfile::tempdir().unwrap();
        let mut sizes = Vec::new();
        let mut items = Vec::new();
        for codec in [WindowCodec::Raw, WindowCodec::Png, WindowCodec::PredZstd] {
            let out = base.path().join(codec.name());
            let s = write_crop_store_with(
                &loader(dir.path(), LoaderMode::Eval, compat),
                &out,
                codec,
                &|_| {},
            )
            .unwrap();
            assert_eq!((s.missing, s.codec), (0, codec));
            assert_eq!(crop_store::read_manifest(&out).unwrap().codec, codec);
            sizes.push(s.bytes);
            for mode in [LoaderMode::Eval, LoaderMode::Train] {
                let mut l = loader(dir.path(), mode, compat);
                l.open_crop_store(&out).unwrap();
                let got: Vec<_> = (0..l.len()).map(|i| l.item(i, 1).unwrap()).collect();
                if mode == LoaderMode::Eval {
                    // Lossless: evaluation items equal the JPEG path's, bit for bit.
                    let plain = loader(dir.path(), mode, compat);
                    for (i, g) in got.iter().enumerate() {
                        assert_eq!(*g, plain.item(i, 1).unwrap(), "{codec:?} {i}");
                    }
                }
                items.push(got);
            }
        }
        // Training items too: the windows decoded are the same bytes.
        for k in [2, 4] {
            assert_eq!(items[0], items[k], "{compat:?} eval {k}");
            assert_eq!(items[1], items[k + 1], "{compat:?} train {k}");
        }
        assert!(
            sizes[2] < sizes[1] && sizes[1] * 2 < sizes[0],
            "{compat:?}: pred-zstd {} bytes, png {}, raw {}",
            sizes[2],
            sizes[1],
            sizes[0]
        );
    }
}
