//! Writes the seed corpus of arkit-data's fuzz targets (`fuzz/corpus/<target>/`) from
//! the files the tool wrote in `WORK` (`fuzz/make_data_seeds.sh` makes them and runs
//! this): each valid file as it is, then truncated, bit-flipped and hostile variants.
//!
//! Usage: `data_fuzz_seeds WORK CORPUS`, where `WORK` holds `pq/` (a dataset converted in
//! shards of one row), `parts/` (the same as two `--shard I/2` parts) and
//! `crops-<codec>/` (a crop store of side 16 per codec).

use arkit_data::fuzz_entry::container;
use arkit_data::store::Dataset;
use arkit_data::store::crop_store::{
    CropStore, WindowCodec, WindowPart, encode_mesh, encode_window, read_manifest,
};
use serde_json::Value;
use std::path::Path;

type Res<T> = Result<T, Box<dyn std::error::Error>>;

/// A named edit of a JSON file, for a variant seed.
type Edit<'a> = (&'a str, Box<dyn Fn(&mut Value)>);

/// Writes `bytes` as seed `name` of `target`.
fn seed(corpus: &Path, target: &str, name: &str, bytes: &[u8]) -> Res<()> {
    let dir = corpus.join(target);
    std::fs::create_dir_all(&dir)?;
    std::fs::write(dir.join(name), bytes)?;
    Ok(())
}

/// `bytes` with bit `bit` of byte `at` flipped.
fn flipped(bytes: &[u8], at: usize, bit: u8) -> Vec<u8> {
    let mut v = bytes.to_vec();
    v[at] ^= 1 << bit;
    v
}

/// The JSON text `text` with `edit` applied.
fn edited(text: &[u8], edit: impl FnOnce(&mut Value)) -> Res<Vec<u8>> {
    let mut v: Value = serde_json::from_slice(text)?;
    edit(&mut v);
    Ok(serde_json::to_vec_pretty(&v)?)
}

