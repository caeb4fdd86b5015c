//! The `samples` and `errors` tables that `convert` writes, as Parquet via polars.
//!
//! Schemas are documented, column by column with types and units, in
//! `schemas/samples.json` and `schemas/errors.json`; [`SAMPLES_COLUMNS`] and
//! [`ERRORS_COLUMNS`] are the same lists in code, and a test checks the two agree and
//! that what we write has exactly these columns and types.
//!
//! Every table is keyed by `(subject_id, facial_action, img_id)`, all strings.
//!
//! Since samples format 2 ([`SAMPLES_FORMAT`]) the fixed-shape columns are fixed-size
//! lists with their shapes (`verts` N x 3, `R_t` 4 x 4, `landmarks_2d` 68 x 2: Arrow
//! `fixed_size_list<fixed_size_list<...>>`, polars `Array`), and the file's key-value
//! metadata carries them as Hugging Face `datasets` features (key `huggingface`,
//! [`huggingface_metadata`]), so polars, DuckDB, pyarrow and `datasets` see the shapes.
//! [`read_samples`] reads both that and format 1 (variable-length lists, files written
//! before), checking every width.

use crate::store::parquet::{
    column, f64_values, parquet_key_value_metadata, polars_err, read_parquet, read_parquet_columns,
    str_values, write_parquet_with_metadata,
};
use arkit_core::SampleKey;
use arkit_core::{Error, Result};
use polars::prelude::*;
use std::path::Path;

/// One validated sample: a row of the `samples` table.
#[derive(Clone, Debug, PartialEq)]
pub struct SampleRecord {
    /// The sample's key.
    pub key: SampleKey,
    /// The release split it was listed in (`train`, `test`, or `all` for a flat layout).
    pub split: String,
    /// The image path relative to the input root, with `/` separators.
    pub image_path: String,
    /// Image width in pixels.
    pub image_width: u32,
    /// Image height in pixels.
    pub image_height: u32,
    /// The JPEG file's bytes, when converted with `--embed-images`.
    pub jpeg: Option<Vec<u8>>,
    /// `verts`, N x 3 row-major, metres, canonical frame (N = 1220 for ARKit data; a
    /// BIWI dataset holds each subject's own head mesh).
    pub verts: Vec<f32>,
    /// `R_t`, 16 numbers row-major, row-vector form.
    pub rt: [f64; 16],
    /// Yaw in degrees (SciPy 'yxz' of `R_t[:3,:3]^T`).
    pub yaw_deg: f64,
    /// Pitch in degrees.
    pub pitch_deg: f64,
    /// Roll in degrees.
    pub roll_deg: f64,
    /// Translation `R_t[3, :3]` in metres.
    pub translation_m: [f64; 3],
    /// The 68 landmarks projected to pixels, `[u0, v0, u1, v1, ...]`.
    pub landmarks_2d: Vec<f32>,
    /// The official crop box `[x0, y0, x1, y1]` in pixels: centred on the landmarks' 2D
    /// bounding box, half-side 0.75 times its larger side.
    pub face_box: [f64; 4],
}

/// A sample that could not be converted: a row of the `errors` table.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ErrorRecord {
    /// The sample's key (empty strings for a file no list names).
    pub key: SampleKey,
    /// The split it was listed in.
    pub split: String,
    /// The file at fault, relative to the input root.
    pub file: String,
    /// What is wrong.
    pub reason: String,
}

/// A column of a table we write: name, Parquet/polars type, and meaning.
#[derive(Clone, Copy, Debug)]
pub struct ColumnSpec {
    /// Column name.
    pub name: &'static str,
    /// Type as written in `schemas/*.json` (`string`, `uint32`, `float64`, `binary`,
    /// `list<float32>`, `list<float64>`, or a fixed shape such as `float32[N,3]`,
    /// `float64[4,4]`: a fixed-size list of fixed-size lists, `N` the vertex count, fixed
    /// per file).
    pub dtype: &'static str,
}

/// The samples table's format, recorded in the file's key-value metadata (key
/// `ARKIT_METADATA_KEY`) and in the conversion's fingerprint: 2 = fixed-shape columns
/// as fixed-size lists with a `huggingface` features record; 1 (files without the key)
/// = variable-length lists. Readers read both.
pub const SAMPLES_FORMAT: u32 = 2;

