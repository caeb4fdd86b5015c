//! `reader`: an opened store ([`CropStore`]): its manifest and every part file's header
//! and index checked when it is opened, each record read with two positional reads and
//! checked ([`super::records::StoredRecord::from_bytes`]) before anything of it is
//! decoded. Uses `format`, `manifest`, `records` and `mesh_codec`.

use super::format::{
    FOOTER_BYTES, HEADER_BYTES, INDEX_MAGIC, MANIFEST_FILE, MAX_KEY_BYTES, header_mismatch, margin,
    max_window_bytes, record_prefix, shard_file_name,
};
use super::manifest::{CropStoreManifest, read_manifest};
use super::mesh_codec::max_mesh_bytes;
use super::records::StoredRecord;
use crate::crop::RuleSet;
use crate::store::{LocalFile, ReadAt};
use arkit_core::{Error, Result};
use std::path::{Path, PathBuf};

/// The largest record a store accepts: the largest window and the largest mesh.
fn max_record_bytes(size: u32, vertex_count: usize, key_bytes: usize) -> u64 {
    (record_prefix(key_bytes) + max_window_bytes(size) + max_mesh_bytes(vertex_count)) as u64
}

/// An opened store: its manifest and, per samples shard, its part file and record
/// offsets. Nothing read is trusted before it is checked, and nothing is served from
/// another place than the one asked for: [`CropStore::open`] checks the manifest
/// against the dataset (its fingerprint, [`crate::store::manifest::dataset_fingerprint`]:
/// the checksums of its samples shards, so a store of another or a re-converted dataset
/// is refused, never served stale), the rules, `S` and `V` the loader asks for, and
/// every file's header and record index (a part of another store, of another dataset or
/// of another shard, swapped or renamed, is refused by name; a truncated part or a
/// damaged index when the store is opened); [`CropStore::read`] checks each record, in
/// training and in evaluation alike. Reads are positional (`pread` of a local file, or a
/// ranged GET of an object, through [`ReadAt`]): a store is safe to share between
/// threads and forked processes.
#[derive(Debug)]
pub struct CropStore {
    dir: PathBuf,
    manifest: CropStoreManifest,
    /// Per samples shard index, its file, path and record offsets (`records + 1`).
    files: Vec<Option<PartFile>>,
}

/// One opened `part-K.bin`: the file, its path (which errors name) and its record
/// offsets (`records + 1`).
#[derive(Debug)]
struct PartFile {
    file: Box<dyn ReadAt>,
    path: PathBuf,
    offsets: Vec<u64>,
}

impl PartFile {
    /// Opens the part file `path` of samples shard `index` (`records` records) of the
    /// store `manifest`: its header checked first (a file of another store, dataset or
    /// shard is named as such, whatever its length), then its index ([`read_index`]).
    fn open(
        file: Box<dyn ReadAt>,
        manifest: &CropStoreManifest,
        index: usize,
        records: usize,
    ) -> Result<PartFile> {
        let path = file.name().to_path_buf();
        let len = file.len();
        let mut head = [0u8; HEADER_BYTES as usize];
        if len >= HEADER_BYTES {
            file.read_exact_at(&mut head, 0)?;
        }
        let want_head = manifest.part_header(index, records)?;
        if len >= HEADER_BYTES && head != want_head {
            return Err(header_mismatch(
                &path,
                &head,
                &want_head,
                &manifest.dataset_fingerprint,
            ));
        }
        if len < HEADER_BYTES {
            return Err(Error::format(
                &path,
                format!(
                    "{len} bytes, shorter than a header: the file is truncated or not this store's"
                ),
            ));
        }
        let offsets = read_index(&*file, &path, len, records, manifest)?;
        Ok(PartFile {
            file,
            path,
            offsets,
        })
    }
}

