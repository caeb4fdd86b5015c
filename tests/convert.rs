//! `convert`, `merge` and `split` on synthetic data and on every kind of broken input.

use crate::support::{convert_context as context, convert_options as options};
use arkit_core::conventions::{Camera, Pose};
use arkit_core::release::{self, ReleaseLayout, SampleKey, Split};
use arkit_core::{NpyArray, NpzCompression};
use arkit_data::ingest::synth::{self, FaceSource, SynthOptions};
use arkit_data::ingest::{self, ConvertOptions, HoldOut};
use arkit_data::store::{self, ERRORS_COLUMNS, SAMPLES_COLUMNS};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

fn make_release(dir: &Path, subjects: usize, images: usize) -> SynthOptions {
    let options = SynthOptions {
        subjects,
        images_per_subject: images,
        width: 128,
        height: 128,
        seed: 11,
        ..SynthOptions::default()
    };
    synth::generate(&FaceSource::builtin(), &options, dir, &|| {}).unwrap();
    options
}

fn run(opts: &ConvertOptions, threads: usize) -> arkit_data::store::Manifest {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| ingest::convert(opts, &context(), &|_| {}).unwrap())
}

fn files(root: &Path, sub: &str) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    if let Ok(rd) = std::fs::read_dir(root.join(sub)) {
        for e in rd.flatten() {
            out.insert(
                e.file_name().to_string_lossy().into_owned(),
                std::fs::read(e.path()).unwrap(),
            );
        }
    }
    out
}

/// A renderer for the built-in synthetic face with the release camera.
fn builtin_renderer() -> arkit_data::render::FaceRenderer {
    arkit_data::render::FaceRenderer::new(
        arkit_data::mesh::builtin().topology.clone(),
        Camera::release_projection(),
    )
    .unwrap()
}

fn keys_of(dir: &Path, split: Split) -> Vec<SampleKey> {
    release::read_list(&ReleaseLayout::new(dir).list_path(split))
        .unwrap()
        .into_iter()
        .map(|r| r.key)
        .collect()
}

#[test]
fn converts_synthetic_data_exactly_and_deterministically() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 3, 4);
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let m1 = run(&options(input.path(), a.path(), 5), 1);
    let m2 = run(&options(input.path(), b.path(), 5), 2);
    assert_eq!(
        (m1.converted, m1.skipped, m1.listing_problems, m1.listed),
        (12, 0, 0, 12)
    );
    assert_eq!(m1.shards.len(), 3);
    assert_eq!(
        files(a.path(), "samples"),
        files(b.path(), "samples"),
        "thread count changed the bytes"
    );
    assert_eq!(m1.shards, m2.shards);
    // Values equal the npz values exactly.
    let rows = ingest::read_dataset_samples(a.path()).unwrap();
    let layout = ReleaseLayout::new(input.path());
    let listed: Vec<SampleKey> = keys_of(input.path(), Split::Train)
        .into_iter()
        .chain(keys_of(input.path(), Split::Test))
        .collect();
    assert_eq!(
        rows.iter().map(|r| r.key.clone()).collect::<Vec<_>>(),
        listed,
        "list order kept"
    );
    for r in &rows {
        let split = if r.split == "train" {
            Split::Train
        } else {
            Split::Test
        };
        let info = release::read_info(&layout.info_path(split, &r.key)).unwrap();
        let flat: Vec<f32> = info.verts.iter().flat_map(|p| [p.x, p.y, p.z]).collect();
        assert_eq!(r.verts, flat);
        assert_eq!(r.rt, info.rt);
        let e = Pose::from_release_rt(&info.rt).unwrap().euler();
        assert_eq!(
            (r.yaw_deg, r.pitch_deg, r.roll_deg),
            (e.yaw_deg, e.pitch_deg, e.roll_deg)
        );
        assert_eq!((r.image_width, r.image_height), (128, 128));
        assert_eq!(r.landmarks_2d.len(), 136);
        // The crop box is square, contains every landmark, and is 1.5x their extent.
        let (us, vs): (Vec<f32>, Vec<f32>) = r.landmarks_2d.chunks(2).map(|c| (c[0], c[1])).unzip();
        let ext = (us.iter().cloned().fold(f32::MIN, f32::max)
            - us.iter().cloned().fold(f32::MAX, f32::min))
        .max(
            vs.iter().cloned().fold(f32::MIN, f32::max)
                - vs.iter().cloned().fold(f32::MAX, f32::min),
        );
        assert!(((r.face_box[2] - r.face_box[0]) - 1.5 * ext as f64).abs() < 1e-3);
        assert!(
            us.iter()
                .all(|&u| (u as f64) >= r.face_box[0] && (u as f64) <= r.face_box[2])
        );
    }
}

fn write_npz(path: &Path, members: Vec<(&str, NpyArray)>) {
    let refs: Vec<(&str, &NpyArray)> = members.iter().map(|(k, a)| (*k, a)).collect();
    let mut f = std::fs::File::create(path).unwrap();
    arkit_core::write_npz(&mut f, &refs, NpzCompression::Stored).unwrap();
}

