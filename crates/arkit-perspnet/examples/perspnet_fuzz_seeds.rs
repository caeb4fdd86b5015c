//! Writes the seed corpus of arkit-perspnet's fuzz targets (`fuzz/corpus/<target>/`)
//! from a checkpoint folder `train` wrote (`fuzz/make_data_seeds.sh` makes it and runs
//! this): its `checkpoint.json` and `perspnet.json` as they are, then variants.
//!
//! Usage: `perspnet_fuzz_seeds MODEL CORPUS`.

use arkit_perspnet::fuzz_entry::checkpoint_file_bytes;
use serde_json::{Value, json};
use sha2::Digest;
use std::path::Path;

type Res<T> = Result<T, Box<dyn std::error::Error>>;

/// A named edit of a JSON file, for a variant seed.
type Edit<'a> = (&'a str, Box<dyn Fn(&mut Value)>);

fn seed(corpus: &Path, target: &str, name: &str, bytes: &[u8]) -> Res<()> {
    let dir = corpus.join(target);
    std::fs::create_dir_all(&dir)?;
    std::fs::write(dir.join(name), bytes)?;
    Ok(())
}

fn edited(v: &Value, edit: impl FnOnce(&mut Value)) -> Res<Vec<u8>> {
    let mut v = v.clone();
    edit(&mut v);
    Ok(serde_json::to_vec_pretty(&v)?)
}

fn main() -> Res<()> {
    let args: Vec<String> = std::env::args().collect();
    let [_, model, corpus] = &args[..] else {
        return Err("usage: perspnet_fuzz_seeds MODEL CORPUS".into());
    };
    let (model, corpus) = (Path::new(model), Path::new(corpus));

    // checkpoint_json: train's record as written (its files are not the entry's: refused),
    // then the same record describing the entry's files (accepted), then variants of it.
    let written = std::fs::read(model.join("checkpoint.json"))?;
    seed(corpus, "checkpoint_json", "as_written.json", &written)?;
    let mut record: Value = serde_json::from_slice(&written)?;
    for f in record["files"].as_array_mut().ok_or("no files")? {
        let name = f["name"].as_str().ok_or("no name")?.to_string();
        let bytes = checkpoint_file_bytes(&name);
        let sha: String = sha2::Sha256::digest(&bytes)
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        f["bytes"] = json!(bytes.len());
        f["sha256"] = json!(sha);
    }
    let valid = serde_json::to_vec_pretty(&record)?;
    seed(corpus, "checkpoint_json", "valid.json", &valid)?;
    seed(
        corpus,
        "checkpoint_json",
        "truncated.json",
        &valid[..valid.len() / 2],
    )?;
    let variants: [Edit; 4] = [
        (
            "file_unlisted",
            Box::new(|v| {
                v["files"].as_array_mut().unwrap().remove(0);
            }),
        ),
        (
            "size_off_by_one",
            Box::new(|v| {
                v["files"][1]["bytes"] = json!(v["files"][1]["bytes"].as_u64().unwrap() + 1)
            }),
        ),
        (
            "sha_other",
            Box::new(|v| v["files"][2]["sha256"] = json!("0".repeat(64))),
        ),
        (
            "size_huge",
            Box::new(|v| v["files"][3]["bytes"] = json!(u64::MAX)),
        ),
    ];
    for (name, edit) in variants {
        seed(
            corpus,
            "checkpoint_json",
            &format!("{name}.json"),
            &edited(&record, edit)?,
        )?;
    }

    // perspnet_json: train's and the shipped model's, then variants.
    let info = std::fs::read(model.join("perspnet.json"))?;
    seed(corpus, "perspnet_json", "trained.json", &info)?;
    let shipped =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/tiny-synthetic/perspnet.json");
    seed(
        corpus,
        "perspnet_json",
        "shipped.json",
        &std::fs::read(shipped)?,
    )?;
    seed(
        corpus,
        "perspnet_json",
        "truncated.json",
        &info[..info.len() / 2],
    )?;
    let v: Value = serde_json::from_slice(&info)?;
    let variants: [Edit; 4] = [
        (
            "input_size_huge",
            Box::new(|v| v["config"]["input_size"] = json!(1u64 << 40)),
        ),
        (
            "dropout_one",
            Box::new(|v| v["config"]["dropout"] = json!(1.0)),
        ),
        (
            "losses_null",
            Box::new(|v| {
                v["first_loss"] = Value::Null;
                v["last_loss"] = Value::Null;
            }),
        ),
        (
            "widths_zero",
            Box::new(|v| v["config"]["encoder_widths"] = json!([0, 0, 0, 0])),
        ),
    ];
    for (name, edit) in variants {
        seed(
            corpus,
            "perspnet_json",
            &format!("{name}.json"),
            &edited(&v, edit)?,
        )?;
    }
    Ok(())
}
