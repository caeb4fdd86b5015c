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

/// What went wrong, and where. New variants may be added: match on [`Error::kind`].
#[derive(Debug)]
#[non_exhaustive]
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

/// The kind of an [`Error`], to match on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum ErrorKind {
    /// The operating system could not read or write a file.
    Io,
    /// A file was read but its content is not what it must be.
    Format,
    /// A value (an option, a pose, a camera) is invalid.
    Invalid,
}

impl Error {
    /// What kind of error this is.
    pub fn kind(&self) -> ErrorKind {
        match self {
            Error::Io { .. } => ErrorKind::Io,
            Error::Format { .. } => ErrorKind::Format,
            Error::Invalid { .. } => ErrorKind::Invalid,
        }
    }

    /// The error's message without the file it names (for tables whose rows already
    /// name the file): the I/O error, the content problem, or `what: why`.
    pub fn reason(&self) -> String {
        match self {
            Error::Io { source, .. } => source.to_string(),
            Error::Format { message, .. } => message.clone(),
            Error::Invalid { what, message } => format!("{what}: {message}"),
        }
    }

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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kind_and_reason_follow_the_variant() {
        let io = Error::io("a.npz", io::Error::new(io::ErrorKind::NotFound, "gone"));
        assert_eq!(
            (io.kind(), io.reason()),
            (ErrorKind::Io, "gone".to_string())
        );
        assert_eq!(io.to_string(), "a.npz: gone");
        assert!(std::error::Error::source(&io).is_some());
        let f = Error::format("b.jpg", "truncated");
        assert_eq!(
            (f.kind(), f.reason().as_str()),
            (ErrorKind::Format, "truncated")
        );
        let v = Error::invalid("--size", "must be positive");
        assert_eq!(v.kind(), ErrorKind::Invalid);
        assert_eq!(v.reason(), "--size: must be positive");
        // A value error re-attributed to the file it came from.
        let r = v.in_file("c.json");
        assert_eq!(r.kind(), ErrorKind::Format);
        assert_eq!(r.path(), Some(Path::new("c.json")));
    }
}
