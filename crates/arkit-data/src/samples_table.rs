//! The `samples` and `errors` tables that `convert` writes, as Parquet via polars.
//!
//! Schemas are documented, column by column with types and units, in
//! `schemas/samples.json` and `schemas/errors.json`; [`SAMPLES_COLUMNS`] and
//! [`ERRORS_COLUMNS`] are the same lists in code, and a test checks the two agree and
//! that what we write has exactly these columns and types.
//!
//! Every table is keyed by `(subject_id, facial_action, img_id)`, all strings.

use crate::error::{Error, Result};
use crate::release::SampleKey;
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
    /// `list<float32>`, `list<float64>`).
    pub dtype: &'static str,
}

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
        dtype: "list<float32>",
    },
    ColumnSpec {
        name: "R_t",
        dtype: "list<float64>",
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
        dtype: "list<float32>",
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

fn polars_err(path: &Path, e: PolarsError) -> Error {
    Error::format(path, format!("parquet: {e}"))
}

fn list_f32(name: &str, rows: impl Iterator<Item = Vec<f32>>) -> Column {
    let series: Vec<Series> = rows.map(|v| Series::new(PlSmallStr::EMPTY, v)).collect();
    Column::new(name.into(), series)
}

fn list_f64(name: &str, rows: impl Iterator<Item = Vec<f64>>) -> Column {
    let series: Vec<Series> = rows.map(|v| Series::new(PlSmallStr::EMPTY, v)).collect();
    Column::new(name.into(), series)
}

fn strings<'a>(name: &str, rows: impl Iterator<Item = &'a str>) -> Column {
    let v: Vec<&str> = rows.collect();
    Column::new(name.into(), v)
}

fn f64s(name: &str, rows: impl Iterator<Item = f64>) -> Column {
    let v: Vec<f64> = rows.collect();
    Column::new(name.into(), v)
}

/// The `samples` rows as a DataFrame with exactly [`SAMPLES_COLUMNS`].
pub fn samples_frame(rows: &[SampleRecord]) -> Result<DataFrame> {
    let jpeg: Vec<Option<&[u8]>> = rows.iter().map(|r| r.jpeg.as_deref()).collect();
    let mut jpeg_col = Column::new("jpeg".into(), jpeg);
    if rows.is_empty() {
        jpeg_col = Column::new_empty("jpeg".into(), &DataType::Binary);
    }
    let empty_list = |name: &str, inner: DataType| {
        Column::new_empty(name.into(), &DataType::List(Box::new(inner)))
    };
    let (verts, rt, landmarks) = if rows.is_empty() {
        (
            empty_list("verts", DataType::Float32),
            empty_list("R_t", DataType::Float64),
            empty_list("landmarks_2d", DataType::Float32),
        )
    } else {
        (
            list_f32("verts", rows.iter().map(|r| r.verts.clone())),
            list_f64("R_t", rows.iter().map(|r| r.rt.to_vec())),
            list_f32("landmarks_2d", rows.iter().map(|r| r.landmarks_2d.clone())),
        )
    };
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
    DataFrame::new(rows.len(), columns).map_err(|e| Error::invalid("samples table", e.to_string()))
}

/// The `errors` rows as a DataFrame with exactly [`ERRORS_COLUMNS`].
pub fn errors_frame(rows: &[ErrorRecord]) -> Result<DataFrame> {
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

/// Writes a DataFrame as Parquet (zstd, statistics on) to `path` atomically.
pub fn write_parquet(path: &Path, df: &mut DataFrame) -> Result<()> {
    crate::atomic_file::write_atomically(path, |w| {
        ParquetWriter::new(w)
            .with_compression(ParquetCompression::Zstd(None))
            .set_parallel(false)
            .finish(df)
            .map(|_| ())
            .map_err(|e| polars_err(path, e))
    })
}

/// Reads a whole Parquet file.
pub fn read_parquet(path: &Path) -> Result<DataFrame> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    ParquetReader::new(file)
        .finish()
        .map_err(|e| polars_err(path, e))
}

/// Reads only the named columns of a Parquet file (cheap: `verts` and images are not
/// touched).
pub fn read_parquet_columns(path: &Path, columns: &[&str]) -> Result<DataFrame> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    ParquetReader::new(file)
        .with_columns(Some(columns.iter().map(|c| c.to_string()).collect()))
        .finish()
        .map_err(|e| polars_err(path, e))
}

/// Number of rows of a Parquet file, from its footer.
pub fn parquet_row_count(path: &Path) -> Result<usize> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    ParquetReader::new(file)
        .num_rows()
        .map_err(|e| polars_err(path, e))
}

fn column<'a>(df: &'a DataFrame, name: &str, path: &Path) -> Result<&'a Column> {
    df.column(name)
        .map_err(|_| Error::format(path, format!("no column '{name}'")))
}

