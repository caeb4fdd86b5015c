//! `writer`: a part file written from its records ([`write_shard_file`]), under a
//! temporary name and renamed. Records come from [`super::records::encode_record`];
//! `crops.json` is written last ([`super::manifest::write_manifest`]). What runs it
//! for a whole dataset, holding the folder's lock, is `loader::crops_dataset`. Uses
//! [`super::format`] and [`super::manifest`].

use super::format::{FOOTER_BYTES, HEADER_BYTES, INDEX_MAGIC, shard_file_name};
use super::manifest::{CropShard, CropStoreManifest};
use arkit_core::{Error, Result};
use std::path::Path;

/// Writes `dir/part-K.bin` (atomically) from its records, in row order: the header,
/// the records, their index (`records + 1` offsets from the file's start, the last
/// the index's own) and the footer (its magic and the index's CRC).
pub(crate) fn write_shard_file(
    dir: &Path,
    manifest: &CropStoreManifest,
    index: usize,
    records: &mut dyn Iterator<Item = Result<Vec<u8>>>,
    count: usize,
) -> Result<CropShard> {
    let file = shard_file_name(index);
    let path = dir.join(&file);
    let head = manifest.part_header(index, count)?;
    let mut total = 0;
    arkit_core::atomic_file::write_atomically(&path, |w| {
        w.write_all(&head).map_err(|e| Error::io(&path, e))?;
        let mut offsets = Vec::with_capacity(count + 1);
        let mut at = HEADER_BYTES;
        for r in records {
            let r = r?;
            offsets.push(at);
            at += r.len() as u64;
            w.write_all(&r).map_err(|e| Error::io(&path, e))?;
        }
        if offsets.len() != count {
            return Err(Error::invalid(
                "crop store",
                format!(
                    "{}: {} records for {count} rows",
                    path.display(),
                    offsets.len()
                ),
            ));
        }
        offsets.push(at);
        let index: Vec<u8> = offsets.iter().flat_map(|o| o.to_le_bytes()).collect();
        let mut footer = [0u8; FOOTER_BYTES as usize];
        footer[..8].copy_from_slice(INDEX_MAGIC);
        footer[8..12].copy_from_slice(&crc32fast::hash(&index).to_le_bytes());
        w.write_all(&index).map_err(|e| Error::io(&path, e))?;
        w.write_all(&footer).map_err(|e| Error::io(&path, e))?;
        total = at + index.len() as u64 + FOOTER_BYTES;
        Ok(())
    })?;
    Ok(CropShard {
        index,
        file,
        records: count,
        bytes: total,
    })
}
