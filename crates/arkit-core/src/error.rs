//! The one error type of the library.
//!
//! Every error that comes from a file names that file and says what is wrong with it
//! (`path: what is wrong`), so that a report of thousands of skipped samples can be read
//! line by line. Errors that are about values rather than files (a pose that cannot
//! project, a bad argument) say which value and why.

use std::fmt;
use std::io;
use std::path::{Path, PathBuf};

/// Result alias used throughout the library.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// What went wrong, and where.
#[derive(Debug)]
pub enum Error {
    /// The operating system could not read or write `path`.
    Io {
        /// The file or directory concerned.
        path: PathBuf,
        /// The underlying I/O error.
        source: io::Error,
    },
    /// `path` was read, but its content is not what it must be (bad header, wrong
    /// shape, missing key, non-finite value, truncated archive, ...).
    Format {
        /// The file concerned (for a member of an archive: `archive.npz:member.npy`).
        path: PathBuf,
        /// What is wrong, in words a user can act on.
        message: String,
    },
    /// A value (not tied to one file) is invalid: a pose that cannot project, a camera
    /// with a non-positive focal length, an argument out of range.
    Invalid {
        /// What was checked (for example `pose` or `--size`).
        what: String,
        /// Why it is rejected.
        message: String,
    },
}

impl Error {
    /// An I/O error on `path`.
    pub fn io(path: impl AsRef<Path>, source: io::Error) -> Self {
        Error::Io {
            path: path.as_ref().to_path_buf(),
            source,
        }
    }

    /// A content error in `path`.
    pub fn format(path: impl AsRef<Path>, message: impl Into<String>) -> Self {
        Error::Format {
            path: path.as_ref().to_path_buf(),
            message: message.into(),
        }
    }

    /// An invalid value named `what`.
    pub fn invalid(what: impl Into<String>, message: impl Into<String>) -> Self {
        Error::Invalid {
            what: what.into(),
            message: message.into(),
        }
    }

    /// The same error, re-attributed to `path` when it was about a value; used when a
    /// value read from a file fails validation, so the report names the file.
    pub fn in_file(self, path: impl AsRef<Path>) -> Self {
        match self {
            Error::Invalid { what, message } => Error::Format {
                path: path.as_ref().to_path_buf(),
                message: format!("{what}: {message}"),
            },
            other => other,
        }
    }

    /// The file this error is about, if any.
    pub fn path(&self) -> Option<&Path> {
        match self {
            Error::Io { path, .. } | Error::Format { path, .. } => Some(path),
            Error::Invalid { .. } => None,
        }
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::Io { path, source } => write!(f, "{}: {}", path.display(), source),
            Error::Format { path, message } => write!(f, "{}: {}", path.display(), message),
            Error::Invalid { what, message } => write!(f, "invalid {what}: {message}"),
        }
    }
}

impl std::error::Error for Error {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Error::Io { source, .. } => Some(source),
            _ => None,
        }
    }
}