/// The record offsets of the part file `path` (`len` bytes, `records` records, of the
/// store `manifest`), read from its index and checked: the footer's magic and the
/// index's CRC, offsets that start after the header, increase by at least a record's
/// prefix and at most [`max_record_bytes`], and end where the index starts.
fn read_index(
    file: &dyn ReadAt,
    path: &Path,
    len: u64,
    records: usize,
    manifest: &CropStoreManifest,
) -> Result<Vec<u64>> {
    let index_bytes = 8 * (records as u64 + 1);
    let truncated = |what: &str| {
        Error::format(
            path,
            format!(
                "{len} bytes: {what}; the file is truncated or not this store's (rerun `arkit-tool crops`)"
            ),
        )
    };
    if len < HEADER_BYTES + index_bytes + FOOTER_BYTES {
        return Err(truncated("too short for its header, index and footer"));
    }
    // The index and the footer after it, in one read (one request from a bucket).
    let index_at = len - FOOTER_BYTES - index_bytes;
    let mut index = vec![0u8; (index_bytes + FOOTER_BYTES) as usize];
    file.read_exact_at(&mut index, index_at)?;
    let footer = index.split_off(index_bytes as usize);
    if &footer[..8] != INDEX_MAGIC {
        return Err(truncated("no index footer at its end"));
    }
    if crc32fast::hash(&index).to_le_bytes() != footer[8..12] {
        return Err(Error::format(
            path,
            "its record index's CRC does not match (the file is damaged); rerun `arkit-tool crops`",
        ));
    }
    let offsets: Vec<u64> = index
        .chunks_exact(8)
        .map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes")))
        .collect();
    let (least, most) = (
        record_prefix(manifest.key_bytes) as u64,
        max_record_bytes(manifest.img_size, manifest.vertex_count, manifest.key_bytes),
    );
    let ok = offsets[0] == HEADER_BYTES
        && offsets[records] == index_at
        && offsets
            .windows(2)
            .all(|p| p[1] >= p[0] + least && p[1] - p[0] <= most);
    if !ok {
        return Err(Error::format(
            path,
            format!(
                "its record index does not fit the file (records of {least}..={most} bytes from byte {HEADER_BYTES} to the index at {index_at}); rerun `arkit-tool crops`"
            ),
        ));
    }
    Ok(offsets)
}

/// Recomputes, in the bytes `part` of a part file of `records` records, the CRC of each
/// record its index delimits (where the offsets lie in the file and increase) and the
/// index's CRC in the footer; nothing else is changed, and a file too short for its
/// index and footer is left as it is. For the fuzz entries (`crate::fuzz_entry`), which
/// use it to reach the checks and decoders behind the CRCs with mutated records (a
/// hostile file can carry valid CRCs).
pub(crate) fn reseal_part(part: &mut [u8], records: usize) {
    let len = part.len() as u64;
    let index_bytes = 8 * (records as u64 + 1);
    if len < HEADER_BYTES + index_bytes + FOOTER_BYTES {
        return;
    }
    let index_at = (len - FOOTER_BYTES - index_bytes) as usize;
    let offsets: Vec<u64> = part[index_at..index_at + index_bytes as usize]
        .chunks_exact(8)
        .map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes")))
        .collect();
    for w in offsets.windows(2) {
        let (a, b) = (w[0], w[1]);
        if a.checked_add(4).is_some_and(|a4| a4 <= b) && b <= index_at as u64 {
            let r = &mut part[a as usize..b as usize];
            let crc = crc32fast::hash(&r[4..]);
            r[..4].copy_from_slice(&crc.to_le_bytes());
        }
    }
    let crc = crc32fast::hash(&part[index_at..index_at + index_bytes as usize]);
    let at = (len - FOOTER_BYTES) as usize + 8;
    part[at..at + 4].copy_from_slice(&crc.to_le_bytes());
}

