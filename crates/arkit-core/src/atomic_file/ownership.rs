//! Who owns a temporary, proved by a lock, never by a process id.
//!
//! A temporary is named `.NAME.tmp-TOKEN`, TOKEN 16 random hexadecimal digits (never a
//! process id). It is owned from the instant it exists:
//!
//! - A temporary **file** is locked (`flock`, exclusive) by its writer.
//! - A temporary **folder** (`.NAME.tmp-TOKEN/`, and the old folder a publication sets
//!   aside, `.NAME.tmp-TOKEN.aside/`) is owned through its owner file
//!   `.NAME.tmp-TOKEN.owner`, locked by its writer, made before the folder and removed
//!   after it.
//!
//! A writer makes a temporary (and locks it, or its owner) while it holds a **shared**
//! lock on the folder it is made in; the sweeper holds that folder's lock
//! **exclusively** while it looks. So the sweeper never sees a temporary between its
//! creation and its lock: whatever it finds unlocked is abandoned, and it removes that
//! only. A writer's locks end with its process however it ends (killed, left a zombie by
//! a parent that does not reap it, on another node of a shared file system), and a
//! process id that another process got again changes nothing.
//!
//! Where the file system gives no working locks (some NFS mounts, Lustre without
//! `-o flock`), nothing can be proved abandoned: the sweeper removes nothing and says so
//! once on stderr; `arkit-tool clean --force` removes the leftovers when the user knows
//! no writer runs. [`lock_support`] tells which case a folder is in.

use crate::error::{Error, Result};
use std::fs;
use std::hash::{BuildHasher, Hasher};
use std::path::{Path, PathBuf};

/// The suffix of an owner file.
const OWNER: &str = ".owner";
/// The suffix of a folder set aside by a publication.
const ASIDE: &str = ".aside";

/// What a temporary-named entry is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Role {
    /// `.NAME.tmp-TOKEN`: a file (owned by its own lock) or a folder (by its owner).
    Temporary,
    /// `.NAME.tmp-TOKEN.owner`: the lock file owning the folders of that name.
    Owner,
    /// `.NAME.tmp-TOKEN.aside`: an old folder set aside by a publication.
    Aside,
}

/// The role of the entry named `name`, and the name of its `.NAME.tmp-TOKEN` stem,
/// when it is a temporary of ours (any version: the process ids older versions put
/// after `.tmp-` are digits, so hexadecimal too).
pub(crate) fn parse(name: &str) -> Option<(Role, &str)> {
    if !name.starts_with('.') {
        return None;
    }
    let (stem, role) = if let Some(stem) = name.strip_suffix(OWNER) {
        (stem, Role::Owner)
    } else if let Some(stem) = name.strip_suffix(ASIDE) {
        (stem, Role::Aside)
    } else {
        (name, Role::Temporary)
    };
    let (_, token) = stem.rsplit_once(".tmp-")?;
    (!token.is_empty() && token.bytes().all(|b| b.is_ascii_hexdigit())).then_some((role, stem))
}

/// A fresh token: 64 random bits as 16 hexadecimal digits.
fn token() -> String {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    // Keys from the operating system's randomness (new ones for each `RandomState`),
    // over the time, the process and a counter.
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u64(COUNTER.fetch_add(1, Ordering::Relaxed));
    h.write_u32(std::process::id());
    if let Ok(t) = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH) {
        h.write_u128(t.as_nanos());
    }
    format!("{:016x}", h.finish())
}

/// The `.NAME.tmp-TOKEN` name for `path` with a fresh token.
pub(crate) fn fresh_name(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.tmp-{}", token()))
}

/// The folder `path` is in (`.` for a bare name).
fn folder_of(path: &Path) -> PathBuf {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// A lock on a folder (its own descriptor, `flock`), shared by writers making
/// temporaries and exclusive for the sweeper.
struct FolderSection {
    _dir: Option<fs::File>,
}

impl FolderSection {
    /// The shared lock of `dir`, waited for (sweeps are short). A file system without
    /// locks gives none, and the writer goes on: nothing is swept there.
    fn shared(dir: &Path) -> FolderSection {
        let dir = fs::File::open(dir).ok().filter(|d| d.lock_shared().is_ok());
        FolderSection { _dir: dir }
    }

    /// The exclusive lock of `dir`, waited for; the error when the file system gives
    /// no locks.
    fn exclusive(dir: &Path) -> std::io::Result<FolderSection> {
        let d = fs::File::open(dir)?;
        d.lock()?;
        Ok(FolderSection { _dir: Some(d) })
    }
}

/// Creates the temporary file for `path` (`.NAME.tmp-TOKEN` beside it), locked by the
/// returned handle until it is closed. The folder must exist.
pub(crate) fn create_file(path: &Path) -> Result<(fs::File, PathBuf)> {
    let dir = folder_of(path);
    let _section = FolderSection::shared(&dir);
    let tmp = fresh_name(path);
    let file = fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&tmp)
        .map_err(|e| Error::io(path, e))?;
    // A file system without locks still writes (and its temporaries are not swept).
    let _ = file.try_lock();
    Ok((file, tmp))
}

