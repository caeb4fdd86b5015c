//! The Parquet helpers every table of a dataset shares: atomic writes (with key-value
//! and Arrow schema metadata), reads of whole files or columns, row counts, and typed
//! column values with errors that name the file.

use arkit_core::{Error, Result};
use polars::prelude::*;
use std::path::Path;

/// A polars error of the file at `path`.
pub(crate) fn polars_err(path: &Path, e: PolarsError) -> Error {
    Error::format(path, format!("parquet: {e}"))
}

/// Writes a DataFrame as Parquet (zstd, statistics on) to `path` atomically.
pub fn write_parquet(path: &Path, df: &mut DataFrame) -> Result<()> {
    write_parquet_with_metadata(path, df, Vec::new())
}

/// Standard base64 with padding (RFC 4648), as the `ARROW:schema` value is written.
fn base64(bytes: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            *chunk.get(1).unwrap_or(&0),
            *chunk.get(2).unwrap_or(&0),
        ];
        let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
        for k in 0..4 {
            if k <= chunk.len() {
                out.push(ALPHABET[(n >> (18 - 6 * k)) as usize & 63] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// The `ARROW:schema` value for `df` (the Arrow IPC schema message, length-prefixed and
/// base64-encoded, as polars writes it) carrying `metadata` as the schema's own
/// metadata. pyarrow, and so Hugging Face `datasets`, take a Parquet file's schema
/// metadata from this entry, not from the file's other key-value pairs. With no
/// `metadata` it equals what polars writes (a test checks).
pub fn arrow_schema_value(df: &DataFrame, metadata: &[(String, String)]) -> String {
    use polars_arrow::io::ipc::write::{default_ipc_fields, schema_to_bytes};
    let schema = df.schema().to_arrow(CompatLevel::newest());
    let custom: polars_arrow::datatypes::Metadata = metadata
        .iter()
        .map(|(k, v)| (k.as_str().into(), v.as_str().into()))
        .collect();
    let message = schema_to_bytes(
        &schema,
        &default_ipc_fields(schema.iter_values()),
        (!custom.is_empty()).then_some(&custom),
    );
    let mut framed = Vec::with_capacity(message.len() + 8);
    framed.extend_from_slice(&[255, 255, 255, 255]);
    framed.extend_from_slice(&(message.len() as u32).to_le_bytes());
    framed.extend_from_slice(&message);
    base64(&framed)
}

/// [`write_parquet`] with file-level key-value metadata, also written into the
/// `ARROW:schema` entry's schema metadata ([`arrow_schema_value`]) so that Arrow readers
/// see it as the schema's metadata.
pub fn write_parquet_with_metadata(
    path: &Path,
    df: &mut DataFrame,
    metadata: Vec<(String, String)>,
) -> Result<()> {
    let metadata = (!metadata.is_empty()).then(|| {
        let mut kv = vec![(
            "ARROW:schema".to_string(),
            arrow_schema_value(df, &metadata),
        )];
        kv.extend(metadata);
        KeyValueMetadata::from_static(kv)
    });
    arkit_core::atomic_file::write_atomically(path, |w| {
        ParquetWriter::new(w)
            .with_compression(ParquetCompression::Zstd(None))
            .set_parallel(false)
            .with_key_value_metadata(metadata)
            .finish(df)
            .map(|_| ())
            .map_err(|e| polars_err(path, e))
    })
}

/// The file-level key-value metadata of a Parquet file (from its footer).
pub fn parquet_key_value_metadata(path: &Path) -> Result<Vec<(String, Option<String>)>> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut reader = ParquetReader::new(file);
    let meta = reader.get_metadata().map_err(|e| polars_err(path, e))?;
    Ok(meta
        .key_value_metadata()
        .iter()
        .flatten()
        .map(|kv| (kv.key.clone(), kv.value.clone()))
        .collect())
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

pub(crate) fn column<'a>(df: &'a DataFrame, name: &str, path: &Path) -> Result<&'a Column> {
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

/// A table file a reader opened and keeps open: read through it, it gives the bytes the
/// file had when it was opened, even after a writer (`convert --overwrite`, `render`)
/// renamed another file over its name or removed it. So a reader keeps serving the
/// generation it opened instead of mixing it with the next. Read by position only (no
/// shared offset), so threads and forked processes may read it at once.
#[derive(Debug)]
pub struct HeldFile {
    path: std::path::PathBuf,
    file: std::fs::File,
}

impl HeldFile {
    /// Opens `path` to hold it (the error as the operating system gave it).
    pub fn open(path: &Path) -> std::io::Result<HeldFile> {
        Ok(HeldFile {
            path: path.to_path_buf(),
            file: std::fs::File::open(path)?,
        })
    }

    /// The path it was opened at (what errors name).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Its size in bytes.
    pub fn len(&self) -> Result<u64> {
        Ok(self
            .file
            .metadata()
            .map_err(|e| Error::io(&self.path, e))?
            .len())
    }

    /// Whether it holds no byte.
    pub fn is_empty(&self) -> Result<bool> {
        Ok(self.len()? == 0)
    }

    /// `len` bytes from `at`.
    fn bytes(&self, at: u64, len: u64) -> Result<Vec<u8>> {
        let mut buf = vec![0u8; len as usize];
        crate::store::read_at::pread_exact(&self.file, &mut buf, at)
            .map_err(|e| Error::io(&self.path, e))?;
        Ok(buf)
    }

    /// SHA-256 (hex) of its last `bytes` bytes (all of a smaller file).
    pub fn tail_sha256(&self, bytes: u64) -> Result<String> {
        use sha2::{Digest, Sha256};
        let len = self.len()?;
        let start = len.saturating_sub(bytes);
        let tail = self.bytes(start, len - start)?;
        Ok(crate::store::manifest::hex(&Sha256::digest(&tail)))
    }

    /// Reads the whole table, or only `columns`.
    pub fn read_frame(&self, columns: Option<&[&str]>) -> Result<DataFrame> {
        let whole = self.bytes(0, self.len()?)?;
        let mut reader = ParquetReader::new(std::io::Cursor::new(whole));
        if let Some(columns) = columns {
            reader = reader.with_columns(Some(columns.iter().map(|c| c.to_string()).collect()));
        }
        reader.finish().map_err(|e| polars_err(&self.path, e))
    }
}