#[test]
fn every_kind_of_broken_sample_is_reported_and_the_rest_converts() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 4, 4);
    let root = input.path();
    let layout = ReleaseLayout::new(root);
    let train = keys_of(root, Split::Train);
    assert!(train.len() >= 12);
    let info = |k: &SampleKey| layout.info_path(Split::Train, k);
    let image = |k: &SampleKey| layout.image_path(Split::Train, k);
    let good = release::read_info(&info(&train[0])).unwrap();
    let arrays = good.to_arrays();
    let get = |name: &str| arrays.iter().find(|(n, _)| *n == name).unwrap().1.clone();
    // 0: truncated npz.
    let bytes = std::fs::read(info(&train[0])).unwrap();
    std::fs::write(info(&train[0]), &bytes[..bytes.len() / 3]).unwrap();
    // 1: missing key.
    write_npz(&info(&train[1]), vec![("verts", get("verts"))]);
    // 2: verts of the wrong shape.
    write_npz(
        &info(&train[2]),
        vec![
            (
                "verts",
                NpyArray::from_f32(vec![1219, 3], vec![0.0; 3657]).unwrap(),
            ),
            ("R_t", get("R_t")),
        ],
    );
    // 3: NaN.
    let mut v = get("verts").to_f32_vec();
    v[7] = f32::NAN;
    write_npz(
        &info(&train[3]),
        vec![
            ("verts", NpyArray::from_f32(vec![1220, 3], v).unwrap()),
            ("R_t", get("R_t")),
        ],
    );
    // 4: positive tz.
    let mut rt = good.rt;
    rt[14] = 0.4;
    write_npz(
        &info(&train[4]),
        vec![
            ("verts", get("verts")),
            ("R_t", NpyArray::from_f64(vec![4, 4], rt.to_vec()).unwrap()),
        ],
    );
    // 5: missing image.
    std::fs::remove_file(image(&train[5])).unwrap();
    // 6: truncated JPEG.
    let jpg = std::fs::read(image(&train[6])).unwrap();
    std::fs::write(image(&train[6]), &jpg[..jpg.len() / 2]).unwrap();
    // 7: not a JPEG.
    std::fs::write(image(&train[7]), b"\x89PNG\r\n\x1a\n not really").unwrap();
    // 8: a list row with no files.
    let list = layout.list_path(Split::Train);
    let mut text = std::fs::read_to_string(&list).unwrap();
    text.push_str("099999,01_Neutral,1234567890123\n");
    std::fs::write(&list, text).unwrap();
    // An unlisted file on disk.
    let orphan = info(&train[8]).with_file_name("9999999999999_info.npz");
    std::fs::copy(info(&train[8]), &orphan).unwrap();

    let out = tempfile::tempdir().unwrap();
    let m = run(&options(root, out.path(), 4), 2);
    let listed = m.listed;
    assert_eq!(m.skipped, 9);
    assert_eq!(m.converted, listed - 9);
    assert_eq!(m.listing_problems, 1);
    let mut errors = Vec::new();
    for s in &m.shards {
        errors.extend(store::read_errors(&out.path().join(&s.errors_file)).unwrap());
    }
    let reason = |k: &SampleKey| {
        errors
            .iter()
            .find(|e| &e.key == k)
            .map(|e| e.reason.clone())
            .unwrap_or_else(|| panic!("{k} not in errors"))
    };
    assert!(reason(&train[0]).contains("zip"), "{}", reason(&train[0]));
    assert!(reason(&train[1]).contains("missing key 'R_t'"));
    assert!(reason(&train[2]).contains("[1220, 3]") && reason(&train[2]).contains("[1219, 3]"));
    assert!(reason(&train[3]).contains("non-finite"));
    assert!(reason(&train[4]).contains("negative"));
    assert!(reason(&train[5]).to_lowercase().contains("no such file"));
    assert!(reason(&train[6]).contains("truncated JPEG"));
    assert!(reason(&train[7]).contains("not a JPEG"));
    let ghost = SampleKey {
        subject_id: "099999".into(),
        facial_action: "01_Neutral".into(),
        img_id: "1234567890123".into(),
    };
    assert!(reason(&ghost).contains("No such file") || reason(&ghost).contains("no such file"));
    // Each error names the file at fault, relative to the input root.
    let e6 = errors.iter().find(|e| e.key == train[6]).unwrap();
    assert!(e6.file.starts_with("ARKitFace_image_train/image/") && e6.file.ends_with("_ar.jpg"));
    let listing = store::read_errors(&out.path().join("errors/listing.parquet")).unwrap();
    assert_eq!(listing.len(), 1);
    assert!(listing[0].file.ends_with("9999999999999_info.npz"));
    // Every other sample converted.
    let rows = ingest::read_dataset_samples(out.path()).unwrap();
    assert_eq!(rows.len(), listed - 9);
    assert!(rows.iter().any(|r| r.key == train[9]));
}

#[test]
fn resume_keeps_finished_shards_and_gives_the_same_bytes() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 2, 5);
    let out = tempfile::tempdir().unwrap();
    let first = run(&options(input.path(), out.path(), 3), 2);
    let before = files(out.path(), "samples");
    // Simulate an interruption: one shard lost, a stale temporary left behind.
    std::fs::remove_file(out.path().join("samples/part-00002.parquet")).unwrap();
    std::fs::write(
        out.path().join("samples/.part-00002.parquet.tmp-1"),
        b"half",
    )
    .unwrap();
    let second = run(&options(input.path(), out.path(), 3), 1);
    assert_eq!(first, second);
    let mut after = files(out.path(), "samples");
    after.retain(|k, _| !k.starts_with('.'));
    assert_eq!(before, after);
    // A finished shard from other input is refused, not silently mixed.
    let other = tempfile::tempdir().unwrap();
    make_release(other.path(), 3, 5);
    let e = ingest::convert(&options(other.path(), out.path(), 3), &context(), &|_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("other input"), "{e}");
}