/// The key-value metadata key of our own record (`{"table": "samples",
/// "samples_format": 2}`).
pub(crate) const ARKIT_METADATA_KEY: &str = "arkit_tool";

/// The key-value metadata key Hugging Face `datasets` reads its features from.
pub(crate) const HUGGINGFACE_METADATA_KEY: &str = "huggingface";

/// Number of landmarks in `landmarks_2d` (the iBUG 68-point scheme).
pub(crate) const LANDMARKS: usize = crate::mesh::topology::LANDMARK_COUNT;

/// The columns of the `samples` table, in order.
pub const SAMPLES_COLUMNS: [ColumnSpec; 20] = [
    ColumnSpec {
        name: "subject_id",
        dtype: "string",
    },
    ColumnSpec {
        name: "facial_action",
        dtype: "string",
    },
    ColumnSpec {
        name: "img_id",
        dtype: "string",
    },
    ColumnSpec {
        name: "split",
        dtype: "string",
    },
    ColumnSpec {
        name: "image_path",
        dtype: "string",
    },
    ColumnSpec {
        name: "image_width",
        dtype: "uint32",
    },
    ColumnSpec {
        name: "image_height",
        dtype: "uint32",
    },
    ColumnSpec {
        name: "jpeg",
        dtype: "binary",
    },
    ColumnSpec {
        name: "verts",
        dtype: "float32[N,3]",
    },
    ColumnSpec {
        name: "R_t",
        dtype: "float64[4,4]",
    },
    ColumnSpec {
        name: "yaw_deg",
        dtype: "float64",
    },
    ColumnSpec {
        name: "pitch_deg",
        dtype: "float64",
    },
    ColumnSpec {
        name: "roll_deg",
        dtype: "float64",
    },
    ColumnSpec {
        name: "tx_m",
        dtype: "float64",
    },
    ColumnSpec {
        name: "ty_m",
        dtype: "float64",
    },
    ColumnSpec {
        name: "tz_m",
        dtype: "float64",
    },
    ColumnSpec {
        name: "landmarks_2d",
        dtype: "float32[68,2]",
    },
    ColumnSpec {
        name: "face_box_x0",
        dtype: "float64",
    },
    ColumnSpec {
        name: "face_box_y0",
        dtype: "float64",
    },
    ColumnSpec {
        name: "face_box_side",
        dtype: "float64",
    },
];

/// The columns of the `errors` table, in order.
pub const ERRORS_COLUMNS: [ColumnSpec; 6] = [
    ColumnSpec {
        name: "subject_id",
        dtype: "string",
    },
    ColumnSpec {
        name: "facial_action",
        dtype: "string",
    },
    ColumnSpec {
        name: "img_id",
        dtype: "string",
    },
    ColumnSpec {
        name: "split",
        dtype: "string",
    },
    ColumnSpec {
        name: "file",
        dtype: "string",
    },
    ColumnSpec {
        name: "reason",
        dtype: "string",
    },
];

/// A fixed-shape column: `rows` values of shape `outer x inner` each, flat row-major in
/// `flat`, as `Array(Array(leaf, inner), outer)`.
fn fixed_shape(
    name: &str,
    flat: Series,
    rows: usize,
    outer: usize,
    inner: usize,
) -> Result<Column> {
    let dims = [rows, outer, inner].map(|d| ReshapeDimension::new(d as i64));
    flat.reshape_array(&dims)
        .map(|s| s.with_name(name.into()).into_column())
        .map_err(|e| Error::invalid("samples table", format!("column '{name}': {e}")))
}

fn strings<'a>(name: &str, rows: impl Iterator<Item = &'a str>) -> Column {
    let v: Vec<&str> = rows.collect();
    Column::new(name.into(), v)
}

fn f64s(name: &str, rows: impl Iterator<Item = f64>) -> Column {
    let v: Vec<f64> = rows.collect();
    Column::new(name.into(), v)
}

