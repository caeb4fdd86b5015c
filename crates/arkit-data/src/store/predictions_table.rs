//! Pose predictions: the file `predict` writes and `eval` reads (Parquet or CSV).
//!
//! Schema (also `schemas/predictions.json`), keyed like `samples`:
//! - `subject_id`, `facial_action`, `img_id`: strings.
//! - `R_t`: the predicted pose in the release's row-vector form, 16 numbers row-major;
//!   null when the predictor failed (counted as a PnP failure).
//! - `verts` (optional column): predicted canonical vertices, 1220 x 3 row-major, metres.
//! - `mask_rle` (optional column, Parquet only): the predicted face mask over the
//!   `targets` crop, encoded as the `targets` table encodes its mask (u32 LE run
//!   lengths, starting with a background run).
//!
//! In CSV, `R_t` and `verts` are single fields holding the numbers separated by spaces,
//! and an empty field is null. A header line names the columns.

use crate::store::parquet::{read_parquet, str_values, write_parquet};
use arkit_core::SampleKey;
use arkit_core::{Error, Result};
use polars::prelude::*;

use arkit_core::{PredictionRecord, parse_predictions_csv as parse_csv, rt_of};
use std::path::Path;

/// The rows as a DataFrame. Optional columns are written only when some row has them.
pub fn predictions_frame(rows: &[PredictionRecord]) -> Result<DataFrame> {
    let s = |name: &str, f: &dyn Fn(&PredictionRecord) -> &str| {
        Column::new(name.into(), rows.iter().map(f).collect::<Vec<&str>>())
    };
    let mut columns = vec![
        s("subject_id", &|r| &r.key.subject_id),
        s("facial_action", &|r| &r.key.facial_action),
        s("img_id", &|r| &r.key.img_id),
    ];
    let rt: Vec<Option<Series>> = rows
        .iter()
        .map(|r| r.rt.map(|m| Series::new("".into(), m.to_vec())))
        .collect();
    columns.push(list_column("R_t", rt, DataType::Float64));
    if rows.iter().any(|r| r.verts.is_some()) {
        let v: Vec<Option<Series>> = rows
            .iter()
            .map(|r| r.verts.as_ref().map(|v| Series::new("".into(), v.clone())))
            .collect();
        columns.push(list_column("verts", v, DataType::Float32));
    }
    if rows.iter().any(|r| r.mask_rle.is_some()) {
        let blobs: Vec<Option<Vec<u8>>> = rows
            .iter()
            .map(|r| {
                r.mask_rle
                    .as_ref()
                    .map(|m| m.iter().flat_map(|x| x.to_le_bytes()).collect())
            })
            .collect();
        let refs: Vec<Option<&[u8]>> = blobs.iter().map(|b| b.as_deref()).collect();
        columns.push(Column::new("mask_rle".into(), refs));
    }
    DataFrame::new(rows.len(), columns).map_err(|e| Error::invalid("predictions", e.to_string()))
}

fn list_column(name: &str, values: Vec<Option<Series>>, inner: DataType) -> Column {
    let mut ca: ListChunked = values.into_iter().collect();
    ca.rename(name.into());
    let col = ca.into_series().into_column();
    col.cast(&DataType::List(Box::new(inner)))
        .expect("a list of numbers casts to its own type")
}

/// Writes predictions as Parquet (atomically). A name ending in `.csv` is refused:
/// [`read_predictions`] would read it as CSV.
pub fn write_predictions(path: &Path, rows: &[PredictionRecord]) -> Result<()> {
    if path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("csv"))
    {
        return Err(Error::invalid(
            "--output",
            format!(
                "{}: predictions are written as Parquet; name the file .parquet",
                path.display()
            ),
        ));
    }
    let mut df = predictions_frame(rows)?;
    write_parquet(path, &mut df)
}

/// Reads predictions from Parquet or, when the name ends in `.csv`, CSV.
pub fn read_predictions(path: &Path) -> Result<Vec<PredictionRecord>> {
    if path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("csv"))
    {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        parse_csv(&text, path)
    } else {
        read_parquet_predictions(path)
    }
}

