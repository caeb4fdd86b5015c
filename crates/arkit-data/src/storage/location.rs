//! `location`: a dataset argument read as a local folder or an object-store URL, and the
//! URL's printable form (no user, password or query: where a secret could be).

use arkit_core::{Error, Result};
use std::fmt;
use std::path::PathBuf;

/// Where a dataset is: a local folder, or a prefix in an object store.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DatasetLocation {
    /// A folder on a local or shared file system.
    Local(PathBuf),
    /// A prefix in a bucket.
    Remote(RemoteUrl),
}

impl DatasetLocation {
    /// Reads `arg` as a URL when it starts with `s3://`, `s3a://`, `gs://`, `az://`,
    /// `abfs://`, `abfss://`, `http://` or `https://`; as a local folder otherwise
    /// (`file://` URLs too).
    pub fn parse(arg: &str) -> Result<Self> {
        if let Some(rest) = arg.strip_prefix("file://") {
            return Ok(DatasetLocation::Local(PathBuf::from(rest)));
        }
        match RemoteUrl::scheme_of(arg) {
            Some(_) => Ok(DatasetLocation::Remote(RemoteUrl::parse(arg)?)),
            None => Ok(DatasetLocation::Local(PathBuf::from(arg))),
        }
    }

    /// Whether `arg` names an object store (a URL of a scheme [`DatasetLocation::parse`]
    /// reads as remote).
    pub fn is_remote_arg(arg: &str) -> bool {
        RemoteUrl::scheme_of(arg).is_some()
    }
}

/// An object-store URL (`s3://bucket/prefix`), kept whole for the client and printed
/// without the parts that can carry a secret.
#[derive(Clone, PartialEq, Eq)]
pub struct RemoteUrl {
    url: url::Url,
    /// The key prefix inside the bucket, without slashes at either end.
    prefix: String,
}

const SCHEMES: [&str; 8] = ["s3", "s3a", "gs", "az", "abfs", "abfss", "http", "https"];

impl RemoteUrl {
    fn scheme_of(arg: &str) -> Option<&'static str> {
        let (scheme, rest) = arg.split_once("://")?;
        let _ = rest;
        SCHEMES
            .iter()
            .find(|s| s.eq_ignore_ascii_case(scheme))
            .copied()
    }

    /// Parses `arg` (a URL of one of the object-store schemes); an error, printed
    /// without secrets, when it is not one.
    pub fn parse(arg: &str) -> Result<Self> {
        let shown = redact_url_text(arg);
        let url = url::Url::parse(arg)
            .map_err(|e| Error::invalid("dataset URL", format!("{shown}: {e}")))?;
        if Self::scheme_of(arg).is_none() {
            return Err(Error::invalid(
                "dataset URL",
                format!("{shown}: not an object-store URL (s3://, gs://, az://, https://)"),
            ));
        }
        if url.host_str().is_none_or(str::is_empty) {
            return Err(Error::invalid(
                "dataset URL",
                format!("{shown}: no bucket (s3://BUCKET/PREFIX)"),
            ));
        }
        let prefix = url.path().trim_matches('/').to_string();
        Ok(RemoteUrl { url, prefix })
    }

    /// The URL as given (with any query: what the client is built from). Never print
    /// it: use [`RemoteUrl`]'s `Display`.
    pub fn secret_url(&self) -> &url::Url {
        &self.url
    }

    /// The scheme (`s3`, `gs`, ...).
    pub fn scheme(&self) -> &str {
        self.url.scheme()
    }

    /// The bucket (the URL's host).
    pub fn bucket(&self) -> &str {
        self.url.host_str().unwrap_or_default()
    }

    /// The key prefix, without slashes at either end (may be empty).
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    /// The object key of `relative` (a `/`-separated path inside the dataset).
    pub fn key(&self, relative: &str) -> String {
        let relative = relative.trim_start_matches('/');
        if self.prefix.is_empty() {
            relative.to_string()
        } else if relative.is_empty() {
            self.prefix.clone()
        } else {
            format!("{}/{relative}", self.prefix)
        }
    }

    /// This URL with `relative` appended to its prefix.
    pub fn join(&self, relative: &str) -> RemoteUrl {
        let mut url = self.url.clone();
        let key = self.key(relative);
        url.set_path(&format!("/{key}"));
        RemoteUrl { url, prefix: key }
    }

    /// What errors and logs show of the object `relative`: `s3://bucket/prefix/relative`
    /// without user, password or query.
    pub fn shown(&self, relative: &str) -> String {
        let key = self.key(relative);
        let host = self.url.host_str().unwrap_or_default();
        match self.url.port() {
            Some(p) => format!("{}://{host}:{p}/{key}", self.url.scheme()),
            None => format!("{}://{host}/{key}", self.url.scheme()),
        }
    }

    /// [`RemoteUrl::shown`] as a path, for the errors that name a file.
    pub fn shown_path(&self, relative: &str) -> PathBuf {
        PathBuf::from(self.shown(relative))
    }
}