/// The `samples` rows as a DataFrame with exactly [`SAMPLES_COLUMNS`]; `vertices` is N,
/// the vertex count of every row's `verts` (the topology's: fixed per file, so the
/// column is `N x 3` even when there are no rows). A row of another size is an error.
pub fn samples_frame(rows: &[SampleRecord], vertices: usize) -> Result<DataFrame> {
    if vertices == 0 {
        return Err(Error::invalid("samples table", "0 vertices per mesh"));
    }
    for r in rows {
        let bad = if r.verts.len() != 3 * vertices {
            Some(("verts", r.verts.len(), 3 * vertices))
        } else if r.landmarks_2d.len() != 2 * LANDMARKS {
            Some(("landmarks_2d", r.landmarks_2d.len(), 2 * LANDMARKS))
        } else {
            None
        };
        if let Some((column, got, want)) = bad {
            return Err(Error::invalid(
                "samples table",
                format!(
                    "sample {}: column '{column}' has {got} values, expected {want}",
                    r.key
                ),
            ));
        }
    }
    let n = rows.len();
    let verts: Vec<f32> = rows.iter().flat_map(|r| r.verts.iter().copied()).collect();
    let rt: Vec<f64> = rows.iter().flat_map(|r| r.rt).collect();
    let landmarks: Vec<f32> = rows
        .iter()
        .flat_map(|r| r.landmarks_2d.iter().copied())
        .collect();
    frame(
        rows,
        [
            fixed_shape("verts", Series::new("".into(), verts), n, vertices, 3)?,
            fixed_shape("R_t", Series::new("".into(), rt), n, 4, 4)?,
            fixed_shape(
                "landmarks_2d",
                Series::new("".into(), landmarks),
                n,
                LANDMARKS,
                2,
            )?,
        ],
    )
}

/// The samples table of `rows` with the given `verts`, `R_t` and `landmarks_2d` columns.
fn frame(rows: &[SampleRecord], fixed: [Column; 3]) -> Result<DataFrame> {
    let [verts, rt, landmarks] = fixed;
    let jpeg: Vec<Option<&[u8]>> = rows.iter().map(|r| r.jpeg.as_deref()).collect();
    let mut jpeg_col = Column::new("jpeg".into(), jpeg);
    if rows.is_empty() {
        jpeg_col = Column::new_empty("jpeg".into(), &DataType::Binary);
    }
    let n = rows.len();
    let columns = vec![
        strings("subject_id", rows.iter().map(|r| r.key.subject_id.as_str())),
        strings(
            "facial_action",
            rows.iter().map(|r| r.key.facial_action.as_str()),
        ),
        strings("img_id", rows.iter().map(|r| r.key.img_id.as_str())),
        strings("split", rows.iter().map(|r| r.split.as_str())),
        strings("image_path", rows.iter().map(|r| r.image_path.as_str())),
        Column::new(
            "image_width".into(),
            rows.iter().map(|r| r.image_width).collect::<Vec<u32>>(),
        ),
        Column::new(
            "image_height".into(),
            rows.iter().map(|r| r.image_height).collect::<Vec<u32>>(),
        ),
        jpeg_col,
        verts,
        rt,
        f64s("yaw_deg", rows.iter().map(|r| r.yaw_deg)),
        f64s("pitch_deg", rows.iter().map(|r| r.pitch_deg)),
        f64s("roll_deg", rows.iter().map(|r| r.roll_deg)),
        f64s("tx_m", rows.iter().map(|r| r.translation_m[0])),
        f64s("ty_m", rows.iter().map(|r| r.translation_m[1])),
        f64s("tz_m", rows.iter().map(|r| r.translation_m[2])),
        landmarks,
        f64s("face_box_x0", rows.iter().map(|r| r.face_box[0])),
        f64s("face_box_y0", rows.iter().map(|r| r.face_box[1])),
        f64s(
            "face_box_side",
            rows.iter().map(|r| r.face_box[2] - r.face_box[0]),
        ),
    ];
    DataFrame::new(n, columns).map_err(|e| Error::invalid("samples table", e.to_string()))
}

/// The samples table as versions before samples format 2 wrote it: `verts`, `R_t` and
/// `landmarks_2d` as variable-length lists (any lengths, unchecked), no key-value
/// metadata. For tests that readers still read such files (and refuse bad widths in
/// them); [`samples_frame`] is what `convert` writes.
#[doc(hidden)]
pub fn samples_frame_format1(rows: &[SampleRecord]) -> Result<DataFrame> {
    let list = |name: &str, leaf: DataType, values: Vec<Series>| {
        if values.is_empty() {
            Column::new_empty(name.into(), &DataType::List(Box::new(leaf)))
        } else {
            Column::new(name.into(), values)
        }
    };
    let series = |v: &[f32]| Series::new("".into(), v);
    frame(
        rows,
        [
            list(
                "verts",
                DataType::Float32,
                rows.iter().map(|r| series(&r.verts)).collect(),
            ),
            list(
                "R_t",
                DataType::Float64,
                rows.iter()
                    .map(|r| Series::new("".into(), r.rt.to_vec()))
                    .collect(),
            ),
            list(
                "landmarks_2d",
                DataType::Float32,
                rows.iter().map(|r| series(&r.landmarks_2d)).collect(),
            ),
        ],
    )
}