/// Checks the store manifest `m` (read from `mpath`) against what the loader asks for
/// (rule set `rules`, crop side `img_size`, meshes of `vertex_count` vertices), its key
/// field's width against [`MAX_KEY_BYTES`] and its dataset fingerprint's form (64
/// lower-case hex digits, as every part header holds it): what [`CropStore::open`]
/// checks of the manifest alone, before its dataset and files.
pub(crate) fn check_for_loader(
    m: &CropStoreManifest,
    mpath: &Path,
    rules: RuleSet,
    img_size: u32,
    vertex_count: usize,
) -> Result<()> {
    let expect = |what: &str, found: String, want: String| -> Result<()> {
        if found == want {
            Ok(())
        } else {
            Err(Error::format(
                mpath,
                format!(
                    "{what} is {found}, the loader needs {want}: make a store for it with `arkit-tool crops`"
                ),
            ))
        }
    };
    expect("compat", m.rules.to_string(), rules.to_string())?;
    expect("img_size", m.img_size.to_string(), img_size.to_string())?;
    expect("margin", m.margin.to_string(), margin(img_size).to_string())?;
    expect(
        "vertex_count",
        m.vertex_count.to_string(),
        vertex_count.to_string(),
    )?;
    if m.key_bytes == 0 || m.key_bytes > MAX_KEY_BYTES || !m.key_bytes.is_multiple_of(8) {
        return Err(Error::format(
            mpath,
            format!(
                "key_bytes is {}, not a multiple of 8 in 8..={MAX_KEY_BYTES}",
                m.key_bytes
            ),
        ));
    }
    let fp = &m.dataset_fingerprint;
    if fp.len() != 64
        || !fp
            .bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
    {
        return Err(Error::format(
            mpath,
            format!("dataset_fingerprint '{fp}' is not 64 lower-case hex digits"),
        ));
    }
    Ok(())
}

impl CropStore {
    /// Opens the store in `dir` for `dataset`, crops of rule set `rules` and side
    /// `img_size`, meshes of `vertex_count` vertices; every check of [`CropStore`]'s
    /// docs but the records'.
    pub fn open(
        dir: &Path,
        dataset: &crate::store::dataset::Dataset,
        rules: RuleSet,
        img_size: u32,
        vertex_count: usize,
    ) -> Result<Self> {
        let open_part = |file: &str| -> Result<Box<dyn ReadAt>> {
            Ok(Box::new(LocalFile::open(&dir.join(file))?))
        };
        Self::open_with(dir, &open_part, dataset, rules, img_size, vertex_count)
    }

    /// [`CropStore::open`] with the part files opened by `open_part` (a file name in
    /// the store's folder to its reader): local files, or objects in a bucket
    /// (`RemoteDataset::open_crop_store`).
    pub(crate) fn open_with(
        dir: &Path,
        open_part: &dyn Fn(&str) -> Result<Box<dyn ReadAt>>,
        dataset: &crate::store::dataset::Dataset,
        rules: RuleSet,
        img_size: u32,
        vertex_count: usize,
    ) -> Result<Self> {
        let manifest = read_manifest(dir)?;
        let mpath = dir.join(MANIFEST_FILE);
        check_for_loader(&manifest, &mpath, rules, img_size, vertex_count)?;
        let fingerprint = crate::store::manifest::dataset_fingerprint(dataset.manifest());
        if manifest.dataset_fingerprint != fingerprint {
            return Err(Error::format(
                &mpath,
                format!(
                    "made from another dataset than {} (or before it was converted again): run `arkit-tool crops` again",
                    dataset.dir().display()
                ),
            ));
        }
        let shards = dataset.shards();
        let mut files: Vec<Option<PartFile>> =
            (0..shards.iter().map(|s| s.index + 1).max().unwrap_or(0))
                .map(|_| None)
                .collect();
        for s in shards {
            let entry = manifest
                .shards
                .iter()
                .find(|c| c.index == s.index)
                .ok_or_else(|| {
                    Error::format(&mpath, format!("no file for samples shard {}", s.index))
                })?;
            if entry.records != s.rows || entry.file != shard_file_name(s.index) {
                return Err(Error::format(
                    &mpath,
                    format!(
                        "shard {}: {} records in '{}', the dataset has {} rows",
                        s.index, entry.records, entry.file, s.rows
                    ),
                ));
            }
            files[s.index] = Some(PartFile::open(
                open_part(&entry.file)?,
                &manifest,
                s.index,
                entry.records,
            )?);
        }
        Ok(CropStore {
            dir: dir.to_path_buf(),
            manifest,
            files,
        })
    }