#[test]
fn shard_parts_merge_to_the_single_run() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 3, 3);
    let single = tempfile::tempdir().unwrap();
    let whole = run(&options(input.path(), single.path(), 2), 2);
    let parts = tempfile::tempdir().unwrap();
    for i in 0..3 {
        let mut o = options(input.path(), parts.path(), 2);
        o.shard_index = i;
        o.shard_count = 3;
        run(&o, 1);
    }
    // Not all parts present yet? All three are; merge.
    let merged = ingest::merge(parts.path()).unwrap();
    assert!(merged.ignored.is_empty());
    let merged = merged.manifest;
    assert_eq!(merged.shards, whole.shards);
    assert_eq!(
        (merged.converted, merged.skipped),
        (whole.converted, whole.skipped)
    );
    assert_eq!(
        ingest::read_dataset_samples(parts.path()).unwrap(),
        ingest::read_dataset_samples(single.path()).unwrap()
    );
    // A missing part is named.
    std::fs::remove_file(parts.path().join(ingest::manifest_name(1, 3))).unwrap();
    let e = ingest::merge(parts.path()).unwrap_err().to_string();
    assert!(e.contains("part 1 of 3 is missing"), "{e}");
}

/// A `--shard I/2` conversion of 3 x 4 samples, 2 rows per shard, into a new folder.
fn two_parts(input: &Path) -> tempfile::TempDir {
    let parts = tempfile::tempdir().unwrap();
    for i in 0..2 {
        let mut o = options(input, parts.path(), 2);
        (o.shard_index, o.shard_count) = (i, 2);
        run(&o, 1);
    }
    parts
}

#[test]
fn merge_reads_only_the_parts_the_conversion_names() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 3, 4);
    let single = tempfile::tempdir().unwrap();
    let whole = run(&options(input.path(), single.path(), 2), 2);
    let parts = two_parts(input.path());
    let p = |name: &str| parts.path().join("manifest").join(name);
    // A copy of part 0 beside it (what a file manager makes): not read, listed; the
    // count is the distinct samples', as a single run's.
    std::fs::copy(
        p("part-0000-of-0002.json"),
        p("part-0000-of-0002 (copy).json"),
    )
    .unwrap();
    std::fs::copy(p("part-0001-of-0002.json"), p("part-1-of-2.json")).unwrap();
    let merged = ingest::merge(parts.path()).unwrap();
    assert_eq!(
        merged.ignored,
        vec![p("part-0000-of-0002 (copy).json"), p("part-1-of-2.json")]
    );
    assert_eq!(merged.manifest.shards, whole.shards);
    assert_eq!(merged.manifest.converted, whole.converted);
    assert_eq!(merged.manifest.converted, 12);
    // A copy under another part's canonical name (of another split count): refused,
    // never a guess.
    std::fs::copy(p("part-0000-of-0002.json"), p("part-0002-of-0003.json")).unwrap();
    let e = ingest::merge(parts.path()).unwrap_err().to_string();
    assert!(e.contains("split 2 and 3 ways"), "{e}");
    std::fs::remove_file(p("part-0002-of-0003.json")).unwrap();
    // Part 0's manifest copied over part 1's: it says it is part 0.
    let part1 = std::fs::read(p("part-0001-of-0002.json")).unwrap();
    std::fs::copy(p("part-0000-of-0002.json"), p("part-0001-of-0002.json")).unwrap();
    let e = ingest::merge(parts.path()).unwrap_err().to_string();
    assert!(
        e.contains("part-0001-of-0002.json") && e.contains("says it is part 0 of 2"),
        "{e}"
    );
    // A part that lists a shard twice, or drops one.
    let mut m: arkit_data::store::Manifest = serde_json::from_slice(&part1).unwrap();
    let write = |m: &arkit_data::store::Manifest| {
        std::fs::write(p("part-0001-of-0002.json"), serde_json::to_vec(m).unwrap()).unwrap()
    };
    let kept = m.shards.clone();
    m.shards.push(m.shards[0].clone());
    write(&m);
    let e = ingest::merge(parts.path()).unwrap_err().to_string();
    assert!(e.contains("shard index 1 listed twice"), "{e}");
    m.shards = kept[1..].to_vec();
    write(&m);
    let e = ingest::merge(parts.path()).unwrap_err().to_string();
    assert!(e.contains("does not list shard 1"), "{e}");
    // A part of another conversion (its fingerprint is not conversion.json's).
    m.shards = kept;
    m.fingerprint = "0".repeat(64);
    write(&m);
    let e = ingest::merge(parts.path()).unwrap_err().to_string();
    assert!(
        e.contains("another conversion than the one conversion.json records"),
        "{e}"
    );
    std::fs::write(p("part-0001-of-0002.json"), &part1).unwrap();
    assert_eq!(ingest::merge(parts.path()).unwrap().manifest.converted, 12);
}

