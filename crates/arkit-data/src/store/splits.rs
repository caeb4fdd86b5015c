//! Which split each sample of a dataset is in, as every stage that picks a split reads
//! it: `split`'s assignment (`splits/splits.parquet`) when it has run, else the split
//! of the release list `convert` read each sample from.

use crate::store::parquet;
use crate::store::samples_table::SampleRecord;
use arkit_core::Result;
use arkit_core::SampleKey;
use std::collections::HashMap;
use std::path::Path;

/// Which split each sample of a dataset is in: `split`'s assignment
/// (`splits/splits.parquet`) when it has run, else the release lists `convert` read.
#[derive(Clone, Debug)]
pub struct SplitLookup(Option<HashMap<SampleKey, String>>);

impl SplitLookup {
    /// Reads the assignment of `dataset`, if any.
    pub fn read(dataset: &Path) -> Result<Self> {
        split_map(dataset).map(SplitLookup)
    }

    /// The split of a sample.
    pub fn of(&self, r: &SampleRecord) -> String {
        self.of_key(&r.key, &r.split)
    }

    /// The split of the sample `key` that the release listed in `listed`.
    pub fn of_key(&self, key: &SampleKey, listed: &str) -> String {
        self.0
            .as_ref()
            .and_then(|m| m.get(key).cloned())
            .unwrap_or_else(|| listed.to_string())
    }

    /// Whether a sample is in `want` (`None`: every split).
    pub fn keeps(&self, r: &SampleRecord, want: Option<&str>) -> bool {
        self.keeps_key(&r.key, &r.split, want)
    }

    /// [`SplitLookup::keeps`] from a sample's key and listed split only (as
    /// [`crate::store::samples_table::read_sample_keys`] gives them, without the meshes).
    pub(crate) fn keeps_key(&self, key: &SampleKey, listed: &str, want: Option<&str>) -> bool {
        want.is_none_or(|w| self.of_key(key, listed) == w)
    }
}

fn split_map(dataset: &Path) -> Result<Option<HashMap<SampleKey, String>>> {
    let path = dataset.join("splits").join("splits.parquet");
    if !path.exists() {
        return Ok(None);
    }
    let names = ["subject_id", "facial_action", "img_id", "split"];
    let df = parquet::read_parquet_columns(&path, &names)?;
    let cols: Vec<Vec<String>> = names
        .iter()
        .map(|c| parquet::str_values(&df, c, &path))
        .collect::<Result<_>>()?;
    Ok(Some(
        (0..cols[0].len())
            .map(|i| {
                (
                    SampleKey {
                        subject_id: cols[0][i].clone(),
                        facial_action: cols[1][i].clone(),
                        img_id: cols[2][i].clone(),
                    },
                    cols[3][i].clone(),
                )
            })
            .collect(),
    ))
}