/// A temporary folder (`.NAME.tmp-TOKEN/` beside the final `NAME`), owned through its
/// locked owner file while this value lives; dropped, it removes what is left of it.
#[derive(Debug)]
pub struct TemporaryDir {
    path: PathBuf,
    owner: PathBuf,
    _lock: fs::File,
}

impl TemporaryDir {
    /// Creates the temporary folder for the final folder (or file) `path`; its parent
    /// folder is created if needed.
    pub fn create(path: &Path) -> Result<TemporaryDir> {
        let dir = folder_of(path);
        fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        let _section = FolderSection::shared(&dir);
        let tmp = fresh_name(path);
        let owner = owner_of(&tmp);
        let lock = fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&owner)
            .map_err(|e| Error::io(path, e))?;
        let _ = lock.try_lock();
        if let Err(e) = fs::create_dir(&tmp) {
            let _ = fs::remove_file(&owner);
            return Err(Error::io(path, e));
        }
        Ok(TemporaryDir {
            path: tmp,
            owner,
            _lock: lock,
        })
    }

    /// The temporary folder.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The name the old folder is set aside under while this one replaces it.
    pub(crate) fn aside(&self) -> PathBuf {
        let mut name = self.path.as_os_str().to_owned();
        name.push(ASIDE);
        PathBuf::from(name)
    }
}

impl Drop for TemporaryDir {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.path);
        let _ = fs::remove_dir_all(self.aside());
        let _ = fs::remove_file(&self.owner);
    }
}

/// The owner file of the temporary folder `tmp` (`.NAME.tmp-TOKEN.owner`).
fn owner_of(stem: &Path) -> PathBuf {
    let mut name = stem.as_os_str().to_owned();
    name.push(OWNER);
    PathBuf::from(name)
}

/// Whether a folder's file system gives working locks, as the sweeper needs them.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum LockSupport {
    /// Locks work: abandoned temporaries are told from live ones and swept.
    Working,
    /// No working locks (the error the file system gave): nothing is swept.
    Missing(String),
}

/// Whether `dir`'s file system gives the locks the sweeper needs (an exclusive lock on
/// the folder itself). A folder that does not exist is asked of its nearest parent.
pub fn lock_support(dir: &Path) -> LockSupport {
    let mut d = dir;
    while !d.exists() {
        match d.parent() {
            Some(p) if !p.as_os_str().is_empty() => d = p,
            _ => break,
        }
    }
    let probe = fs::File::open(d).and_then(|f| match f.try_lock() {
        Ok(()) | Err(fs::TryLockError::WouldBlock) => Ok(()),
        Err(fs::TryLockError::Error(e)) => Err(e),
    });
    match probe {
        Ok(()) => LockSupport::Working,
        Err(e) => LockSupport::Missing(e.to_string()),
    }
}

/// A temporary left in a folder (or being written).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Leftover {
    /// The file or folder.
    pub path: PathBuf,
    /// Its size in bytes (a folder's: the files in it).
    pub bytes: u64,
    /// `Some(true)`: its writer is gone (its lock is free); `Some(false)`: a live writer
    /// holds it; `None`: the file system gives no locks to tell.
    pub abandoned: Option<bool>,
}

/// Whether the lock of the file at `path` is free: `Some(true)` free, `Some(false)`
/// held, `None` no lock to tell (or the file cannot be opened).
fn lock_is_free(path: &Path) -> Option<bool> {
    let file = fs::File::open(path).ok()?;
    match file.try_lock() {
        Ok(()) => Some(true),
        Err(fs::TryLockError::WouldBlock) => Some(false),
        Err(fs::TryLockError::Error(_)) => None,
    }
}

fn size_of(path: &Path) -> u64 {
    let Ok(meta) = fs::symlink_metadata(path) else {
        return 0;
    };
    if !meta.is_dir() {
        return meta.len();
    }
    fs::read_dir(path)
        .map(|entries| entries.flatten().map(|e| size_of(&e.path())).sum())
        .unwrap_or(0)
}