#[test]
fn merge_refuses_a_sample_key_in_two_shards() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 3, 4);
    let parts = two_parts(input.path());
    // Shard 3 (part 1) rewritten with shard 0's rows, and its part manifest updated to
    // match the new file: every file agrees with its record, yet two shards hold the
    // same samples.
    let part = parts.path().join(ingest::manifest_name(1, 2));
    let mut m = arkit_data::store::read_manifest(&part).unwrap();
    let shard0 = parts.path().join("samples/part-00000.parquet");
    let rows = store::read_samples(&shard0).unwrap();
    let entry = m.shards.iter_mut().find(|s| s.index == 3).unwrap();
    let path = parts.path().join(&entry.samples_file);
    store::write_samples(&path, &rows, context().topology.vertex_count).unwrap();
    entry.rows = rows.len();
    entry.bytes = std::fs::metadata(&path).unwrap().len();
    entry.sha256 = arkit_data::store::sha256_file(&path).unwrap();
    entry.tail_sha256 = arkit_data::store::tail_sha256(&path).unwrap();
    std::fs::write(&part, serde_json::to_vec(&m).unwrap()).unwrap();
    let e = ingest::merge(parts.path()).unwrap_err().to_string();
    assert!(
        e.contains("part-00003.parquet")
            && e.contains(&format!(
                "sample {} is in shard 0 and again in shard 3",
                rows[0].key
            )),
        "{e}"
    );
    assert!(!parts.path().join("dataset.json").exists());
}

#[test]
fn flat_layout_is_discovered() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 2, 2);
    let flat = tempfile::tempdir().unwrap();
    let root = input.path();
    // Move train files into image/ and info/ with one CSV.
    for kind in ["image", "info"] {
        std::fs::rename(
            root.join(format!("ARKitFace_{kind}_train")).join(kind),
            flat.path().join(kind),
        )
        .unwrap();
    }
    std::fs::copy(
        ReleaseLayout::new(root).list_path(Split::Train),
        flat.path().join("list.csv"),
    )
    .unwrap();
    let d = ingest::discover(flat.path()).unwrap();
    assert_eq!(d.kind, arkit_data::store::LayoutKind::Flat);
    let out = tempfile::tempdir().unwrap();
    let m = run(&options(flat.path(), out.path(), 10), 1);
    assert_eq!((m.converted, m.skipped), (m.listed, 0));
    let e = ingest::discover(out.path()).unwrap_err().to_string();
    assert!(e.contains("not an ARKitFace release"), "{e}");
}

#[test]
fn written_tables_match_the_schema_files() {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("schemas");
    for (file, spec) in [
        ("samples.json", &SAMPLES_COLUMNS[..]),
        ("errors.json", &ERRORS_COLUMNS[..]),
    ] {
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join(file)).unwrap()).unwrap();
        let cols: Vec<(String, String)> = v["columns"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| {
                (
                    c["name"].as_str().unwrap().to_string(),
                    c["type"].as_str().unwrap().to_string(),
                )
            })
            .collect();
        let code: Vec<(String, String)> = spec
            .iter()
            .map(|c| (c.name.to_string(), c.dtype.to_string()))
            .collect();
        assert_eq!(cols, code, "{file} and the code disagree");
    }
    // What convert writes has exactly these columns and types.
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 2, 1);
    let out = tempfile::tempdir().unwrap();
    let m = run(&options(input.path(), out.path(), 10), 1);
    for (path, spec) in [
        (&m.shards[0].samples_file, &SAMPLES_COLUMNS[..]),
        (&m.shards[0].errors_file, &ERRORS_COLUMNS[..]),
    ] {
        let df = store::read_parquet(&out.path().join(path)).unwrap();
        let got: Vec<(String, String)> = df
            .schema()
            .iter()
            .map(|(n, t)| (n.to_string(), format!("{t:?}")))
            .collect();
        let want: Vec<(String, String)> = spec
            .iter()
            .map(|c| {
                (
                    c.name.to_string(),
                    format!("{:?}", store::polars_dtype_with(c.dtype, 1220).unwrap()),
                )
            })
            .collect();
        assert_eq!(got, want);
    }
}

