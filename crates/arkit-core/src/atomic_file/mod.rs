//! Writing files so that no half-written output is ever left behind.
//!
//! Every file the tool writes goes through [`write_atomically`]: the bytes are written to
//! a temporary name in the same directory (`.NAME.tmp-TOKEN`, TOKEN random), flushed,
//! and renamed over the final name. A crash or an error leaves either the old file or
//! the new one, never a truncated one; the temporary is removed on error.
//!
//! A process killed while writing (kill -9, power loss) leaves its temporary behind.
//! Who owns a temporary is proved by a lock its writer holds from the instant it exists,
//! never by a process id (`ownership`'s docs): [`remove_stale_temporaries`] removes only
//! what no live writer holds, whether the writer was reaped, left a zombie, ran in
//! another PID namespace or on another node of a shared folder. Every command that
//! writes a folder calls it on that folder when it starts; [`leftovers`] lists them for
//! `inspect` and `arkit-tool clean`.
//!
//! [`FolderLock`] is the writer's claim on a whole output folder: a second writer of the
//! same folder is refused with a message naming the folder, instead of interleaving its
//! files with the first's. Locks are the operating system's advisory file locks
//! (`flock`), released when the process ends however it ends, so a killed run never
//! leaves a stale lock.
//!
//! Tested: a failed write leaves nothing; a second lock on a folder is refused while the
//! first is held and granted after it is dropped; a temporary that is locked survives
//! the clean-up and an unlocked one does not, whatever process its name names.

mod ownership;

pub use ownership::{
    Leftover, LockSupport, TemporaryDir, leftovers, lock_support, remove_all_temporaries,
};

use crate::error::{Error, Result};
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

/// A fresh temporary name for `path` (`.NAME.tmp-TOKEN` beside it). It names nothing
/// owned: writers make their temporaries with [`write_atomically`],
/// [`create_temporary`] or [`TemporaryDir`].
#[cfg(test)]
fn temporary_name(path: &Path) -> PathBuf {
    ownership::fresh_name(path)
}