/// The values of a string column (nulls as empty strings); `path` names the file in errors.
pub fn str_values(df: &DataFrame, name: &str, path: &Path) -> Result<Vec<String>> {
    let c = column(df, name, path)?;
    let ca = c.str().map_err(|e| polars_err(path, e))?;
    Ok(ca
        .iter()
        .map(|v| v.unwrap_or_default().to_string())
        .collect())
}

/// The values of a float64 column (nulls as NaN); `path` names the file in errors.
pub fn f64_values(df: &DataFrame, name: &str, path: &Path) -> Result<Vec<f64>> {
    let c = column(df, name, path)?;
    let ca = c.f64().map_err(|e| polars_err(path, e))?;
    Ok(ca.iter().map(|v| v.unwrap_or(f64::NAN)).collect())
}

fn u32_values(df: &DataFrame, name: &str, path: &Path) -> Result<Vec<u32>> {
    let c = column(df, name, path)?;
    let ca = c.u32().map_err(|e| polars_err(path, e))?;
    Ok(ca.iter().map(|v| v.unwrap_or(0)).collect())
}

fn list_values<T: Copy>(
    df: &DataFrame,
    name: &str,
    path: &Path,
    get: impl Fn(&Series) -> PolarsResult<Vec<T>>,
) -> Result<Vec<Vec<T>>> {
    let c = column(df, name, path)?;
    let ca = c.list().map_err(|e| polars_err(path, e))?;
    ca.series_iter()
        .map(|s| match s {
            Some(s) => get(&s).map_err(|e| polars_err(path, e)),
            None => Ok(Vec::new()),
        })
        .collect()
}

/// Reads a `samples` Parquet file back into records (the inverse of [`samples_frame`]).
pub fn read_samples(path: &Path) -> Result<Vec<SampleRecord>> {
    let df = read_parquet(path)?;
    let subject = str_values(&df, "subject_id", path)?;
    let action = str_values(&df, "facial_action", path)?;
    let img = str_values(&df, "img_id", path)?;
    let split = str_values(&df, "split", path)?;
    let image_path = str_values(&df, "image_path", path)?;
    let width = u32_values(&df, "image_width", path)?;
    let height = u32_values(&df, "image_height", path)?;
    let jpeg: Vec<Option<Vec<u8>>> = {
        let c = column(&df, "jpeg", path)?;
        let ca = c.binary().map_err(|e| polars_err(path, e))?;
        ca.iter().map(|v| v.map(|b| b.to_vec())).collect()
    };
    let verts = list_values(&df, "verts", path, |s| {
        Ok(s.f32()?.iter().map(|v| v.unwrap_or(f32::NAN)).collect())
    })?;
    let rt = list_values(&df, "R_t", path, |s| {
        Ok(s.f64()?.iter().map(|v| v.unwrap_or(f64::NAN)).collect())
    })?;
    let landmarks = list_values(&df, "landmarks_2d", path, |s| {
        Ok(s.f32()?.iter().map(|v| v.unwrap_or(f32::NAN)).collect())
    })?;
    let (yaw, pitch, roll) = (
        f64_values(&df, "yaw_deg", path)?,
        f64_values(&df, "pitch_deg", path)?,
        f64_values(&df, "roll_deg", path)?,
    );
    let (tx, ty, tz) = (
        f64_values(&df, "tx_m", path)?,
        f64_values(&df, "ty_m", path)?,
        f64_values(&df, "tz_m", path)?,
    );
    let (bx, by, bs) = (
        f64_values(&df, "face_box_x0", path)?,
        f64_values(&df, "face_box_y0", path)?,
        f64_values(&df, "face_box_side", path)?,
    );
    let mut out = Vec::with_capacity(df.height());
    for i in 0..df.height() {
        if rt[i].len() != 16 {
            return Err(Error::format(
                path,
                format!("row {i}: R_t has {} values, expected 16", rt[i].len()),
            ));
        }
        let mut m = [0.0; 16];
        m.copy_from_slice(&rt[i]);
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
            verts: verts[i].clone(),
            rt: m,
            yaw_deg: yaw[i],
            pitch_deg: pitch[i],
            roll_deg: roll[i],
            translation_m: [tx[i], ty[i], tz[i]],
            landmarks_2d: landmarks[i].clone(),
            face_box: [bx[i], by[i], bx[i] + bs[i], by[i] + bs[i]],
        });
    }
    Ok(out)
}

/// Reads only the keys and the split of a `samples` file: `(key, split)` per row.
pub fn read_sample_keys(path: &Path) -> Result<Vec<(SampleKey, String)>> {
    let names = ["subject_id", "facial_action", "img_id", "split"];
    let df = read_parquet_columns(path, &names)?;
    let cols: Vec<Vec<String>> = names
        .iter()
        .map(|c| str_values(&df, c, path))
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
    let df = read_parquet(path)?;
    let cols: Vec<Vec<String>> = ERRORS_COLUMNS
        .iter()
        .map(|c| str_values(&df, c.name, path))
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

/// The polars type of a schema type name.
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