    /// The store of one part file, samples shard `shard`'s at `path` (of `records`
    /// records, in the folder `dir`), opened with `manifest`: the part's checks (header
    /// and index), not the manifest's against a dataset. For the tests and the fuzz
    /// entries (`crate::fuzz_entry`); `shard` is the caller's, as a dataset's shard
    /// index is (bounded by [`crate::store::manifest::MAX_SHARDS`]).
    pub(crate) fn of_part(
        dir: &Path,
        manifest: &CropStoreManifest,
        path: &Path,
        shard: usize,
        records: usize,
    ) -> Result<Self> {
        let part = PartFile::open(Box::new(LocalFile::open(path)?), manifest, shard, records)?;
        let mut files: Vec<Option<PartFile>> = (0..shard).map(|_| None).collect();
        files.push(Some(part));
        Ok(CropStore {
            dir: dir.to_path_buf(),
            manifest: manifest.clone(),
            files,
        })
    }

    /// Whether its part files are read from a bucket.
    pub fn is_remote(&self) -> bool {
        self.files.iter().flatten().any(|p| p.file.is_remote())
    }

    /// The store folder (for a store in a bucket: its local mirror).
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Its manifest.
    pub fn manifest(&self) -> &CropStoreManifest {
        &self.manifest
    }

    /// Where the record of row `row` of samples shard `shard` lies in its part file:
    /// its first byte and its length.
    pub fn record_span(&self, shard: usize, row: usize) -> Option<(u64, u64)> {
        let o = &self.files.get(shard)?.as_ref()?.offsets;
        (row + 1 < o.len()).then(|| (o[row], o[row + 1] - o[row]))
    }

    /// The record of row `row` of samples shard `shard`, which must be that of sample
    /// `key` (`subject/action/img_id`) of this store's dataset: checked before anything
    /// of it is decoded or returned (its CRC; that it is the record of this dataset,
    /// shard, row and sample, a comparison of a few dozen bytes; its status: a sample
    /// that had no readable image when the store was made is an error naming it and the
    /// recorded reason; that the window's and the mesh's lengths fill the record and are
    /// within their bounds). Its mesh is decoded here, into a buffer of its exact size,
    /// its window when asked for (`StoredRecord::crop_pixels`,
    /// [`StoredRecord::decode`]).
    pub fn read(&self, shard: usize, row: usize, key: &str) -> Result<StoredRecord> {
        let (part, at, len) = self.locate(shard, row)?;
        let m = &self.manifest;
        // `len` was bounded when the index was read. The head (CRC to the lengths) and
        // the rest (the window, then the mesh) read into their own buffers, so a raw
        // window is returned as read, not moved out of the record; a remote record is
        // read in one request and split.
        let prefix = record_prefix(m.key_bytes);
        let head_len = (len as usize).min(prefix);
        if part.file.is_remote() {
            let bytes = part.file.read_spans(&[(at, len)])?.pop().expect("one span");
            return self.check_remote(part, (shard, row, key), (at, len), bytes);
        }
        let mut r = vec![0u8; head_len];
        let mut tail = vec![0u8; len as usize - head_len];
        part.file.read_exact_at(&mut r, at)?;
        part.file.read_exact_at(&mut tail, at + head_len as u64)?;
        StoredRecord::from_bytes(m, &part.path, (shard, row, key), r, tail)
    }

