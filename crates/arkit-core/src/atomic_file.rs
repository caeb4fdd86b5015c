//! Writing files so that no half-written output is ever left behind.
//!
//! Every file the tool writes goes through [`write_atomically`]: the bytes are written to
//! a temporary name in the same directory (`.NAME.tmp-PID`), flushed, and renamed over
//! the final name. A crash or an error leaves either the old file or the new one, never a
//! truncated one; the temporary is removed on error.
//!
//! A process killed while writing (kill -9, power loss) leaves its temporary behind. The
//! writer holds an exclusive lock on the temporary while it fills it, so
//! [`remove_stale_temporaries`] can tell a live write (locked) from a dead one's
//! left-over (lockable) and removes only the latter; every command that writes a folder
//! calls it on that folder when it starts.
//!
//! [`FolderLock`] is the writer's claim on a whole output folder: a second writer of the
//! same folder is refused with a message naming the folder, instead of interleaving its
//! files with the first's. Locks are the operating system's advisory file locks
//! (`flock`), released when the process ends however it ends, so a killed run never
//! leaves a stale lock.
//!
//! Tested: a failed write leaves nothing; a second lock on a folder is refused while the
//! first is held and granted after it is dropped; a temporary that is locked survives
//! the clean-up and an unlocked one does not.

use crate::error::{Error, Result};
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

/// The temporary name used while `path` is being written.
pub(crate) fn temporary_name(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.tmp-{}", std::process::id()))
}

/// Writes `path` by calling `fill` on a buffered writer over a temporary file, then
/// renaming it into place. Parent directories are created.
pub fn write_atomically<F>(path: &Path, fill: F) -> Result<()>
where
    F: FnOnce(&mut dyn Write) -> Result<()>,
{
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
    }
    let tmp = temporary_name(path);
    let result = (|| {
        let file = fs::File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
        // Held until the rename: marks the temporary as a live write for
        // `remove_stale_temporaries`. A file system without locks still writes.
        let _ = file.try_lock();
        let mut writer = std::io::BufWriter::new(file);
        fill(&mut writer)?;
        let file = writer
            .into_inner()
            .map_err(|e| Error::io(&tmp, e.into_error()))?;
        file.sync_all().map_err(|e| Error::io(&tmp, e))?;
        fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

/// Writes `bytes` to `path` atomically.
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomically(path, |w| w.write_all(bytes).map_err(|e| Error::io(path, e)))
}

/// Whether `name` is a temporary of [`write_atomically`] (`.NAME.tmp-PID`).
pub fn is_temporary_name(name: &str) -> bool {
    name.starts_with('.')
        && name
            .rsplit_once(".tmp-")
            .is_some_and(|(_, pid)| !pid.is_empty() && pid.bytes().all(|b| b.is_ascii_digit()))
}

/// Removes the temporaries that killed writers left in `dir` and, when `recursive`, in
/// its sub-folders. A temporary is left alone when a live writer holds it locked, or
/// when the process its name ends with (`.tmp-PID`) is still running: a writer creates
/// its temporary an instant before it locks it, and another process cleaning the same
/// folder in that instant must not take the file from under it. Returns the files
/// removed. A folder that does not exist has none.
pub fn remove_stale_temporaries(dir: &Path, recursive: bool) -> Result<Vec<PathBuf>> {
    let mut removed = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let entries = match fs::read_dir(&d) {
            Ok(e) => e,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => return Err(Error::io(&d, e)),
        };
        for entry in entries {
            let entry = entry.map_err(|e| Error::io(&d, e))?;
            let path = entry.path();
            let kind = entry.file_type().map_err(|e| Error::io(&path, e))?;
            if kind.is_dir() {
                if recursive {
                    stack.push(path);
                }
                continue;
            }
            let name = entry.file_name();
            let name = name.to_string_lossy();
            if !kind.is_file() || !is_temporary_name(&name) || writer_is_running(&name) {
                continue;
            }
            let Ok(file) = fs::File::open(&path) else {
                continue;
            };
            if file.try_lock().is_ok() {
                fs::remove_file(&path).map_err(|e| Error::io(&path, e))?;
                removed.push(path);
            }
        }
    }
    removed.sort();
    Ok(removed)
}