#[test]
fn samples_have_fixed_shapes_recorded_for_datasets_and_old_files_still_read() {
    use polars::prelude::{DataType, NamedFrom};
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 2, 2);
    let out = tempfile::tempdir().unwrap();
    let m = run(&options(input.path(), out.path(), 10), 1);
    let file = out.path().join(&m.shards[0].samples_file);
    // Fixed-size lists of fixed-size lists, with the right widths.
    let df = store::read_parquet(&file).unwrap();
    let shape = |name: &str| match df.column(name).unwrap().dtype() {
        DataType::Array(row, outer) => match row.as_ref() {
            DataType::Array(leaf, inner) => (leaf.as_ref().clone(), *outer, *inner),
            t => panic!("{name}: {t:?}"),
        },
        t => panic!("{name}: {t:?}"),
    };
    assert_eq!(shape("verts"), (DataType::Float32, 1220, 3));
    assert_eq!(shape("R_t"), (DataType::Float64, 4, 4));
    assert_eq!(shape("landmarks_2d"), (DataType::Float32, 68, 2));
    // The `huggingface` record: Array2D features with these shapes, Value features for
    // every other column, all columns in order.
    let kv = store::parquet_key_value_metadata(&file).unwrap();
    let hf = kv.iter().find(|(k, _)| k == "huggingface").unwrap();
    let v: serde_json::Value = serde_json::from_str(hf.1.as_deref().unwrap()).unwrap();
    let features = v["info"]["features"].as_object().unwrap();
    assert_eq!(features.len(), SAMPLES_COLUMNS.len());
    for c in &SAMPLES_COLUMNS {
        let f = &features[c.name];
        match c.name {
            "verts" | "R_t" | "landmarks_2d" => assert_eq!(f["_type"], "Array2D", "{}", c.name),
            _ => {
                assert_eq!(f["_type"], "Value", "{}", c.name);
                assert_eq!(f["dtype"], c.dtype, "{}", c.name);
            }
        }
    }
    assert_eq!(features["verts"]["shape"], serde_json::json!([1220, 3]));
    assert_eq!(features["verts"]["dtype"], "float32");
    assert_eq!(features["R_t"]["shape"], serde_json::json!([4, 4]));
    assert_eq!(features["R_t"]["dtype"], "float64");
    assert_eq!(
        features["landmarks_2d"]["shape"],
        serde_json::json!([68, 2])
    );
    let shapes = store::huggingface_shapes(&file).unwrap().unwrap();
    assert_eq!(
        shapes,
        vec![
            ("R_t".to_string(), [4, 4]),
            ("landmarks_2d".to_string(), [68, 2]),
            ("verts".to_string(), [1220, 3]),
        ]
    );
    // Arrow readers (pyarrow, so `datasets`) take schema metadata from `ARROW:schema`:
    // it carries both records too, and without them it is exactly what polars writes.
    let arrow = kv.iter().find(|(k, _)| k == "ARROW:schema").unwrap();
    let with_meta = store::arrow_schema_value(&df, &store::huggingface_metadata(1220));
    assert_eq!(arrow.1.as_deref(), Some(with_meta.as_str()));
    let plain = out.path().join("plain.parquet");
    store::write_parquet(&plain, &mut df.clone()).unwrap();
    let polars_own = store::parquet_key_value_metadata(&plain).unwrap();
    assert_eq!(
        polars_own,
        vec![(
            "ARROW:schema".to_string(),
            Some(store::arrow_schema_value(&df, &[]))
        )]
    );
    let ours = kv.iter().find(|(k, _)| k == "arkit_tool").unwrap();
    let ours: serde_json::Value = serde_json::from_str(ours.1.as_deref().unwrap()).unwrap();
    assert_eq!(ours["samples_format"], store::SAMPLES_FORMAT);
    // What was written reads back, with the topology's N or without it; another N is
    // refused, naming the file and the column.
    let rows = store::read_samples(&file).unwrap();
    assert!(rows.len() >= 2 && rows.len() == m.converted);
    assert!(
        rows.iter()
            .all(|r| r.verts.len() == 3660 && r.landmarks_2d.len() == 136)
    );
    assert_eq!(
        store::read_samples_expecting(&file, Some(1220)).unwrap(),
        rows
    );
    let e = store::read_samples_expecting(&file, Some(1219))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(&file.display().to_string()) && e.contains("'verts'"),
        "{e}"
    );
    // A file written before (variable-length lists, no metadata) reads as the same rows.
    let old = out.path().join("old.parquet");
    store::write_parquet(&old, &mut store::samples_frame_format1(&rows).unwrap()).unwrap();
    assert_eq!(
        store::read_parquet(&old).unwrap()["verts"].dtype(),
        &DataType::List(Box::new(DataType::Float32))
    );
    assert!(store::huggingface_shapes(&old).unwrap().is_none());
    assert_eq!(store::read_samples(&old).unwrap(), rows);
    // ... and its widths are checked as well: a row of another N than the others, an R_t
    // of 15 numbers, each name the file and the column.
    for (k, column) in [(0, "verts"), (1, "R_t")] {
        let mut broken = rows.clone();
        if k == 0 {
            broken[1].verts.truncate(3 * 1219);
        }
        let mut df = store::samples_frame_format1(&broken).unwrap();
        if k == 1 {
            let short: Vec<polars::prelude::Series> = broken
                .iter()
                .map(|r| polars::prelude::Series::new("".into(), &r.rt[..15]))
                .collect();
            df.replace("R_t", polars::prelude::Column::new("R_t".into(), short))
                .unwrap();
        }
        store::write_parquet(&old, &mut df).unwrap();
        let e = store::read_samples(&old).unwrap_err().to_string();
        assert!(
            e.contains(&old.display().to_string()) && e.contains(&format!("column '{column}'")),
            "{e}"
        );
    }
    // An empty shard still has the shapes.
    let empty = out.path().join("empty.parquet");
    store::write_samples(&empty, &[], 1220).unwrap();
    assert_eq!(
        store::read_parquet(&empty).unwrap()["verts"].dtype(),
        &store::polars_dtype_with("float32[N,3]", 1220).unwrap()
    );
    assert!(store::read_samples(&empty).unwrap().is_empty());
    // A file whose metadata and column disagree is refused.
    let lying = out.path().join("lying.parquet");
    store::write_parquet_with_metadata(
        &lying,
        &mut store::samples_frame(&rows, 1220).unwrap(),
        store::huggingface_metadata(1000),
    )
    .unwrap();
    let e = store::read_samples(&lying).unwrap_err().to_string();
    assert!(e.contains("lying.parquet") && e.contains("'verts'"), "{e}");
}

#[test]
fn split_is_subject_disjoint_and_reproducible() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 6, 2);
    let out = tempfile::tempdir().unwrap();
    run(&options(input.path(), out.path(), 100), 2);
    let rows = ingest::read_dataset_samples(out.path()).unwrap();
    let mut per: BTreeMap<String, usize> = BTreeMap::new();
    for r in &rows {
        *per.entry(r.key.subject_id.clone()).or_default() += 1;
    }
    let a = ingest::assign(&per, HoldOut::Subjects(2), 1, 5).unwrap();
    assert_eq!(a, ingest::assign(&per, HoldOut::Subjects(2), 1, 5).unwrap());
    let c = a.counts(&per);
    assert_eq!((c["train"].0, c["test"].0, c["val"].0), (3, 2, 1));
}