/// Creates the temporary file of `path` (`.NAME.tmp-TOKEN` beside it; the folder must
/// exist), owned by the returned handle's lock until it is closed, for a writer that
/// fills it itself (a stream of frames or rows): write through the handle, then
/// [`publish`] it, or remove the temporary on failure. Errors name `path`.
pub fn create_temporary(path: &Path) -> Result<(fs::File, PathBuf)> {
    ownership::create_file(path)
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
    // Locked until the rename: a live write for `remove_stale_temporaries`.
    let (file, tmp) = ownership::create_file(path)?;
    let result = (|| {
        let mut writer = std::io::BufWriter::new(file);
        fill(&mut writer)?;
        // Errors name the file being written, not its temporary.
        let file = writer
            .into_inner()
            .map_err(|e| Error::io(path, e.into_error()))?;
        publish(&file, &tmp, path)
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

/// Publishes the complete temporary `tmp` (open as `file`) under its final name `path`:
/// flushes its bytes to the disk, then renames it over `path`. The one place every
/// writer renames, so a file is never visible under its final name before its last
/// byte is on the disk. Writers whose library writes the temporary itself (the
/// safetensors files) open it and call this.
pub fn publish(file: &fs::File, tmp: &Path, path: &Path) -> Result<()> {
    file.sync_all().map_err(|e| Error::io(path, e))?;
    pause_before_rename(tmp, path);
    fs::rename(tmp, path).map_err(|e| Error::io(path, e))
}

/// Replaces the folder `path` with the complete folder `tmp` (its files each written
/// with [`write_atomically`], so already on the disk), for outputs that must change
/// together (a release's train and test lists): the old folder is renamed aside, `tmp`
/// renamed into place, the old one removed. A reader sees the old folder, the new one,
/// or (in the instant between the two renames, or after a kill there) none, never some
/// files of each. A kill leaves `tmp`, or the old folder aside, owned by `tmp`'s owner
/// file: [`remove_stale_temporaries`] removes them once that writer is gone.
pub fn publish_dir(tmp: TemporaryDir, path: &Path) -> Result<()> {
    pause_before_rename(tmp.path(), path);
    let aside = tmp.aside();
    let had_old = match fs::rename(path, &aside) {
        Ok(()) => true,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => false,
        Err(e) => return Err(Error::io(path, e)),
    };
    fs::rename(tmp.path(), path).map_err(|e| Error::io(path, e))?;
    if had_old {
        fs::remove_dir_all(&aside).map_err(|e| Error::io(&aside, e))?;
    }
    // Its owner file goes last.
    drop(tmp);
    Ok(())
}

/// Publishes a temporary that a library wrote and closed: [`publish`] on it reopened.
pub fn publish_written(tmp: &Path, path: &Path) -> Result<()> {
    let file = fs::File::open(tmp).map_err(|e| Error::io(tmp, e))?;
    publish(&file, tmp, path)
}

/// The environment variable of the test hook in [`publish`]: when set to a non-empty
/// text, a writer whose final path contains it stops for good once that file's
/// temporary is complete and flushed, just before the rename, after printing
/// `ARKIT_PAUSE_BEFORE_RENAME: paused before renaming TMP to PATH` on stderr. For the
/// kill harness (tests/kill_all.rs), which kills the process there; not for users.
pub const PAUSE_BEFORE_RENAME: &str = "ARKIT_PAUSE_BEFORE_RENAME";

/// The test hook of [`PAUSE_BEFORE_RENAME`] (the variable is read once per process).
fn pause_before_rename(tmp: &Path, path: &Path) {
    static PAUSE: std::sync::OnceLock<Option<String>> = std::sync::OnceLock::new();
    let pause = PAUSE.get_or_init(|| {
        std::env::var(PAUSE_BEFORE_RENAME)
            .ok()
            .filter(|s| !s.is_empty())
    });
    if let Some(part) = pause
        && path.to_string_lossy().contains(part.as_str())
    {
        eprintln!(
            "{PAUSE_BEFORE_RENAME}: paused before renaming {} to {}",
            tmp.display(),
            path.display()
        );
        loop {
            std::thread::sleep(std::time::Duration::from_secs(3600));
        }
    }
}

/// The environment variables of the readers' test hook [`reader_pause`]: when
/// `ARKIT_PAUSE_READER` names a point (`opened`: a dataset's manifest read and its
/// shards opened; `reading`: the first rows read through an opened shard), a reader
/// reaching it the first time prints `ARKIT_PAUSE_READER: paused at POINT in DIR` on
/// stderr and waits until the file `ARKIT_RESUME_READER` names exists (at most 300 s).
/// For tests/readers.rs, which replaces the dataset there; not for users.
pub const PAUSE_READER: &str = "ARKIT_PAUSE_READER";
/// See [`PAUSE_READER`].
pub const RESUME_READER: &str = "ARKIT_RESUME_READER";

/// The test hook of [`PAUSE_READER`] at `point`, reading the dataset `dir`.
pub fn reader_pause(point: &str, dir: &Path) {
    static PAUSED: std::sync::Mutex<Vec<String>> = std::sync::Mutex::new(Vec::new());
    static WANTED: std::sync::OnceLock<Option<(String, PathBuf)>> = std::sync::OnceLock::new();
    let wanted = WANTED.get_or_init(|| {
        let point = std::env::var(PAUSE_READER).ok().filter(|s| !s.is_empty())?;
        let resume = std::env::var_os(RESUME_READER)?;
        Some((point, PathBuf::from(resume)))
    });
    let Some((wanted, resume)) = wanted else {
        return;
    };
    if wanted != point {
        return;
    }
    {
        let mut paused = PAUSED.lock().unwrap_or_else(|p| p.into_inner());
        if paused.iter().any(|p| p == point) {
            return;
        }
        paused.push(point.to_string());
    }
    eprintln!("{PAUSE_READER}: paused at {point} in {}", dir.display());
    let start = std::time::Instant::now();
    while !resume.exists() && start.elapsed() < std::time::Duration::from_secs(300) {
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
}

/// Writes `bytes` to `path` atomically.
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomically(path, |w| w.write_all(bytes).map_err(|e| Error::io(path, e)))
}

/// Whether `name` is a temporary of ours: `.NAME.tmp-TOKEN` (a file of
/// [`write_atomically`] or a folder of [`TemporaryDir`]), its owner file
/// (`.NAME.tmp-TOKEN.owner`) or an old folder set aside (`.NAME.tmp-TOKEN.aside`).
pub fn is_temporary_name(name: &str) -> bool {
    ownership::parse(name).is_some()
}

/// Removes the temporaries (files, and the folders of [`TemporaryDir`]) that killed
/// writers left in `dir` and, when `recursive`, in its sub-folders: those whose lock (or
/// owner file's lock) no live process holds, told while the folder's own lock is held
/// exclusively, so a writer making a temporary at that moment waits. Returns what it
/// removed. Where the file system gives no locks it removes nothing and says so on
/// stderr. A folder that does not exist has none.
pub fn remove_stale_temporaries(dir: &Path, recursive: bool) -> Result<Vec<PathBuf>> {
    ownership::remove_abandoned(dir, recursive)
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

/// This process as a lock file names it: `pid PID on HOST: COMMAND LINE`.
fn holder_description() -> String {
    let host = fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "an unknown host".to_string());
    let command: Vec<String> = std::env::args().collect();
    format!(
        "pid {} on {host}: {}",
        std::process::id(),
        command.join(" ")
    )
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
            Ok(()) => Ok(Self::held(file, path)),
            Err(fs::TryLockError::WouldBlock) => Err(Self::refusal(dir, &path, what)),
            Err(fs::TryLockError::Error(e)) => Err(Error::io(&path, e)),
        }
    }

    /// Takes the lock file `dir/.NAME.lock` shared: any number of processes hold it
    /// together (the parts of one conversion), and an exclusive [`FolderLock::acquire`]
    /// of it is refused while one does. Refuses at once while an exclusive holder has
    /// it; `what` names that holder in the error.
    pub fn acquire_shared(dir: &Path, name: &str, what: &str) -> Result<Self> {
        let (file, path) = open_lock_file(dir, name)?;
        match file.try_lock_shared() {
            Ok(()) => Ok(Self::held(file, path)),
            Err(fs::TryLockError::WouldBlock) => Err(Self::refusal(dir, &path, what)),
            Err(fs::TryLockError::Error(e)) => Err(Error::io(&path, e)),
        }
    }

    /// This exclusive lock turned into a shared one (the file stays locked throughout
    /// for everyone who takes it exclusively; a shared taker may get in at the turn).
    pub fn into_shared(self) -> Result<Self> {
        self._file
            .lock_shared()
            .map_err(|e| Error::io(&self.path, e))?;
        Ok(self)
    }

    /// The error for a lock another process holds: the lock file and its holder.
    fn refusal(dir: &Path, path: &Path, what: &str) -> Error {
        let holder = fs::read_to_string(path).unwrap_or_default();
        let holder = holder.trim();
        let holder = if holder.is_empty() {
            "a process that is just starting".to_string()
        } else {
            holder.to_string()
        };
        Error::format(
            dir,
            format!(
                "another {what} is writing this folder: {} is held by {holder}; wait for it to finish or choose another output folder",
                path.display()
            ),
        )
    }

    /// Takes the lock file `dir/.NAME.lock`, waiting while another process holds it: for
    /// short critical sections that parallel writers of one folder take in turn.
    pub fn wait(dir: &Path, name: &str) -> Result<Self> {
        let (file, path) = open_lock_file(dir, name)?;
        file.lock().map_err(|e| Error::io(&path, e))?;
        Ok(Self::held(file, path))
    }

    /// The lock, held: its file now names the holder (`pid PID on HOST: COMMAND`), for
    /// the refusal a second writer gets. The name is a courtesy: a file system that
    /// cannot write it still locks.
    fn held(mut file: fs::File, path: PathBuf) -> Self {
        let _ = file
            .set_len(0)
            .and_then(|()| file.write_all(format!("{}\n", holder_description()).as_bytes()));
        Self { _file: file, path }
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
    fn an_error_creating_the_temporary_names_the_users_file() {
        // A name of 250 bytes is a valid file name; its temporary (`.NAME.tmp-PID`) is
        // longer than the 255 a name may have, so creating it fails.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(format!("{}.json", "a".repeat(245)));
        let e = write_bytes(&path, b"{}").unwrap_err().to_string();
        assert!(e.starts_with(&format!("{}:", path.display())), "{e}");
        assert!(!e.contains(".tmp-"), "{e}");
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
        let message = err.to_string();
        assert!(message.contains("another convert is writing"), "{message}");
        // The refusal names the lock file and its holder (this process).
        assert!(
            message.contains(&first.path().display().to_string())
                && message.contains(&format!("held by pid {} on ", std::process::id())),
            "{message}"
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
    fn an_unlocked_temporary_named_after_a_running_process_goes() {
        // Process ids lie (a zombie, an id given again, another node's id): a
        // temporary named after a running process but locked by nobody is abandoned.
        let dir = tempfile::tempdir().unwrap();
        let mut other = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        let theirs = dir.path().join(format!(".a.parquet.tmp-{}", other.id()));
        let mine = dir
            .path()
            .join(format!(".b.parquet.tmp-{}", std::process::id()));
        for p in [&theirs, &mine] {
            fs::write(p, b"x").unwrap();
        }
        let removed = remove_stale_temporaries(dir.path(), false).unwrap();
        other.kill().unwrap();
        other.wait().unwrap();
        assert_eq!(removed, vec![theirs, mine]);
    }

    #[test]
    fn temporary_names_are_recognised() {
        let t = temporary_name(Path::new("/a/b/part-00001.parquet"));
        assert!(is_temporary_name(&t.file_name().unwrap().to_string_lossy()));
        for n in [".x.tmp-12a", ".x.tmp-12a.owner", ".x.tmp-12a.aside"] {
            assert!(is_temporary_name(n), "{n}");
        }
        for n in [
            "part.parquet",
            ".hidden",
            ".x.tmp-",
            ".x.tmp-12g",
            "x.tmp-12",
            ".x.tmp-12.old",
        ] {
            assert!(!is_temporary_name(n), "{n}");
        }
    }
}