/// Whether the process named by a temporary's `.tmp-PID` suffix is running (this
/// process included: another of its threads may be writing). Where processes cannot
/// be looked up (no `/proc`), only the lock tells.
fn writer_is_running(name: &str) -> bool {
    let Some((_, pid)) = name.rsplit_once(".tmp-") else {
        return false;
    };
    let Ok(pid) = pid.parse::<u32>() else {
        return false;
    };
    pid == std::process::id()
        || (Path::new("/proc/self").exists() && Path::new(&format!("/proc/{pid}")).exists())
}

/// Opens (creating it and its folder if needed) the lock file `dir/.NAME.lock`.
fn open_lock_file(dir: &Path, name: &str) -> Result<(fs::File, PathBuf)> {
    fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let path = dir.join(format!(".{name}.lock"));
    let file = fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .map_err(|e| Error::io(&path, e))?;
    Ok((file, path))
}

/// An exclusive claim on an output folder (or on one part of it), held until dropped.
#[derive(Debug)]
pub struct FolderLock {
    _file: fs::File,
    path: PathBuf,
}

impl FolderLock {
    /// Takes the lock file `dir/.NAME.lock` (created if needed); `what` says in the error
    /// what holds it (for example `convert`). Refuses at once when another process
    /// holds it.
    pub fn acquire(dir: &Path, name: &str, what: &str) -> Result<Self> {
        let (file, path) = open_lock_file(dir, name)?;
        match file.try_lock() {
            Ok(()) => Ok(Self { _file: file, path }),
            Err(fs::TryLockError::WouldBlock) => Err(Error::format(
                dir,
                format!(
                    "another {what} is writing this folder (it holds {}); wait for it to finish or choose another output folder",
                    path.display()
                ),
            )),
            Err(fs::TryLockError::Error(e)) => Err(Error::io(&path, e)),
        }
    }

    /// Takes the lock file `dir/.NAME.lock`, waiting while another process holds it: for
    /// short critical sections that parallel writers of one folder take in turn.
    pub fn wait(dir: &Path, name: &str) -> Result<Self> {
        let (file, path) = open_lock_file(dir, name)?;
        file.lock().map_err(|e| Error::io(&path, e))?;
        Ok(Self { _file: file, path })
    }

