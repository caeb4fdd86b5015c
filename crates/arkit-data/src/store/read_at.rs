//! `read_at`: the seam the crop store's reader reads through ([`ReadAt`]), and its local
//! implementation ([`LocalFile`], positional reads of an open file). The remote one is
//! `crate::storage::RemoteObject`, which `storage` implements on top of this seam.

use arkit_core::{Error, Result};
use std::fmt::Debug;
use std::fs::File;
use std::path::{Path, PathBuf};

/// Bytes read by position from one file or object of a known length. Implementations
/// are safe to share between threads and, for [`LocalFile`], forked processes (a
/// remote object makes its client again in a forked child).
pub trait ReadAt: Send + Sync + Debug + std::any::Any {
    /// What errors name: the file's path, or the object's URL without secrets.
    fn name(&self) -> &Path;

    /// Its length in bytes, as found when it was opened.
    fn len(&self) -> u64;

    /// Whether it is empty.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Exactly `buf.len()` bytes from `offset`; an error naming it otherwise (a short
    /// read is an error, never a short buffer).
    fn read_exact_at(&self, buf: &mut [u8], offset: u64) -> Result<()>;

    /// The bytes of each span `(offset, length)`, in order. A remote object fetches them
    /// concurrently; the default reads them one after another.
    fn read_spans(&self, spans: &[(u64, u64)]) -> Result<Vec<Vec<u8>>> {
        spans
            .iter()
            .map(|&(at, len)| {
                let mut buf = vec![0u8; len as usize];
                self.read_exact_at(&mut buf, at)?;
                Ok(buf)
            })
            .collect()
    }

    /// Forgets what a cache holds of the span `(offset, length)` (a record that failed
    /// its checks is then fetched again). Nothing to do for a local file.
    fn forget(&self, _offset: u64, _len: u64) {}

    /// Whether reads go over a network (and a failed check is worth one more fetch).
    fn is_remote(&self) -> bool {
        false
    }

    /// The spans `(source, offset, length)` of several sources of this one's kind, read
    /// together (a remote object's go out concurrently: one ranged GET a span); in
    /// order. The default reads them one after another.
    fn read_across(&self, wanted: &[(&dyn ReadAt, u64, u64)]) -> Result<Vec<Vec<u8>>> {
        wanted
            .iter()
            .map(|&(source, at, len)| Ok(source.read_spans(&[(at, len)])?.pop().expect("one span")))
            .collect()
    }
}

/// A local file opened for positional reads (`pread`).
#[derive(Debug)]
pub struct LocalFile {
    file: File,
    path: PathBuf,
    len: u64,
}

impl LocalFile {
    /// Opens `path`; an error naming it.
    pub fn open(path: &Path) -> Result<Self> {
        let file = File::open(path).map_err(|e| Error::io(path, e))?;
        let len = file.metadata().map_err(|e| Error::io(path, e))?.len();
        Ok(LocalFile {
            file,
            path: path.to_path_buf(),
            len,
        })
    }
}

impl ReadAt for LocalFile {
    fn name(&self) -> &Path {
        &self.path
    }

    fn len(&self) -> u64 {
        self.len
    }

    fn read_exact_at(&self, buf: &mut [u8], offset: u64) -> Result<()> {
        pread_exact(&self.file, buf, offset).map_err(|e| Error::io(&self.path, e))
    }
}

/// `pread` of exactly `buf.len()` bytes at `offset` (positional: safe to share the file
/// between threads and forked processes).
pub(crate) fn pread_exact(file: &File, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
    #[cfg(unix)]
    {
        std::os::unix::fs::FileExt::read_exact_at(file, buf, offset)
    }
    #[cfg(windows)]
    {
        let mut done = 0;
        while done < buf.len() {
            let n = std::os::windows::fs::FileExt::seek_read(
                file,
                &mut buf[done..],
                offset + done as u64,
            )?;
            if n == 0 {
                return Err(std::io::ErrorKind::UnexpectedEof.into());
            }
            done += n;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_local_file_reads_spans_and_refuses_reads_past_its_end() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f.bin");
        std::fs::write(&path, (0u8..100).collect::<Vec<_>>()).unwrap();
        let f = LocalFile::open(&path).unwrap();
        assert_eq!(f.len(), 100);
        let spans = f.read_spans(&[(10, 3), (97, 3)]).unwrap();
        assert_eq!(spans, vec![vec![10, 11, 12], vec![97, 98, 99]]);
        let mut buf = [0u8; 4];
        let err = f.read_exact_at(&mut buf, 98).unwrap_err().to_string();
        assert!(err.contains("f.bin"), "{err}");
    }
}