/// The Hugging Face `datasets` feature of a column we write, as JSON: `Value` for
/// scalars, `Array2D` with its shape for the fixed-shape columns (`N` = `vertices`).
/// What `datasets.Features.to_dict()` gives for the same features.
fn huggingface_feature(dtype: &str, vertices: usize) -> Option<String> {
    let value = |t: &str| format!(r#"{{"dtype": "{t}", "_type": "Value"}}"#);
    let array = |rows: usize, cols: usize, t: &str| {
        format!(r#"{{"shape": [{rows}, {cols}], "dtype": "{t}", "_type": "Array2D"}}"#)
    };
    Some(match dtype {
        "string" | "uint32" | "float64" | "binary" => value(dtype),
        "float32[N,3]" => array(vertices, 3, "float32"),
        "float64[4,4]" => array(4, 4, "float64"),
        "float32[68,2]" => array(LANDMARKS, 2, "float32"),
        _ => return None,
    })
}

/// The key-value metadata of a samples file with `vertices` vertices per mesh: the
/// `huggingface` features record (`{"info": {"features": {...}}}`, the columns in order,
/// as `datasets` writes it) and our own (`ARKIT_METADATA_KEY`).
pub fn huggingface_metadata(vertices: usize) -> Vec<(String, String)> {
    let features: Vec<String> = SAMPLES_COLUMNS
        .iter()
        .map(|c| {
            let f = huggingface_feature(c.dtype, vertices)
                .expect("every samples column has a datasets feature");
            format!("{}: {f}", serde_json::Value::from(c.name))
        })
        .collect();
    vec![
        (
            HUGGINGFACE_METADATA_KEY.to_string(),
            format!(r#"{{"info": {{"features": {{{}}}}}}}"#, features.join(", ")),
        ),
        (
            ARKIT_METADATA_KEY.to_string(),
            format!(r#"{{"table": "samples", "samples_format": {SAMPLES_FORMAT}}}"#),
        ),
    ]
}

/// Writes a samples table (format [`SAMPLES_FORMAT`], with its key-value metadata) to
/// `path` atomically.
pub fn write_samples(path: &Path, rows: &[SampleRecord], vertices: usize) -> Result<()> {
    let mut df = samples_frame(rows, vertices)?;
    write_parquet_with_metadata(path, &mut df, huggingface_metadata(vertices))
}

/// The `errors` rows as a DataFrame with exactly [`ERRORS_COLUMNS`].
pub(crate) fn errors_frame(rows: &[ErrorRecord]) -> Result<DataFrame> {
    let columns = vec![
        strings("subject_id", rows.iter().map(|r| r.key.subject_id.as_str())),
        strings(
            "facial_action",
            rows.iter().map(|r| r.key.facial_action.as_str()),
        ),
        strings("img_id", rows.iter().map(|r| r.key.img_id.as_str())),
        strings("split", rows.iter().map(|r| r.split.as_str())),
        strings("file", rows.iter().map(|r| r.file.as_str())),
        strings("reason", rows.iter().map(|r| r.reason.as_str())),
    ];
    DataFrame::new(rows.len(), columns).map_err(|e| Error::invalid("errors table", e.to_string()))
}

/// A column's name and its two-dimensional shape.
pub(crate) type ColumnShape = (String, [usize; 2]);

/// The shapes a samples file's `huggingface` metadata gives its `Array2D` columns, in
/// order of their names (`None` when the file has no such record: format 1). A record that is
/// not JSON, or a shape that is not two positive integers, is an error naming the file.
pub fn huggingface_shapes(path: &Path) -> Result<Option<Vec<ColumnShape>>> {
    let kv = parquet_key_value_metadata(path)?;
    let Some((_, value)) = kv.iter().find(|(k, _)| k == HUGGINGFACE_METADATA_KEY) else {
        return Ok(None);
    };
    let bad = |m: String| {
        Error::format(
            path,
            format!("key-value metadata '{HUGGINGFACE_METADATA_KEY}': {m}"),
        )
    };
    let v: serde_json::Value = serde_json::from_str(value.as_deref().unwrap_or(""))
        .map_err(|e| bad(format!("not JSON: {e}")))?;
    let features = v["info"]["features"]
        .as_object()
        .ok_or_else(|| bad("no info.features object".into()))?;
    let mut out = Vec::new();
    for (name, f) in features {
        if f["_type"] != "Array2D" {
            continue;
        }
        let shape: Option<Vec<usize>> = f["shape"].as_array().map(|a| {
            a.iter()
                .filter_map(|d| d.as_u64().and_then(|d| usize::try_from(d).ok()))
                .filter(|&d| d > 0)
                .collect()
        });
        match shape.as_deref() {
            Some(&[a, b]) if f["shape"].as_array().is_some_and(|s| s.len() == 2) => {
                out.push((name.clone(), [a, b]))
            }
            _ => {
                return Err(bad(format!(
                    "feature '{name}': shape {} is not two positive integers",
                    f["shape"]
                )));
            }
        }
    }
    Ok(Some(out))
}

fn u32_values(df: &DataFrame, name: &str, path: &Path) -> Result<Vec<u32>> {
    let c = column(df, name, path)?;
    let ca = c.u32().map_err(|e| polars_err(path, e))?;
    Ok(ca.iter().map(|v| v.unwrap_or(0)).collect())
}

/// A fixed-shape column's rows, flat: `(outer, values)` with `height * outer * inner`
/// values. Reads format 2 (`Array(Array(leaf, inner), outer)`) and format 1 (a
/// variable-length list per row, `outer * inner` values each). Every width is checked:
/// `inner`, `outer` against `expect_outer` when given, and in format 1 every row against
/// the first (`N` is fixed per file). Nulls in the lists are errors; null values read as
/// NaN.
fn fixed_values<T: Copy>(
    df: &DataFrame,
    name: &str,
    path: &Path,
    leaf: &DataType,
    inner: usize,
    expect_outer: Option<usize>,
    get: impl Fn(&Series) -> PolarsResult<Vec<T>>,
) -> Result<(usize, Vec<T>)> {
    let c = column(df, name, path)?;
    let bad = |m: String| Error::format(path, format!("column '{name}': {m}"));
    let check_outer = |outer: usize| match expect_outer {
        Some(want) if want != outer => Err(bad(format!(
            "{outer} x {inner} values a row, expected {want} x {inner}"
        ))),
        _ if outer == 0 => Err(bad(format!("0 x {inner} values a row"))),
        _ => Ok(outer),
    };
    let height = df.height();
    match c.dtype() {
        DataType::Array(row, outer) => {
            let DataType::Array(l, w) = row.as_ref() else {
                return Err(bad(format!(
                    "type {}, expected {leaf}[N,{inner}]",
                    c.dtype()
                )));
            };
            if l.as_ref() != leaf || *w != inner {
                return Err(bad(format!(
                    "type {}, expected {leaf}[N,{inner}]",
                    c.dtype()
                )));
            }
            let outer = check_outer(*outer)?;
            let s = c.as_materialized_series();
            let ca = s.array().map_err(|e| polars_err(path, e))?;
            if ca.null_count() > 0 || ca.get_inner().null_count() > 0 {
                return Err(bad("a null row or point".into()));
            }
            let want = height
                .checked_mul(outer)
                .and_then(|v| v.checked_mul(inner))
                .ok_or_else(|| bad("too large".into()))?;
            let values = get(&s.get_leaf_array()).map_err(|e| polars_err(path, e))?;
            if values.len() != want {
                return Err(bad(format!(
                    "{} values in {height} rows of {outer} x {inner}",
                    values.len()
                )));
            }
            Ok((outer, values))
        }
        DataType::List(l) if l.as_ref() == leaf => {
            let ca = c.list().map_err(|e| polars_err(path, e))?;
            let mut values = Vec::new();
            let mut outer = expect_outer;
            for (i, s) in ca.series_iter().enumerate() {
                let row = match s {
                    Some(s) => get(&s).map_err(|e| polars_err(path, e))?,
                    None => return Err(bad(format!("row {i} is null"))),
                };
                let n = outer.unwrap_or(row.len() / inner);
                if n == 0 || row.len() != n * inner {
                    let want = match outer {
                        Some(o) => format!("{}", o * inner),
                        None => format!("a positive multiple of {inner}"),
                    };
                    return Err(bad(format!(
                        "row {i} has {} values, expected {want}",
                        row.len()
                    )));
                }
                outer = Some(n);
                values.extend(row);
            }
            Ok((outer.unwrap_or(0), values))
        }
        other => Err(bad(format!(
            "type {other}, expected {leaf}[N,{inner}] (or list<{leaf}>, before samples format 2)"
        ))),
    }
}

/// Reads a `samples` Parquet file back into records (the inverse of [`samples_frame`]):
/// format 2 (fixed-size lists) or 1 (variable-length lists, files written before). Every
/// width is checked, and `verts` has the same N in every row (the file's `huggingface`
/// record's, when it has one); errors name the file and the column.
pub fn read_samples(path: &Path) -> Result<Vec<SampleRecord>> {
    read_samples_expecting(path, None)
}

/// [`read_samples`], also requiring `vertices` vertices per mesh when given (the
/// topology's).
pub fn read_samples_expecting(path: &Path, vertices: Option<usize>) -> Result<Vec<SampleRecord>> {
    samples_from_frame(&read_parquet(path)?, path, vertices)
}

/// The rows of a `samples` table read as `df` from `path` (which errors name).
pub(crate) fn samples_from_frame(
    df: &DataFrame,
    path: &Path,
    vertices: Option<usize>,
) -> Result<Vec<SampleRecord>> {
    let subject = str_values(df, "subject_id", path)?;
    let action = str_values(df, "facial_action", path)?;
    let img = str_values(df, "img_id", path)?;
    let split = str_values(df, "split", path)?;
    let image_path = str_values(df, "image_path", path)?;
    let width = u32_values(df, "image_width", path)?;
    let height = u32_values(df, "image_height", path)?;
    let jpeg: Vec<Option<Vec<u8>>> = {
        let c = column(df, "jpeg", path)?;
        let ca = c.binary().map_err(|e| polars_err(path, e))?;
        ca.iter().map(|v| v.map(|b| b.to_vec())).collect()
    };
    let f32s = |s: &Series| -> PolarsResult<Vec<f32>> {
        Ok(s.f32()?.iter().map(|v| v.unwrap_or(f32::NAN)).collect())
    };
    let f64s = |s: &Series| -> PolarsResult<Vec<f64>> {
        Ok(s.f64()?.iter().map(|v| v.unwrap_or(f64::NAN)).collect())
    };
    // The N the file's `huggingface` record gives `verts`, which the column must have.
    let recorded = huggingface_shapes(path)?
        .and_then(|shapes| shapes.into_iter().find(|(n, _)| n == "verts"))
        .map(|(_, [n, k])| {
            if k == 3 {
                Ok(n)
            } else {
                Err(Error::format(
                    path,
                    format!("key-value metadata '{HUGGINGFACE_METADATA_KEY}': verts has shape [{n}, {k}], expected [N, 3]"),
                ))
            }
        })
        .transpose()?;
    if let (Some(a), Some(b)) = (recorded, vertices)
        && a != b
    {
        return Err(Error::format(
            path,
            format!("column 'verts': the file records {a} vertices a mesh, expected {b}"),
        ));
    }
    let (n, verts) = fixed_values(
        df,
        "verts",
        path,
        &DataType::Float32,
        3,
        vertices.or(recorded),
        f32s,
    )?;
    let (_, rt) = fixed_values(df, "R_t", path, &DataType::Float64, 4, Some(4), f64s)?;
    let (_, landmarks) = fixed_values(
        df,
        "landmarks_2d",
        path,
        &DataType::Float32,
        2,
        Some(LANDMARKS),
        f32s,
    )?;
    let (yaw, pitch, roll) = (
        f64_values(df, "yaw_deg", path)?,
        f64_values(df, "pitch_deg", path)?,
        f64_values(df, "roll_deg", path)?,
    );
    let (tx, ty, tz) = (
        f64_values(df, "tx_m", path)?,
        f64_values(df, "ty_m", path)?,
        f64_values(df, "tz_m", path)?,
    );
    let (bx, by, bs) = (
        f64_values(df, "face_box_x0", path)?,
        f64_values(df, "face_box_y0", path)?,
        f64_values(df, "face_box_side", path)?,
    );
    let mut out = Vec::with_capacity(df.height());
    for i in 0..df.height() {
        let mut m = [0.0; 16];
        m.copy_from_slice(&rt[16 * i..16 * (i + 1)]);
        out.push(SampleRecord {
            key: SampleKey {
                subject_id: subject[i].clone(),
                facial_action: action[i].clone(),
                img_id: img[i].clone(),
            },
            split: split[i].clone(),
            image_path: image_path[i].clone(),
            image_width: width[i],
            image_height: height[i],
            jpeg: jpeg[i].clone(),
            verts: verts[3 * n * i..3 * n * (i + 1)].to_vec(),
            rt: m,
            yaw_deg: yaw[i],
            pitch_deg: pitch[i],
            roll_deg: roll[i],
            translation_m: [tx[i], ty[i], tz[i]],
            landmarks_2d: landmarks[2 * LANDMARKS * i..2 * LANDMARKS * (i + 1)].to_vec(),
            face_box: [bx[i], by[i], bx[i] + bs[i], by[i] + bs[i]],
        });
    }
    Ok(out)
}

/// Reads only the keys and the split of a `samples` file: `(key, split)` per row.
pub fn read_sample_keys(path: &Path) -> Result<Vec<(SampleKey, String)>> {
    sample_keys_from_frame(&read_parquet_columns(path, &SAMPLE_KEY_COLUMNS)?, path)
}

/// The columns [`read_sample_keys`] reads.
pub(crate) const SAMPLE_KEY_COLUMNS: [&str; 4] = ["subject_id", "facial_action", "img_id", "split"];

/// `(key, split)` per row of `df`, the [`SAMPLE_KEY_COLUMNS`] of the file at `path`.
pub(crate) fn sample_keys_from_frame(
    df: &DataFrame,
    path: &Path,
) -> Result<Vec<(SampleKey, String)>> {
    let names = SAMPLE_KEY_COLUMNS;
    let cols: Vec<Vec<String>> = names
        .iter()
        .map(|c| str_values(df, c, path))
        .collect::<Result<_>>()?;
    Ok(keyed_rows(&cols)
        .map(|(key, i)| (key, cols[3][i].clone()))
        .collect())
}

/// Keys from the first three string columns, with their row numbers.
fn keyed_rows(cols: &[Vec<String>]) -> impl Iterator<Item = (SampleKey, usize)> + '_ {
    (0..cols[0].len()).map(move |i| {
        (
            SampleKey {
                subject_id: cols[0][i].clone(),
                facial_action: cols[1][i].clone(),
                img_id: cols[2][i].clone(),
            },
            i,
        )
    })
}

/// Reads an `errors` Parquet file back into records.
pub fn read_errors(path: &Path) -> Result<Vec<ErrorRecord>> {
    errors_from_frame(&read_parquet(path)?, path)
}

/// The rows of an `errors` table read as `df` from `path` (which errors name).
pub(crate) fn errors_from_frame(df: &DataFrame, path: &Path) -> Result<Vec<ErrorRecord>> {
    let cols: Vec<Vec<String>> = ERRORS_COLUMNS
        .iter()
        .map(|c| str_values(df, c.name, path))
        .collect::<Result<_>>()?;
    Ok(keyed_rows(&cols)
        .map(|(key, i)| ErrorRecord {
            key,
            split: cols[3][i].clone(),
            file: cols[4][i].clone(),
            reason: cols[5][i].clone(),
        })
        .collect())
}

/// The polars type of a schema type name (`N` in a shape, the vertex count, as
/// `vertices`).
pub fn polars_dtype_with(name: &str, vertices: usize) -> Option<DataType> {
    let shaped = |leaf: DataType, outer: usize, inner: usize| {
        DataType::Array(Box::new(DataType::Array(Box::new(leaf), inner)), outer)
    };
    Some(match name {
        "float32[N,3]" => shaped(DataType::Float32, vertices, 3),
        "float64[4,4]" => shaped(DataType::Float64, 4, 4),
        "float32[68,2]" => shaped(DataType::Float32, LANDMARKS, 2),
        _ => return polars_dtype(name),
    })
}

/// The polars type of a schema type name without a vertex count (see
/// [`polars_dtype_with`]).
pub fn polars_dtype(name: &str) -> Option<DataType> {
    Some(match name {
        "string" => DataType::String,
        "uint32" => DataType::UInt32,
        "float64" => DataType::Float64,
        "binary" => DataType::Binary,
        "list<float32>" => DataType::List(Box::new(DataType::Float32)),
        "list<float64>" => DataType::List(Box::new(DataType::Float64)),
        _ => return None,
    })
}
