//! The CSV form of the predictions file that `eval` reads (the Parquet form is read in
//! `arkit_tool::predictions_table`, which re-exports this module's items).
//!
//! A header line names the columns (any order, others ignored): `subject_id`,
//! `facial_action`, `img_id`, `R_t` (the predicted pose in the release's row-vector
//! form, 16 numbers separated by spaces, row-major; an empty field is null, counted as
//! a PnP failure) and optionally `verts` (1220 x 3 numbers, metres). Blank lines are
//! skipped; a leading UTF-8 byte-order mark is skipped.
//!
//! Invariants: every row has as many fields as the header, every number parses, `R_t`
//! has exactly 16 values; otherwise the error names the file and the line. Nothing is
//! allocated from a count in the text (the text's own length bounds everything).
//! Tested below and by the `predictions_csv` fuzz target.

use crate::error::{Error, Result};
use crate::release::SampleKey;
use std::path::Path;

/// One prediction row.
#[derive(Clone, Debug, PartialEq)]
pub struct PredictionRecord {
    /// The sample.
    pub key: SampleKey,
    /// Predicted `R_t` (row-vector form, row-major), `None` when the predictor failed.
    pub rt: Option<[f64; 16]>,
    /// Predicted canonical vertices, 1220 x 3 row-major, metres.
    pub verts: Option<Vec<f32>>,
    /// Predicted crop mask as run lengths (the `targets` mask encoding, see
    /// [`crate::rle_encode`]); Parquet only, always `None` from CSV.
    pub mask_rle: Option<Vec<u32>>,
}

/// The pose of one row's `R_t` values (`None` for a null), checking that there are
/// 16; `row` is the row (or line) number named in the error.
pub fn rt_of(values: Option<&[f64]>, path: &Path, row: usize) -> Result<Option<[f64; 16]>> {
    match values {
        None => Ok(None),
        Some(v) if v.len() == 16 => {
            let mut m = [0.0; 16];
            m.copy_from_slice(v);
            Ok(Some(m))
        }
        Some(v) => Err(Error::format(
            path,
            format!("row {row}: R_t has {} values, expected 16", v.len()),
        )),
    }
}

/// Parses the CSV form (see the module docs).
pub fn parse_csv(text: &str, path: &Path) -> Result<Vec<PredictionRecord>> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let (_, header) = lines
        .next()
        .ok_or_else(|| Error::format(path, "empty file: expected a header line"))?;
    let names: Vec<&str> = header.split(',').map(|h| h.trim()).collect();
    let find = |n: &str| names.iter().position(|h| *h == n);
    let need =
        |n: &str| find(n).ok_or_else(|| Error::format(path, format!("header has no column '{n}'")));
    let (si, fi, ii, ri) = (
        need("subject_id")?,
        need("facial_action")?,
        need("img_id")?,
        need("R_t")?,
    );
    let vi = find("verts");
    let mut out = Vec::new();
    for (n, line) in lines {
        let fields: Vec<&str> = line
            .split(',')
            .map(|f| f.trim().trim_matches('"'))
            .collect();
        if fields.len() != names.len() {
            return Err(Error::format(
                path,
                format!(
                    "line {}: {} fields, the header has {}",
                    n + 1,
                    fields.len(),
                    names.len()
                ),
            ));
        }
        let numbers = |f: &str| -> Result<Option<Vec<f64>>> {
            if f.is_empty() {
                return Ok(None);
            }
            f.split_whitespace()
                .map(|x| {
                    x.parse::<f64>().map_err(|_| {
                        Error::format(path, format!("line {}: '{x}' is not a number", n + 1))
                    })
                })
                .collect::<Result<Vec<f64>>>()
                .map(Some)
        };
        out.push(PredictionRecord {
            key: SampleKey {
                subject_id: fields[si].to_string(),
                facial_action: fields[fi].to_string(),
                img_id: fields[ii].to_string(),
            },
            rt: rt_of(numbers(fields[ri])?.as_deref(), path, n + 1)?,
            verts: match vi {
                Some(v) => numbers(fields[v])?.map(|v| v.iter().map(|&x| x as f32).collect()),
                None => None,
            },
            mask_rle: None,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_reads_and_names_bad_lines() {
        let p = Path::new("pred.csv");
        let ok = "subject_id,facial_action,img_id,R_t\n1,a,2,1 0 0 0 0 1 0 0 0 0 1 0 0 0 -0.5 1\n1,a,3,\n";
        let rows = parse_csv(ok, p).unwrap();
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0].rt.unwrap()[14], -0.5);
        assert_eq!(rows[1].rt, None);
        let short = "subject_id,facial_action,img_id,R_t\n1,a,2,1 0 0\n";
        let e = parse_csv(short, p).unwrap_err().to_string();
        assert!(e.contains("pred.csv") && e.contains("3 values"), "{e}");
        let word = "subject_id,facial_action,img_id,R_t\n1,a,2,x\n";
        assert!(
            parse_csv(word, p)
                .unwrap_err()
                .to_string()
                .contains("line 2")
        );
        let no_rt = "subject_id,facial_action,img_id\n";
        assert!(parse_csv(no_rt, p).unwrap_err().to_string().contains("R_t"));
    }

    #[test]
    fn csv_with_bom_verts_and_blank_lines() {
        let p = Path::new("pred.csv");
        let text = "\u{feff}img_id,R_t,verts,subject_id,facial_action\n\n7,,0.5 -1e-3,s,a\n";
        let rows = parse_csv(text, p).unwrap();
        assert_eq!(rows.len(), 1);
        assert_eq!(rows[0].key.img_id, "7");
        assert_eq!(rows[0].rt, None);
        assert_eq!(rows[0].verts, Some(vec![0.5, -1e-3]));
        let e = parse_csv("subject_id,facial_action,img_id,R_t\n1,a\n", p)
            .unwrap_err()
            .to_string();
        assert_eq!(e, "pred.csv: line 2: 2 fields, the header has 4");
    }
}