#[test]
fn rendered_targets_read_back_dense_equal_the_rasterizer() {
    use arkit_data::crop::CropTransform;
    use arkit_data::render::RenderOptions;
    use arkit_data::store;
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 2, 3);
    let out = tempfile::tempdir().unwrap();
    run(&options(input.path(), out.path(), 4), 2);
    let renderer = builtin_renderer();
    let ro = RenderOptions {
        size: 96,
        uv_size: 64,
        points: 256,
        seed: 3,
        shard: (0, 1),
        full_mask: true,
        output: out.path().to_path_buf(),
    };
    let summary = arkit_data::render::render_dataset(out.path(), &renderer, &ro, &|_| {}).unwrap();
    assert_eq!(summary.samples, 6);
    let samples = ingest::read_dataset_samples(out.path()).unwrap();
    let mut targets = Vec::new();
    for k in 0..2 {
        targets.extend(
            store::read_targets(&out.path().join(format!("targets/part-{k:05}.parquet"))).unwrap(),
        );
    }
    assert_eq!(targets.len(), 6);
    // The written table has exactly the columns and types of schemas/targets.json.
    let schema: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("schemas/targets.json"),
        )
        .unwrap(),
    )
    .unwrap();
    let want: Vec<(String, String)> = schema["columns"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            let name = c["name"].as_str().unwrap().to_string();
            (name, c["type"].as_str().unwrap().to_lowercase())
        })
        .collect();
    let df = store::read_parquet(&out.path().join("targets/part-00000.parquet")).unwrap();
    let got: Vec<(String, String)> = df
        .schema()
        .iter()
        .map(|(n, t)| (n.to_string(), format!("{t:?}").to_lowercase()))
        .collect();
    assert_eq!(
        got, want,
        "schemas/targets.json and the written table disagree"
    );
    // A file written before the crop_side_y and crop_sampling columns (2026-11-30)
    // reads as a square box sampled at pixel centres: the same records.
    let mut old = df
        .drop("crop_side_y")
        .unwrap()
        .drop("crop_sampling")
        .unwrap();
    let old_path = out.path().join("old-targets.parquet");
    store::write_parquet(&old_path, &mut old).unwrap();
    let first = store::read_targets(&out.path().join("targets/part-00000.parquet")).unwrap();
    assert_eq!(store::read_targets(&old_path).unwrap(), first);
    let mut vb = arkit_core::VisibilityBuffer::new(96, 96);
    for (s, t) in samples.iter().zip(&targets) {
        assert_eq!(s.key, t.key);
        let verts: Vec<nalgebra::Point3<f32>> = s
            .verts
            .chunks(3)
            .map(|c| nalgebra::Point3::new(c[0], c[1], c[2]))
            .collect();
        let pose = Pose::from_release_rt(&s.rt).unwrap();
        let crop = CropTransform::around_landmarks(&s.landmarks_2d, 96);
        let direct = renderer
            .render(&verts, &pose, s.image_width, s.image_height, &crop, &mut vb)
            .unwrap();
        let d = store::dense(t, &verts).unwrap();
        // The mask and the correspondence rows match the rasterizer's, within the
        // stated quantisation error.
        assert_eq!(
            d.mask.iter().map(|&m| m == 1).collect::<Vec<_>>(),
            direct.mask
        );
        let pixels = direct.mask_pixels();
        assert_eq!(d.chosen_pixels.len(), 256);
        for (row, &p) in t.points.iter().enumerate() {
            assert_eq!(d.chosen_pixels[row], pixels[p as usize]);
            let ids = direct.corr_vertices[p as usize];
            let w = direct.corr_weights[p as usize];
            for k in 0..3 {
                let stored = d.corr_matrix[row * 1220 + ids[k] as usize];
                assert!(
                    (stored - w[k]).abs() <= 2.0 * store::WEIGHT_QUANTUM,
                    "{stored} vs {}",
                    w[k]
                );
            }
            assert!(
                (d.corr_matrix[row * 1220..(row + 1) * 1220]
                    .iter()
                    .sum::<f32>()
                    - 1.0)
                    .abs()
                    < 1e-5
            );
        }
        // The full-image mask is the rasterizer's over the whole image, and it agrees
        // with the crop mask: the crop's face pixels look at face pixels of the image,
        // and the areas scale with the crop (both within the pixels along the outline).
        let mut full_vb = arkit_core::VisibilityBuffer::new(1, 1);
        let full = t.full_mask().unwrap().expect("rendered with full_mask");
        assert_eq!(
            full,
            renderer
                .render_full_mask(&verts, &pose, s.image_width, s.image_height, &mut full_vb)
                .unwrap()
        );
        let (w, h) = (s.image_width as usize, s.image_height as usize);
        assert_eq!(full.len(), w * h);
        // Every crop face pixel looks at a face pixel of the image or at one next to
        // it (they differ only along the outline, where the two grids sample it apart).
        let near_face = |u: f64, v: f64| {
            let (x, y) = (u as i64, v as i64);
            (-1..=1).any(|dy| {
                (-1..=1).any(|dx| {
                    let (xx, yy) = (x + dx, y + dy);
                    (0..w as i64).contains(&xx)
                        && (0..h as i64).contains(&yy)
                        && full[yy as usize * w + xx as usize]
                })
            })
        };
        for &p in &pixels {
            let (u, v) = crop.to_image((p % 96) as f64 + 0.5, (p / 96) as f64 + 0.5);
            assert!(near_face(u, v), "crop pixel {p} at ({u}, {v})");
        }
        let full_area = full.iter().filter(|&&m| m).count() as f64;
        let scaled = pixels.len() as f64 * (crop.side / 96.0).powi(2);
        assert!(
            (full_area / scaled - 1.0).abs() < 0.03,
            "{full_area} vs {scaled}"
        );
        // UV map: float16 of the direct map.
        let uv = arkit_data::render::UvMapper::derive(renderer.topology())
            .unwrap()
            .position_map(&verts, 64);
        for (a, b) in d.uv_map.chunks(3).zip(&uv) {
            for k in 0..3 {
                assert!(
                    (a[k].is_nan() && b[k].is_nan()) || (a[k] - b[k]).abs() <= 3.06e-5,
                    "{} {}",
                    a[k],
                    b[k]
                );
            }
        }
    }
    // A rerun keeps the shards.
    let again = arkit_data::render::render_dataset(out.path(), &renderer, &ro, &|_| {}).unwrap();
    assert_eq!(again.bytes, summary.bytes);
}