    /// The records of `wanted` (`(shard, row, key)` each), checked as
    /// [`CropStore::read`] checks one; a remote store fetches them concurrently (one
    /// ranged GET a record, many in flight). One result per record, in order.
    pub fn read_many(&self, wanted: &[(usize, usize, &str)]) -> Vec<Result<StoredRecord>> {
        let remote = self
            .files
            .iter()
            .flatten()
            .next()
            .is_some_and(|p| p.file.is_remote());
        if !remote {
            return wanted
                .iter()
                .map(|&(shard, row, key)| self.read(shard, row, key))
                .collect();
        }
        let mut out: Vec<Option<Result<StoredRecord>>> = wanted.iter().map(|_| None).collect();
        let mut by_part: std::collections::BTreeMap<usize, Vec<(usize, u64, u64)>> =
            Default::default();
        for (i, &(shard, row, _)) in wanted.iter().enumerate() {
            match self.locate(shard, row) {
                Ok((_, at, len)) => by_part.entry(shard).or_default().push((i, at, len)),
                Err(e) => out[i] = Some(Err(e)),
            }
        }
        // Every part's records in one go: one ranged GET a record, all in flight together.
        let mut flat: Vec<(usize, usize, u64, u64)> = Vec::new();
        for (shard, items) in by_part {
            flat.extend(items.into_iter().map(|(i, at, len)| (shard, i, at, len)));
        }
        let sources: Vec<(&dyn ReadAt, u64, u64)> = flat
            .iter()
            .map(|&(shard, _, at, len)| {
                let part = self.files[shard].as_ref().expect("located");
                (&*part.file, at, len)
            })
            .collect();
        let fetched = match sources.first() {
            Some(&(first, _, _)) => first.read_across(&sources),
            None => Ok(Vec::new()),
        };
        match fetched {
            Ok(bytes) => {
                for (&(shard, i, at, len), b) in flat.iter().zip(bytes) {
                    let part = self.files[shard].as_ref().expect("located");
                    let (shard, row, key) = wanted[i];
                    out[i] = Some(self.check_remote(part, (shard, row, key), (at, len), b));
                }
            }
            Err(e) => {
                let msg = e.to_string();
                for &(_, i, _, _) in &flat {
                    out[i] = Some(Err(Error::invalid("crop store", msg.clone())));
                }
            }
        }
        out.into_iter().map(|r| r.expect("every record")).collect()
    }

    /// The bytes of the record of row `row` of samples shard `shard`, as stored (not
    /// checked: [`CropStore::record_from_bytes`] checks them).
    pub fn raw_record(&self, shard: usize, row: usize) -> Result<Vec<u8>> {
        let (part, at, len) = self.locate(shard, row)?;
        Ok(part.file.read_spans(&[(at, len)])?.pop().expect("one span"))
    }

    /// `bytes` taken as the record of row `row` of samples shard `shard`, which must be
    /// that of sample `key`: every check of [`CropStore::read`] (length, CRC, dataset,
    /// shard, row and key) before anything of it is decoded.
    pub fn record_from_bytes(
        &self,
        shard: usize,
        row: usize,
        key: &str,
        mut bytes: Vec<u8>,
    ) -> Result<StoredRecord> {
        let (part, _, len) = self.locate(shard, row)?;
        if bytes.len() as u64 != len {
            return Err(Error::format(
                &part.path,
                format!(
                    "record {row}: {} bytes given, the index says {len}",
                    bytes.len()
                ),
            ));
        }
        let head_len = (len as usize).min(record_prefix(self.manifest.key_bytes));
        let tail = bytes.split_off(head_len);
        StoredRecord::from_bytes(&self.manifest, &part.path, (shard, row, key), bytes, tail)
    }

    /// The part, offset and length of row `row` of samples shard `shard`.
    fn locate(&self, shard: usize, row: usize) -> Result<(&PartFile, u64, u64)> {
        let part = self
            .files
            .get(shard)
            .and_then(|f| f.as_ref())
            .ok_or_else(|| Error::invalid("crop store", format!("no samples shard {shard}")))?;
        let (at, len) = self.record_span(shard, row).ok_or_else(|| {
            Error::invalid(
                "crop store",
                format!("{}: no record {row}", part.path.display()),
            )
        })?;
        Ok((part, at, len))
    }

    /// A record fetched whole from a remote part, checked; when its checks fail (a body
    /// damaged on the way, or a damaged cache entry), its cache entry is dropped and it
    /// is fetched once more before the error is returned.
    fn check_remote(
        &self,
        part: &PartFile,
        id: (usize, usize, &str),
        (at, len): (u64, u64),
        mut bytes: Vec<u8>,
    ) -> Result<StoredRecord> {
        let m = &self.manifest;
        let head_len = (len as usize).min(record_prefix(m.key_bytes));
        let tail = bytes.split_off(head_len);
        match StoredRecord::from_bytes(m, &part.path, id, bytes, tail) {
            Ok(r) => Ok(r),
            Err(_) => {
                part.file.forget(at, len);
                let mut again = part.file.read_spans(&[(at, len)])?.pop().expect("one span");
                let tail = again.split_off(head_len);
                StoredRecord::from_bytes(m, &part.path, id, again, tail)
            }
        }
    }
}