fn main() -> Res<()> {
    let args: Vec<String> = std::env::args().collect();
    let [_, work, corpus] = &args[..] else {
        return Err("usage: data_fuzz_seeds WORK CORPUS".into());
    };
    let (work, corpus) = (Path::new(work), Path::new(corpus));
    let ds = Dataset::open(&work.join("pq"))?;

    // crop_part: per codec, shards 0 and 1 as written; shard 0's variants.
    for codec in ["raw", "png", "pred-zstd"] {
        let dir = work.join(format!("crops-{codec}"));
        let json = std::fs::read(dir.join("crops.json"))?;
        for shard in &ds.shards()[..2] {
            let keys: Vec<String> = ds
                .read_sample_keys(shard)?
                .into_iter()
                .map(|(k, _)| k.to_string())
                .collect();
            let keys = keys.join("\n");
            let part = std::fs::read(dir.join(format!("part-{}.bin", shard.index)))?;
            let k = (shard.index as u32).to_le_bytes();
            let pack = |flags: u8, part: &[u8]| {
                let head = [&[flags][..], &k[..]].concat();
                container::join(&[&json, keys.as_bytes(), &head, part])
            };
            let name = |what: &str| format!("{codec}_shard{}_{what}", shard.index);
            seed(corpus, "crop_part", &name("valid"), &pack(0, &part))?;
            if shard.index != 0 {
                continue;
            }
            // The first record's window starts after its prefix (header 128 bytes, then
            // CRC to the lengths: 24 + 64 + the key field + 40).
            let m = read_manifest(&dir)?;
            let in_window = 128 + 24 + 64 + m.key_bytes + 40 + 5;
            let n = part.len();
            seed(
                corpus,
                "crop_part",
                &name("truncated_half"),
                &pack(0, &part[..n / 2]),
            )?;
            seed(
                corpus,
                "crop_part",
                &name("no_footer_byte"),
                &pack(0, &part[..n - 1]),
            )?;
            seed(
                corpus,
                "crop_part",
                &name("window_flipped"),
                &pack(0, &flipped(&part, in_window, 3)),
            )?;
            seed(
                corpus,
                "crop_part",
                &name("window_flipped_resealed"),
                &pack(1, &flipped(&part, in_window, 3)),
            )?;
            seed(
                corpus,
                "crop_part",
                &name("index_crc_flipped"),
                &pack(0, &flipped(&part, n - 8, 0)),
            )?;
        }
    }

    // crop_window and mesh: the first record of the raw store, stored by each codec.
    let raw = work.join("crops-raw");
    let m = read_manifest(&raw)?;
    let store = CropStore::open(&raw, &ds, m.rules, m.img_size, m.vertex_count)?;
    let key = ds.read_sample_keys(&ds.shards()[0])?[0].0.to_string();
    let rec = store.read(0, 0, &key)?;
    let window = rec.decode(WindowPart::Whole)?.window;
    for codec in WindowCodec::ALL {
        let code = u8::try_from(arkit_data::fuzz_entry::codec_code(*codec))?;
        let bytes = encode_window(*codec, &window, m.img_size)?;
        let s = [&[code, m.img_size as u8][..], &bytes].concat();
        let name = codec.name();
        seed(corpus, "crop_window", &format!("{name}_valid"), &s)?;
        seed(
            corpus,
            "crop_window",
            &format!("{name}_truncated"),
            &s[..s.len() - 7],
        )?;
        seed(
            corpus,
            "crop_window",
            &format!("{name}_flipped"),
            &flipped(&s, s.len() / 2, 5),
        )?;
    }
    let v = rec.verts.len() as u16;
    let stored = encode_mesh(&rec.verts);
    let s = [&v.to_le_bytes()[..], &stored].concat();
    seed(corpus, "mesh", "valid", &s)?;
    let few = encode_mesh(&rec.verts[..5]);
    seed(
        corpus,
        "mesh",
        "five_vertices",
        &[&5u16.to_le_bytes()[..], &few].concat(),
    )?;
    seed(
        corpus,
        "mesh",
        "one_vertex_more",
        &[&(v + 1).to_le_bytes()[..], &stored].concat(),
    )?;
    seed(corpus, "mesh", "truncated", &s[..s.len() / 2])?;
    seed(corpus, "mesh", "flipped", &flipped(&s, s.len() / 3, 1))?;

    // crops_json: each codec's as written, then hostile edits of the raw one.
    for codec in ["raw", "png", "pred-zstd"] {
        let json = std::fs::read(work.join(format!("crops-{codec}/crops.json")))?;
        seed(corpus, "crops_json", &format!("{codec}_valid.json"), &json)?;
    }
    let json = std::fs::read(raw.join("crops.json"))?;
    seed(
        corpus,
        "crops_json",
        "truncated.json",
        &json[..json.len() / 2],
    )?;
    let old = edited(&json, |v| v["format"] = 5.into())?;
    seed(corpus, "crops_json", "format_5.json", &old)?;
    let wide = edited(&json, |v| v["key_bytes"] = (1u64 << 40).into())?;
    seed(corpus, "crops_json", "key_bytes_huge.json", &wide)?;
    let codec = edited(&json, |v| v["codec"] = "webp".into())?;
    seed(corpus, "crops_json", "codec_webp.json", &codec)?;

    // dataset_json: the whole dataset's and the two parts', then hostile edits.
    let whole = std::fs::read(work.join("pq/dataset.json"))?;
    seed(corpus, "dataset_json", "whole_valid.json", &whole)?;
    for i in 0..2 {
        let p = std::fs::read(work.join(format!("parts/manifest/part-000{i}-of-0002.json")))?;
        seed(corpus, "dataset_json", &format!("part{i}_valid.json"), &p)?;
    }
    seed(
        corpus,
        "dataset_json",
        "truncated.json",
        &whole[..whole.len() / 2],
    )?;
    let hostile: [Edit; 5] = [
        (
            "samples_file_absolute",
            Box::new(|v| v["shards"][0]["samples_file"] = "/etc/passwd".into()),
        ),
        (
            "samples_file_dotdot",
            Box::new(|v| v["shards"][0]["errors_file"] = "../../x.parquet".into()),
        ),
        (
            "shard_index_huge",
            Box::new(|v| v["shards"][0]["index"] = (1u64 << 50).into()),
        ),
        (
            "listed_huge",
            Box::new(|v| v["listed"] = (1u64 << 60).into()),
        ),
        (
            "part_past_count",
            Box::new(|v| v["part"] = serde_json::json!([2, 2])),
        ),
    ];
    for (name, edit) in hostile {
        seed(
            corpus,
            "dataset_json",
            &format!("{name}.json"),
            &edited(&whole, edit)?,
        )?;
    }

    // conversion_json.
    let conv = std::fs::read(work.join("pq/conversion.json"))?;
    seed(corpus, "conversion_json", "valid.json", &conv)?;
    seed(
        corpus,
        "conversion_json",
        "truncated.json",
        &conv[..conv.len() - 9],
    )?;
    let rows = edited(&conv, |v| v["rows_per_shard"] = Value::from(-1))?;
    seed(corpus, "conversion_json", "rows_negative.json", &rows)?;
    Ok(())
}