#[test]
fn render_reports_and_skips_a_sample_it_cannot_render() {
    use arkit_data::render::RenderOptions;
    use arkit_data::store;
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 2, 3);
    let out = tempfile::tempdir().unwrap();
    let manifest = run(&options(input.path(), out.path(), 4), 2);
    // Break one converted sample after the fact: a rotation scaled by 2 (convert would
    // have refused it), in the first shard.
    let shard0 = out.path().join(&manifest.shards[0].samples_file);
    let mut rows = store::read_samples(&shard0).unwrap();
    let broken = rows[1].key.clone();
    for i in [0, 1, 2, 4, 5, 6, 8, 9, 10] {
        rows[1].rt[i] *= 2.0;
    }
    store::write_samples(&shard0, &rows, 1220).unwrap();
    // Readers refuse a shard that differs from the manifest; this test wants the broken
    // row read, as if convert had written it, so the manifest forgets the shard's size.
    let mut m = arkit_data::store::read_manifest(&out.path().join("dataset.json")).unwrap();
    m.shards[0].bytes = 0;
    std::fs::write(
        out.path().join("dataset.json"),
        serde_json::to_string_pretty(&m).unwrap(),
    )
    .unwrap();
    let renderer = builtin_renderer();
    let ro = RenderOptions {
        size: 64,
        uv_size: 32,
        points: 64,
        seed: 3,
        shard: (0, 1),
        full_mask: false,
        output: out.path().to_path_buf(),
    };
    let summary = arkit_data::render::render_dataset(out.path(), &renderer, &ro, &|_| {}).unwrap();
    // The run finished: the other five samples have targets, the broken one a reason.
    assert_eq!((summary.samples, summary.skipped), (6, 1));
    assert!(
        summary.skipped_examples[0].contains("R_t"),
        "{:?}",
        summary.skipped_examples
    );
    let t0 = store::read_targets_by_key(&store::shard_path(out.path(), 0)).unwrap();
    assert_eq!(t0.len(), rows.len() - 1);
    assert!(!t0.contains_key(&broken));
    let errors = store::read_errors(&store::errors_path(out.path(), 0)).unwrap();
    assert_eq!(errors.len(), 1);
    assert_eq!(errors[0].key, broken);
    assert_eq!(errors[0].file, manifest.shards[0].samples_file);
    assert!(errors[0].reason.contains("R_t"), "{}", errors[0].reason);
    let skipped = store::read_skipped_keys(out.path(), 0).unwrap();
    assert_eq!(
        skipped.into_iter().collect::<Vec<_>>(),
        vec![broken.clone()]
    );
    // Training reads the other five and leaves the skipped one out (without the
    // errors file it would stop at the missing row).
    let cfg = arkit_perspnet::PerspNetConfig {
        points: 64,
        ..arkit_perspnet::PerspNetConfig::tiny()
    };
    let examples = arkit_perspnet::read_examples(out.path(), out.path(), &cfg, None).unwrap();
    assert_eq!(examples.len(), 5);
    assert!(examples.iter().all(|e| e.sample.key != broken));
    // predict --mask truth leaves it out too (a one-step model is enough to run it).
    let model_dir = tempfile::tempdir().unwrap();
    let topts = arkit_perspnet::TrainOptions {
        config: cfg,
        epochs: 1,
        max_steps: Some(1),
        batch: 5,
        learning_rate: 1e-3,
        lr_hold: 1.0,
        augmentation: arkit_perspnet::Augmentation::NONE,
        lowered_start: false,
        seed: 1,
        output: model_dir.path().to_path_buf(),
        resume: false,
    };
    let topology = arkit_data::mesh::builtin().topology.clone();
    arkit_perspnet::train(&examples, &topology, &topts, &|_| {}).unwrap();
    let model = arkit_perspnet::load(model_dir.path(), &topology).unwrap();
    let (preds, ps) = arkit_perspnet::model_predictions(
        out.path(),
        &model,
        None,
        arkit_data::crop::RuleSet::Exact,
        Some(out.path()),
        1,
        &arkit_data::pose::RansacParams::default(),
        &|_| {},
    )
    .unwrap();
    assert_eq!((ps.samples, ps.without_true_mask), (5, 1));
    assert_eq!(preds.len(), 5);
    assert!(preds.iter().all(|p| p.key != broken));
    // The second shard's errors file is there and empty.
    let e1 = store::read_errors(&store::errors_path(out.path(), 1)).unwrap();
    assert!(e1.is_empty());
    // A rerun counts the shard as finished (targets + errors = its rows) and keeps it.
    let before = std::fs::read(store::shard_path(out.path(), 0)).unwrap();
    let again = arkit_data::render::render_dataset(out.path(), &renderer, &ro, &|_| {}).unwrap();
    assert_eq!((again.skipped, again.bytes), (1, summary.bytes));
    assert_eq!(
        std::fs::read(store::shard_path(out.path(), 0)).unwrap(),
        before
    );
    // Without its errors file the shard is not finished: rendered again, same bytes.
    std::fs::remove_file(store::errors_path(out.path(), 0)).unwrap();
    let third = arkit_data::render::render_dataset(out.path(), &renderer, &ro, &|_| {}).unwrap();
    assert_eq!(third.skipped, 1);
    assert_eq!(
        std::fs::read(store::shard_path(out.path(), 0)).unwrap(),
        before
    );
}