fn read_parquet_predictions(path: &Path) -> Result<Vec<PredictionRecord>> {
    let df = read_parquet(path)?;
    let subject = str_values(&df, "subject_id", path)?;
    let action = str_values(&df, "facial_action", path)?;
    let img = str_values(&df, "img_id", path)?;
    let lists = |name: &str| -> Result<Option<Vec<Option<Vec<f64>>>>> {
        let Ok(c) = df.column(name) else {
            return Ok(None);
        };
        let bad = |e: PolarsError| Error::format(path, format!("column {name}: {e}"));
        // Only lists are cast (their numbers to f64): polars would turn any other column
        // into one-element lists, with a deprecation warning on stderr.
        if !matches!(c.dtype(), DataType::List(_)) {
            return Err(Error::format(
                path,
                format!(
                    "column {name} must be a list of numbers per row, found {}",
                    c.dtype()
                ),
            ));
        }
        let c = c
            .cast(&DataType::List(Box::new(DataType::Float64)))
            .map_err(bad)?;
        let ca = c.list().map_err(bad)?;
        ca.series_iter()
            .map(|s| match s {
                None => Ok(None),
                Some(s) => Ok(Some(
                    s.f64()
                        .map_err(bad)?
                        .iter()
                        .map(|v| v.unwrap_or(f64::NAN))
                        .collect(),
                )),
            })
            .collect::<Result<Vec<_>>>()
            .map(Some)
    };
    let rt =
        lists("R_t")?.ok_or_else(|| Error::format(path, "no column 'R_t' (the predicted pose)"))?;
    let verts = lists("verts")?;
    let masks: Option<Vec<Option<Vec<u32>>>> = match df.column("mask_rle") {
        Err(_) => None,
        Ok(c) => {
            let ca = c
                .binary()
                .map_err(|e| Error::format(path, format!("column mask_rle: {e}")))?;
            Some(
                ca.iter()
                    .enumerate()
                    .map(|(i, b)| {
                        b.map(|b| {
                            arkit_core::unpack_u32_le(b, "mask_rle")
                                .map_err(|e| Error::format(path, format!("row {i}: {e}")))
                        })
                        .transpose()
                    })
                    .collect::<Result<Vec<_>>>()?,
            )
        }
    };
    let mut out = Vec::with_capacity(df.height());
    for i in 0..df.height() {
        out.push(PredictionRecord {
            key: SampleKey {
                subject_id: subject[i].clone(),
                facial_action: action[i].clone(),
                img_id: img[i].clone(),
            },
            rt: rt_of(rt[i].as_deref(), path, i)?,
            verts: verts
                .as_ref()
                .and_then(|v| v[i].as_ref())
                .map(|v| v.iter().map(|&x| x as f32).collect()),
            mask_rle: masks.as_ref().and_then(|m| m[i].clone()),
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(i: usize) -> SampleKey {
        SampleKey {
            subject_id: format!("s{i}"),
            facial_action: "a".into(),
            img_id: format!("{i}"),
        }
    }

    #[test]
    fn parquet_round_trip_with_nulls() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.parquet");
        let mut rt = [0.0; 16];
        rt.iter_mut()
            .enumerate()
            .for_each(|(i, v)| *v = i as f64 * 0.25);
        let rows = vec![
            PredictionRecord {
                key: key(0),
                rt: Some(rt),
                verts: Some(vec![0.5; 6]),
                mask_rle: Some(vec![3, 4, 5]),
            },
            PredictionRecord {
                key: key(1),
                rt: None,
                verts: None,
                mask_rle: None,
            },
        ];
        write_predictions(&path, &rows).unwrap();
        assert_eq!(read_predictions(&path).unwrap(), rows);
    }
    #[test]
    fn a_pose_column_that_is_not_a_list_is_refused_and_csv_names_are_not_written() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("flat.parquet");
        let mut df = DataFrame::new(
            1,
            vec![
                Column::new("subject_id".into(), ["s"]),
                Column::new("facial_action".into(), ["a"]),
                Column::new("img_id".into(), ["1"]),
                Column::new("R_t".into(), [0.5f64]),
            ],
        )
        .unwrap();
        write_parquet(&path, &mut df).unwrap();
        let e = read_predictions(&path).unwrap_err().to_string();
        assert!(e.contains("column R_t must be a list"), "{e}");
        let e = write_predictions(&dir.path().join("p.csv"), &[])
            .unwrap_err()
            .to_string();
        assert!(e.contains(".parquet"), "{e}");
    }
}