    /// The lock file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn failed_write_leaves_nothing_behind() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.bin");
        let err = write_atomically(&path, |w| {
            w.write_all(b"partial").unwrap();
            Err(Error::invalid("test", "stop half way"))
        });
        assert!(err.is_err());
        assert!(!path.exists());
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn successful_write_replaces_old_content() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub").join("out.bin");
        write_bytes(&path, b"old").unwrap();
        write_bytes(&path, b"new content").unwrap();
        assert_eq!(fs::read(&path).unwrap(), b"new content");
        assert_eq!(fs::read_dir(path.parent().unwrap()).unwrap().count(), 1);
    }

    #[test]
    fn a_second_lock_is_refused_until_the_first_is_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let first = FolderLock::acquire(dir.path(), "convert", "convert").unwrap();
        let err = FolderLock::acquire(dir.path(), "convert", "convert").unwrap_err();
        assert!(
            err.to_string().contains("another convert is writing"),
            "{err}"
        );
        // Another name is another lock.
        let _other = FolderLock::acquire(dir.path(), "render", "render").unwrap();
        drop(first);
        // Free again. A child process that another test forks at this moment holds a
        // copy of the lock's descriptor until its exec closes it (close-on-exec), so the
        // lock may stay taken for that instant: retried for up to 5 s.
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        let second = loop {
            match FolderLock::acquire(dir.path(), "convert", "convert") {
                Ok(lock) => break lock,
                Err(e) if std::time::Instant::now() < deadline => {
                    assert!(e.to_string().contains("another convert is writing"), "{e}");
                    std::thread::sleep(std::time::Duration::from_millis(10));
                }
                Err(e) => panic!("the lock stayed taken after its holder let go: {e}"),
            }
        };
        // `wait` blocks until the holder lets go.
        let (tx, rx) = std::sync::mpsc::channel();
        let d = dir.path().to_path_buf();
        let waiter = std::thread::spawn(move || {
            let _l = FolderLock::wait(&d, "convert").unwrap();
            tx.send(()).unwrap();
        });
        assert!(
            rx.recv_timeout(std::time::Duration::from_millis(100))
                .is_err()
        );
        drop(second);
        rx.recv_timeout(std::time::Duration::from_secs(10)).unwrap();
        waiter.join().unwrap();
    }

    #[test]
    fn stale_temporaries_go_and_live_ones_stay() {
        let dir = tempfile::tempdir().unwrap();
        let sub = dir.path().join("samples");
        fs::create_dir_all(&sub).unwrap();
        // Named after processes that have ended (reaped children).
        let ended = || {
            let mut child = std::process::Command::new("true").spawn().unwrap();
            child.wait().unwrap();
            child.id()
        };
        let stale = sub.join(format!(".part-00000.parquet.tmp-{}", ended()));
        let live = sub.join(format!(".part-00001.parquet.tmp-{}", ended()));
        let kept = sub.join("part-00000.parquet");
        let dotted = sub.join(".hidden");
        for p in [&stale, &live, &kept, &dotted] {
            fs::write(p, b"x").unwrap();
        }
        let holder = fs::File::open(&live).unwrap();
        holder.try_lock().unwrap();
        assert_eq!(
            remove_stale_temporaries(dir.path(), false).unwrap(),
            Vec::<PathBuf>::new()
        );
        assert_eq!(
            remove_stale_temporaries(dir.path(), true).unwrap(),
            vec![stale.clone()]
        );
        assert!(!stale.exists() && live.exists() && kept.exists() && dotted.exists());
        drop(holder);
        assert_eq!(
            remove_stale_temporaries(dir.path(), true).unwrap(),
            vec![live]
        );
        assert!(
            remove_stale_temporaries(&dir.path().join("absent"), true)
                .unwrap()
                .is_empty()
        );
    }

    #[test]
    fn a_running_writers_temporary_stays_before_it_is_locked() {
        // A writer creates its temporary an instant before it locks it; a cleaner in
        // that instant sees an unlocked file named after a running process.
        let dir = tempfile::tempdir().unwrap();
        let mut writer = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        let theirs = dir.path().join(format!(".a.parquet.tmp-{}", writer.id()));
        let ours = temporary_name(&dir.path().join("b.parquet"));
        for p in [&theirs, &ours] {
            fs::write(p, b"x").unwrap();
        }
        assert!(
            remove_stale_temporaries(dir.path(), false)
                .unwrap()
                .is_empty()
        );
        assert!(theirs.exists() && ours.exists());
        writer.kill().unwrap();
        writer.wait().unwrap();
        assert_eq!(
            remove_stale_temporaries(dir.path(), false).unwrap(),
            vec![theirs]
        );
        assert!(ours.exists());
    }

    #[test]
    fn temporary_names_are_recognised() {
        let t = temporary_name(Path::new("/a/b/part-00001.parquet"));
        assert!(is_temporary_name(&t.file_name().unwrap().to_string_lossy()));
        for n in [
            "part.parquet",
            ".hidden",
            ".x.tmp-",
            ".x.tmp-12a",
            "x.tmp-12",
        ] {
            assert!(!is_temporary_name(n), "{n}");
        }
    }
}