#[test]
#[cfg(feature = "model")]
fn training_streams_shard_by_shard() {
    use arkit_data::render::RenderOptions;
    use arkit_perspnet::PerspNetConfig;
    use arkit_perspnet::{ExampleShards, ShardedExamples, TrainOptions};
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 2, 3);
    let topology = arkit_data::mesh::builtin().topology.clone();
    let cfg = PerspNetConfig {
        points: 32,
        ..PerspNetConfig::tiny()
    };
    // The same six samples in two shards (4 + 2) and in one.
    let dataset = |rows: usize| {
        let out = tempfile::tempdir().unwrap();
        run(&options(input.path(), out.path(), rows), 1);
        let ro = RenderOptions {
            size: 64,
            uv_size: 32,
            points: 32,
            seed: 3,
            shard: (0, 1),
            full_mask: false,
            output: out.path().to_path_buf(),
        };
        arkit_data::render::render_dataset(out.path(), &builtin_renderer(), &ro, &|_| {}).unwrap();
        out
    };
    let (two, one) = (dataset(4), dataset(100));
    let source = ShardedExamples::open(two.path(), two.path(), &cfg, None).unwrap();
    assert_eq!(
        (source.shards(), source.shard_len(0), source.shard_len(1)),
        (2, 4, 2)
    );
    // read_examples is the shards' examples one after the other.
    let all = arkit_perspnet::read_examples(two.path(), two.path(), &cfg, None).unwrap();
    let keys =
        |e: &[arkit_perspnet::Example]| e.iter().map(|e| e.sample.key.clone()).collect::<Vec<_>>();
    let mut loaded = keys(&source.load(0).unwrap());
    loaded.extend(keys(&source.load(1).unwrap()));
    assert_eq!(loaded, keys(&all));
    // A split's counts (from the keys alone) agree with what loading gives.
    for split in ["train", "test"] {
        let part = ShardedExamples::open(two.path(), two.path(), &cfg, Some(split)).unwrap();
        let read =
            arkit_perspnet::read_examples(two.path(), two.path(), &cfg, Some(split)).unwrap();
        assert_eq!(part.total(), read.len(), "{split}");
        assert!((1..6).contains(&read.len()), "{split}: {}", read.len());
        assert!(read.iter().all(|e| e.sample.split == split));
    }
    let out = tempfile::tempdir().unwrap();
    let topts = TrainOptions {
        config: cfg.clone(),
        epochs: 2,
        max_steps: None,
        batch: 3,
        learning_rate: 1e-3,
        lr_hold: 0.5,
        augmentation: arkit_perspnet::Augmentation::NONE,
        lowered_start: false,
        seed: 4,
        output: out.path().to_path_buf(),
        resume: false,
    };
    // Per epoch: ceil(4 / 3) + ceil(2 / 3) = 3 steps (a batch never spans two shards).
    let (ck, log) = arkit_perspnet::train(&source, &topology, &topts, &|_| {}).unwrap();
    assert_eq!((ck.steps, ck.example_shards, ck.examples), (6, 2, 6));
    assert_eq!(arkit_perspnet::steps_per_epoch(&source, 3), 3);
    // Interrupted after the first epoch and resumed: the replayed shard and sample
    // orders give the uninterrupted run's losses.
    let cut = tempfile::tempdir().unwrap();
    let cut_opts = TrainOptions {
        output: cut.path().to_path_buf(),
        ..topts.clone()
    };
    let stopped = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        arkit_perspnet::train(&source, &topology, &cut_opts, &|s| {
            assert!(s.step < 3, "stop")
        })
    }));
    assert!(stopped.is_err());
    let resumed = TrainOptions {
        resume: true,
        ..cut_opts
    };
    let (_, rlog) = arkit_perspnet::train(&source, &topology, &resumed, &|_| {}).unwrap();
    let totals = |l: &[arkit_perspnet::StepLoss]| l.iter().map(|s| s.total).collect::<Vec<_>>();
    assert_eq!(totals(&rlog), totals(&log));
    // Resuming that checkpoint with all examples in memory (another order) is refused.
    let e = match arkit_perspnet::train(&all, &topology, &resumed, &|_| {}) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("resumed a streamed run in memory"),
    };
    assert!(e.contains("other settings"), "{e}");
    // With one shard, streaming is the in-memory run exactly.
    let single = ShardedExamples::open(one.path(), one.path(), &cfg, None).unwrap();
    assert_eq!(single.shards(), 1);
    let in_memory = arkit_perspnet::read_examples(one.path(), one.path(), &cfg, None).unwrap();
    let run_on = |s: &dyn ExampleShards| {
        let o = tempfile::tempdir().unwrap();
        let opts = TrainOptions {
            output: o.path().to_path_buf(),
            ..topts.clone()
        };
        totals(
            &arkit_perspnet::train(s, &topology, &opts, &|_| {})
                .unwrap()
                .1,
        )
    };
    assert_eq!(run_on(&single), run_on(&in_memory));
}