impl fmt::Display for RemoteUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.shown(""))
    }
}

impl fmt::Debug for RemoteUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "RemoteUrl({self})")
    }
}

/// `text` (a URL, perhaps not a valid one) without its user, password and query.
pub(crate) fn redact_url_text(text: &str) -> String {
    let mut out = text
        .split(['?', '#'])
        .next()
        .unwrap_or_default()
        .to_string();
    if let Some((scheme, rest)) = out.split_once("://") {
        let (authority, path) = rest.split_once('/').unwrap_or((rest, ""));
        if let Some((_, host)) = authority.rsplit_once('@') {
            out = format!("{scheme}://{host}/{path}");
        }
    }
    out
}

/// `text` (a message) with the user, password and query of every URL in it removed.
pub(crate) fn redact_url_text_in(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for (i, word) in text.split(' ').enumerate() {
        if i > 0 {
            out.push(' ');
        }
        if word.contains("://") {
            let end = word.find(['"', ')', ',']).unwrap_or(word.len());
            out.push_str(&redact_url_text(&word[..end]));
            out.push_str(&word[end..]);
        } else {
            out.push_str(word);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_and_folders_are_told_apart() {
        assert!(matches!(
            DatasetLocation::parse("s3://b/p/q").unwrap(),
            DatasetLocation::Remote(_)
        ));
        assert!(matches!(
            DatasetLocation::parse("data/arkit").unwrap(),
            DatasetLocation::Local(_)
        ));
        assert_eq!(
            DatasetLocation::parse("file:///tmp/x").unwrap(),
            DatasetLocation::Local(PathBuf::from("/tmp/x"))
        );
        assert!(DatasetLocation::parse("s3:///nobucket").is_err());
    }

    #[test]
    fn keys_join_the_prefix_and_nothing_secret_is_shown() {
        let u = RemoteUrl::parse("s3://bucket/a/b/").unwrap();
        assert_eq!(u.prefix(), "a/b");
        assert_eq!(u.key("dataset.json"), "a/b/dataset.json");
        assert_eq!(
            u.join("crops/x").key("part-0.bin"),
            "a/b/crops/x/part-0.bin"
        );
        let root = RemoteUrl::parse("s3://bucket").unwrap();
        assert_eq!(root.key("dataset.json"), "dataset.json");
        let secret = RemoteUrl::parse("https://user:pw@host.example/c/d?sig=SECRET").unwrap();
        let shown = secret.to_string();
        assert!(
            !shown.contains("SECRET") && !shown.contains("pw"),
            "{shown}"
        );
        assert_eq!(shown, "https://host.example/c/d");
        assert_eq!(
            redact_url_text("az://k:s@acct/x?sv=1&sig=abc"),
            "az://acct/x"
        );
        assert_eq!(
            redact_url_text_in("error for (https://h/k?sig=abc), retry"),
            "error for (https://h/k), retry"
        );
    }
}
