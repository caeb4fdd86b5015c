//! What we write matches the machine-readable schemas in `schemas/`.

use arkit_core::DType;
use arkit_data::ingest::synth::{self, FaceSource, SynthOptions};

fn schema(name: &str) -> serde_json::Value {
    let p = crate::support::workspace().join("schemas").join(name);
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

#[test]
fn info_npz_written_by_synth_matches_its_schema() {
    let s = schema("info_npz.json");
    let keys = s["keys"].as_array().unwrap();
    let options = SynthOptions {
        subjects: 1,
        images_per_subject: 1,
        width: 96,
        height: 96,
        ..SynthOptions::default()
    };
    let plan = synth::plan(&options);
    let sample = synth::render_sample(&FaceSource::builtin(), &options, &plan[0]).unwrap();
    let arrays = sample.info.to_arrays();
    assert_eq!(
        arrays.len(),
        keys.len(),
        "synth writes every key of the schema"
    );
    for k in keys {
        let name = k["key"].as_str().unwrap();
        let (_, a) = arrays
            .iter()
            .find(|(n, _)| *n == name)
            .unwrap_or_else(|| panic!("{name} not written"));
        let dtype = match k["dtype"].as_str().unwrap() {
            "float32" => DType::F32,
            "float64" => DType::F64,
            other => panic!("schema dtype {other}"),
        };
        assert_eq!(a.dtype(), dtype, "{name}");
        let shape: Vec<usize> = k["shape"]
            .as_array()
            .unwrap()
            .iter()
            .map(|d| d.as_u64().unwrap() as usize)
            .collect();
        assert_eq!(a.shape(), shape.as_slice(), "{name}");
    }
    // The required keys are exactly the ones the reader insists on.
    let required: Vec<&str> = keys
        .iter()
        .filter(|k| k["required"] == true)
        .map(|k| k["key"].as_str().unwrap())
        .collect();
    assert_eq!(required, vec!["verts", "R_t"]);
}

#[test]
fn list_csv_header_matches_its_schema() {
    let s = schema("list_csv.json");
    let header: Vec<&str> = s["header_required"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    let text = arkit_core::release::list_csv_text(&[]);
    assert_eq!(text.trim_end(), header.join(","));
}

fn column_names(s: &serde_json::Value) -> Vec<String> {
    s["columns"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["name"].as_str().unwrap().to_string())
        .collect()
}

#[test]
fn eval_per_sample_table_matches_its_schema() {
    let s = schema("eval_samples.json");
    assert_eq!(
        column_names(&s),
        arkit_data::eval::PER_SAMPLE_COLUMNS
            .iter()
            .map(|c| c.to_string())
            .collect::<Vec<_>>()
    );
    let df = arkit_data::eval::per_sample_frame(&[]).unwrap();
    let written: Vec<String> = df
        .get_column_names()
        .iter()
        .map(|c| c.to_string())
        .collect();
    assert_eq!(column_names(&s), written);
}

#[test]
fn predictions_written_match_their_schema() {
    use arkit_core::PredictionRecord;
    use arkit_core::SampleKey;
    use arkit_data::store::predictions_frame;
    let s = schema("predictions.json");
    let row = PredictionRecord {
        key: SampleKey {
            subject_id: "1".into(),
            facial_action: "a".into(),
            img_id: "2".into(),
        },
        rt: Some([0.0; 16]),
        verts: Some(vec![0.0; 3]),
        mask_rle: Some(vec![1]),
    };
    let df = predictions_frame(&[row]).unwrap();
    for c in s["columns"].as_array().unwrap() {
        let name = c["name"].as_str().unwrap();
        let dtype = df.column(name).unwrap().dtype().clone();
        let want = match c["type"].as_str().unwrap() {
            "binary" => polars::prelude::DataType::Binary,
            t => arkit_data::store::polars_dtype(t).unwrap(),
        };
        assert_eq!(dtype, want, "{name}");
    }
    assert_eq!(df.width(), s["columns"].as_array().unwrap().len());
}