/// The temporaries directly in `dir`, each judged while `dir`'s exclusive section is
/// held (or unjudged, `None`, where the file system gives no locks), and the
/// sub-folders that are not temporaries. The section is returned, held.
fn judge(dir: &Path) -> Result<(Vec<Leftover>, Vec<PathBuf>, Option<FolderSection>)> {
    let entries = match fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Ok((Vec::new(), Vec::new(), None));
        }
        Err(e) => return Err(Error::io(dir, e)),
    };
    let section = FolderSection::exclusive(dir).ok();
    let locks = section.is_some();
    let mut found = Vec::new();
    let mut folders = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| Error::io(dir, e))?;
        let path = entry.path();
        let Ok(kind) = entry.file_type() else {
            continue;
        };
        let name = entry.file_name();
        let name = name.to_string_lossy();
        let Some((role, stem)) = parse(&name) else {
            if kind.is_dir() {
                folders.push(path);
            }
            continue;
        };
        let abandoned = if !locks {
            None
        } else if kind.is_dir() {
            // A folder is owned by its owner file; none left means its writer is gone
            // (the owner is made before the folder and removed after it).
            let owner = owner_of(&dir.join(stem));
            if owner.exists() {
                lock_is_free(&owner)
            } else {
                Some(true)
            }
        } else if kind.is_file() && matches!(role, Role::Temporary | Role::Owner) {
            lock_is_free(&path)
        } else {
            continue;
        };
        found.push(Leftover {
            bytes: size_of(&path),
            path,
            abandoned,
        });
    }
    Ok((found, folders, section))
}

/// The temporaries in `dir` and, when `recursive`, in its sub-folders, sorted by path,
/// each with its size and whether its writer is gone.
pub fn leftovers(dir: &Path, recursive: bool) -> Result<Vec<Leftover>> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let (found, folders, _section) = judge(&d)?;
        out.extend(found);
        if recursive {
            stack.extend(folders);
        }
    }
    out.sort_by(|a, b| a.path.cmp(&b.path));
    Ok(out)
}

/// Removes what [`leftovers`] finds abandoned; returns what it removed. Where the file
/// system gives no locks it removes nothing and says so once on stderr.
pub fn remove_abandoned(dir: &Path, recursive: bool) -> Result<Vec<PathBuf>> {
    let mut removed = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let (found, folders, section) = judge(&d)?;
        if section.is_none() && d.is_dir() {
            warn_no_locks(&d);
        }
        // Folders before their owner files, as a writer removes them.
        let mut found = found;
        found.sort_by_key(|l| !l.path.is_dir());
        for leftover in found {
            if leftover.abandoned == Some(true) && remove_entry(&leftover.path)? {
                removed.push(leftover.path);
            }
        }
        drop(section);
        if recursive {
            stack.extend(folders);
        }
    }
    removed.sort();
    Ok(removed)
}

/// Removes every temporary in `dir` (and its sub-folders when `recursive`), live or
/// not: for a file system without locks, when the user knows no writer runs.
pub fn remove_all_temporaries(dir: &Path, recursive: bool) -> Result<Vec<PathBuf>> {
    let mut removed = Vec::new();
    for leftover in leftovers(dir, recursive)? {
        if remove_entry(&leftover.path)? {
            removed.push(leftover.path);
        }
    }
    Ok(removed)
}

/// Removes the file or folder `path`: `false` when it was already gone.
fn remove_entry(path: &Path) -> Result<bool> {
    let gone = if path.is_dir() {
        fs::remove_dir_all(path)
    } else {
        fs::remove_file(path)
    };
    match gone {
        Ok(()) => Ok(true),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
        Err(e) => Err(Error::io(path, e)),
    }
}

