//! `cache`: an optional local cache of the byte spans read from object storage
//! ([`RecordCache`]), with a size cap, safe for several processes on one node: each
//! entry is written under a temporary name and renamed (readers see a whole entry or
//! none; the temporary is owned by its writer's lock, as every temporary of
//! `arkit_core::atomic_file`, and removed by the next eviction once no process holds
//! it), entries are keyed by the object's URL, size and ETag (a replaced object is
//! never served from an older entry) and checked for their length when read. Each
//! process measures the folder after every sixteenth of the cap it writes and removes the
//! oldest entries (by modification time) down to three quarters of it: the folder stays
//! within the cap with up to four processes writing at once (each may add a sixteenth
//! between its measures).

use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// A folder of cached spans, at most `cap` bytes (see the module's docs).
#[derive(Debug)]
pub struct RecordCache {
    dir: PathBuf,
    cap: u64,
    /// Bytes this process wrote since it last measured the folder.
    written: AtomicU64,
}

impl RecordCache {
    /// A cache in `dir` (made if missing) holding at most `cap` bytes.
    pub fn new(dir: &Path, cap: u64) -> arkit_core::Result<Self> {
        std::fs::create_dir_all(dir).map_err(|e| arkit_core::Error::io(dir, e))?;
        Ok(RecordCache {
            dir: dir.to_path_buf(),
            cap,
            written: AtomicU64::new(0),
        })
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn entry(&self, id: &str, at: u64, len: u64) -> PathBuf {
        let digest = Sha256::digest(format!("{id}@{at}+{len}").as_bytes());
        let hex = crate::store::manifest::hex(&digest[..16]);
        self.dir.join(&hex[..2]).join(&hex[2..])
    }

    /// The span `(at, len)` of the object `id`, if cached whole.
    pub fn get(&self, id: &str, at: u64, len: u64) -> Option<Vec<u8>> {
        let bytes = std::fs::read(self.entry(id, at, len)).ok()?;
        (bytes.len() as u64 == len).then_some(bytes)
    }

    /// Caches `bytes`, the span at `at` of the object `id` (errors are ignored: the
    /// cache only saves requests).
    pub fn put(&self, id: &str, at: u64, bytes: &[u8]) {
        if bytes.len() as u64 > self.cap / 4 {
            return;
        }
        let path = self.entry(id, at, bytes.len() as u64);
        let Some(parent) = path.parent() else { return };
        if std::fs::create_dir_all(parent).is_err() {
            return;
        }
        // Owned by its lock from the instant it exists (`.NAME.tmp-TOKEN`, never a
        // process id): a sweep removes it only once its writer is gone. Not flushed to
        // the disk: a cache entry lost to a power cut costs one request.
        let Ok((mut file, tmp)) = arkit_core::atomic_file::create_temporary(&path) else {
            return;
        };
        let written = std::io::Write::write_all(&mut file, bytes).is_ok();
        if !written || std::fs::rename(&tmp, &path).is_err() {
            let _ = std::fs::remove_file(&tmp);
            return;
        }
        drop(file);
        let w = self
            .written
            .fetch_add(bytes.len() as u64, Ordering::Relaxed)
            + bytes.len() as u64;
        if w > self.cap / 16 {
            self.written.store(0, Ordering::Relaxed);
            self.evict();
        }
    }

    /// Removes the entry of a span that failed its checks.
    pub fn forget(&self, id: &str, at: u64, len: u64) {
        let _ = std::fs::remove_file(self.entry(id, at, len));
    }

    /// The bytes the folder holds now.
    pub fn bytes(&self) -> u64 {
        self.entries().iter().map(|e| e.1).sum()
    }

    fn entries(&self) -> Vec<(PathBuf, u64, std::time::SystemTime)> {
        let mut out = Vec::new();
        let Ok(top) = std::fs::read_dir(&self.dir) else {
            return out;
        };
        for sub in top.flatten() {
            if sub.file_type().is_ok_and(|t| t.is_dir()) {
                // Temporaries whose writer is gone, proved by their free lock.
                let _ = arkit_core::atomic_file::remove_stale_temporaries(&sub.path(), false);
            }
            let Ok(files) = std::fs::read_dir(sub.path()) else {
                continue;
            };
            for f in files.flatten() {
                let Ok(meta) = f.metadata() else { continue };
                if !meta.is_file() {
                    continue;
                }
                let modified = meta.modified().unwrap_or(std::time::UNIX_EPOCH);
                let name = f.file_name();
                if name
                    .to_str()
                    .is_some_and(arkit_core::atomic_file::is_temporary_name)
                {
                    // Being written, or left by a writer killed between its write and
                    // its rename (the sweep below removes those).
                    continue;
                }
                out.push((f.path(), meta.len(), modified));
            }
        }
        out
    }

    /// Removes the oldest entries until the folder holds at most three quarters of the
    /// cap, when it holds more than the cap less a sixteenth (another process removing
    /// the same entry is not an error).
    fn evict(&self) {
        let mut entries = self.entries();
        let mut total: u64 = entries.iter().map(|e| e.1).sum();
        if total <= self.cap - self.cap / 16 {
            return;
        }
        entries.sort_by_key(|e| e.2);
        let target = self.cap / 4 * 3;
        for (path, len, _) in entries {
            if total <= target {
                break;
            }
            let _ = std::fs::remove_file(path);
            total = total.saturating_sub(len);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spans_round_trip_and_the_cap_holds() {
        let dir = tempfile::tempdir().unwrap();
        let cache = RecordCache::new(dir.path(), 64 * 1024).unwrap();
        assert_eq!(cache.get("s3://b/k#1#e", 0, 4), None);
        cache.put("s3://b/k#1#e", 0, b"abcd");
        assert_eq!(
            cache.get("s3://b/k#1#e", 0, 4).as_deref(),
            Some(&b"abcd"[..])
        );
        // Another ETag is another object.
        assert_eq!(cache.get("s3://b/k#1#f", 0, 4), None);
        for i in 0..200u64 {
            cache.put("s3://b/big#1#e", i * 1000, &[7u8; 1000]);
        }
        assert!(cache.bytes() <= 64 * 1024, "{} bytes", cache.bytes());
        cache.forget("s3://b/k#1#e", 0, 4);
        assert_eq!(cache.get("s3://b/k#1#e", 0, 4), None);
    }

    /// A temporary left by a writer that is gone (its lock free) is removed by the next
    /// eviction; one a live writer holds is kept; neither counts as an entry.
    #[test]
    fn eviction_sweeps_abandoned_temporaries_only() {
        let dir = tempfile::tempdir().unwrap();
        let cache = RecordCache::new(dir.path(), 64 * 1024).unwrap();
        cache.put("s3://b/k#1#e", 0, b"abcd");
        let entry = cache.entry("s3://b/k#1#e", 0, 4);
        let (held, held_path) = arkit_core::atomic_file::create_temporary(&entry).unwrap();
        let (gone, gone_path) = arkit_core::atomic_file::create_temporary(&entry).unwrap();
        std::io::Write::write_all(&mut &gone, &[1u8; 10_000]).unwrap();
        drop(gone);
        assert_eq!(cache.bytes(), 4, "temporaries counted as entries");
        assert!(held_path.exists(), "a held temporary was removed");
        assert!(!gone_path.exists(), "an abandoned temporary was kept");
        drop(held);
    }
}