/// Says once per process that `dir` gives no locks, so its leftovers stay.
fn warn_no_locks(dir: &Path) {
    static SAID: std::sync::Once = std::sync::Once::new();
    SAID.call_once(|| {
        let why = match lock_support(dir) {
            LockSupport::Missing(e) => e,
            LockSupport::Working => "the folder could not be locked".to_string(),
        };
        eprintln!(
            "arkit-tool: {}: this file system gives no working locks ({why}): temporaries of killed writers are not removed; run `arkit-tool clean {} --force` when no writer is running",
            dir.display(),
            dir.display()
        );
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_by_role() {
        assert_eq!(
            parse(".a.parquet.tmp-0123456789abcdef"),
            Some((Role::Temporary, ".a.parquet.tmp-0123456789abcdef"))
        );
        assert_eq!(parse(".a.tmp-12"), Some((Role::Temporary, ".a.tmp-12")));
        assert_eq!(
            parse(".list.tmp-ab.owner"),
            Some((Role::Owner, ".list.tmp-ab"))
        );
        assert_eq!(
            parse(".list.tmp-ab.aside"),
            Some((Role::Aside, ".list.tmp-ab"))
        );
        for n in ["a.tmp-12", ".a.tmp-", ".a.tmp-12x", ".hidden", ".a.owner"] {
            assert_eq!(parse(n), None, "{n}");
        }
        let a = fresh_name(Path::new("/d/x.bin"));
        let b = fresh_name(Path::new("/d/x.bin"));
        assert_ne!(a, b);
        let name = a.file_name().unwrap().to_string_lossy().into_owned();
        assert!(name.starts_with(".x.bin.tmp-") && name.len() == ".x.bin.tmp-".len() + 16);
    }

    #[test]
    fn a_free_lock_is_abandoned_whatever_process_its_name_names() {
        let dir = tempfile::tempdir().unwrap();
        // Named after a live process (this one, and PID 1): a name proves nothing.
        let by_name = [
            dir.path().join(format!(".a.tmp-{}", std::process::id())),
            dir.path().join(".b.tmp-1"),
        ];
        for p in &by_name {
            fs::write(p, b"x").unwrap();
        }
        let (live, live_path) = create_file(&dir.path().join("c.bin")).unwrap();
        let kept = TemporaryDir::create(&dir.path().join("lists")).unwrap();
        fs::write(kept.path().join("one.csv"), b"1234").unwrap();
        let found = leftovers(dir.path(), false).unwrap();
        let judged: Vec<(String, Option<bool>)> = found
            .iter()
            .map(|l| {
                (
                    l.path.file_name().unwrap().to_string_lossy().into_owned(),
                    l.abandoned,
                )
            })
            .collect();
        assert_eq!(found.len(), 5, "{judged:?}");
        let held = [
            live_path.clone(),
            kept.path().to_path_buf(),
            owner_of(kept.path()),
        ];
        for l in &found {
            assert_eq!(l.abandoned, Some(!held.contains(&l.path)), "{judged:?}");
        }
        let dir_entry = found.iter().find(|l| l.path == kept.path()).unwrap();
        assert_eq!(dir_entry.bytes, 4);
        let removed = remove_abandoned(dir.path(), false).unwrap();
        assert_eq!(removed, by_name.to_vec());
        assert!(live_path.exists() && kept.path().is_dir());
        // The writers gone: everything is abandoned and goes.
        drop(live);
        let kept_path = kept.path().to_path_buf();
        std::mem::forget(kept); // as a killed writer: its owner file stays, unlocked
        // (the forgotten lock handle leaks: unlock it as the end of a process would).
        let owner = owner_of(&kept_path);
        fs::remove_file(&owner).unwrap();
        fs::write(&owner, b"").unwrap();
        let removed = remove_abandoned(dir.path(), false).unwrap();
        assert_eq!(removed.len(), 3, "{removed:?}");
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn a_folder_without_its_owner_is_abandoned_and_a_dropped_one_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let orphan = dir.path().join(".lists.tmp-00ff");
        fs::create_dir_all(orphan.join("list")).unwrap();
        let aside = dir.path().join(".lists.tmp-00ff.aside");
        fs::create_dir_all(&aside).unwrap();
        assert_eq!(
            remove_abandoned(dir.path(), true).unwrap(),
            vec![orphan, aside]
        );
        let t = TemporaryDir::create(&dir.path().join("sub/lists")).unwrap();
        fs::write(t.path().join("a"), b"1").unwrap();
        drop(t);
        assert_eq!(fs::read_dir(dir.path().join("sub")).unwrap().count(), 0);
    }

    #[test]
    fn the_sweeper_waits_for_a_writer_making_a_temporary() {
        // A writer between creating its temporary and locking it holds the folder's
        // shared lock: the sweeper waits, then finds the temporary locked.
        let dir = tempfile::tempdir().unwrap();
        let tmp = dir.path().join(".x.bin.tmp-abc");
        let section = FolderSection::shared(dir.path());
        assert!(section._dir.is_some());
        fs::write(&tmp, b"x").unwrap(); // created, not yet locked
        let d = dir.path().to_path_buf();
        let (tx, rx) = std::sync::mpsc::channel();
        let sweeper = std::thread::spawn(move || {
            tx.send(remove_abandoned(&d, false).unwrap()).unwrap();
        });
        assert!(
            rx.recv_timeout(std::time::Duration::from_millis(200))
                .is_err(),
            "the sweeper did not wait for the writer's section"
        );
        let lock = fs::File::open(&tmp).unwrap();
        lock.try_lock().unwrap();
        drop(section);
        let removed = rx.recv_timeout(std::time::Duration::from_secs(10)).unwrap();
        sweeper.join().unwrap();
        assert!(removed.is_empty() && tmp.exists());
        drop(lock);
        assert_eq!(remove_abandoned(dir.path(), false).unwrap(), vec![tmp]);
    }

    #[test]
    fn locks_work_here() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(lock_support(dir.path()), LockSupport::Working);
        assert_eq!(
            lock_support(&dir.path().join("not/yet/made")),
            LockSupport::Working
        );
    }
}
