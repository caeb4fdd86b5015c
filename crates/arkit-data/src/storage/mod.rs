//! `storage`: where a dataset's bytes live, and the one seam every remote reader goes
//! through.
//!
//! Contract. A dataset is read from a local folder or from an object-store prefix
//! (`s3://bucket/prefix`; `gs://`, `az://` and `https://` where the backend allows):
//! [`DatasetLocation::parse`] tells which. A published dataset (written by
//! [`push`]) has a publication record, `arkit-publication.json`, uploaded last, that
//! names every object of the dataset with its size and SHA-256. [`open_remote`] reads
//! it, copies the small files a reader asks for (the manifests and the Parquet tables)
//! into a local mirror, each checked against the record, and leaves the crop stores'
//! part files where they are: those are read record by record with ranged GETs
//! ([`RemoteObject`], an implementation of [`ReadAt`]), pinned to the ETag the object had
//! when the job opened it, so a dataset replaced under a running job stops it with an
//! error naming the object instead of mixing two generations.
//!
//! Credentials and endpoints come from the standard environment (`AWS_ACCESS_KEY_ID`,
//! `AWS_SECRET_ACCESS_KEY`, `AWS_SESSION_TOKEN`, `AWS_REGION`, `AWS_ENDPOINT_URL`, the
//! instance and container roles through the `object_store` crate) and from the AWS
//! config files (`AWS_PROFILE`, `~/.aws/credentials`, `~/.aws/config`). A secret never
//! appears in a URL printed, an error or a log: [`RemoteStore`] redacts them.
//!
//! Faults: every request is retried with exponential backoff (server errors, resets,
//! time-outs, a body shorter than asked), then fails with an error naming the bucket and
//! the key. A missing object or refused credentials fail at once.
//!
//! Files: `location` (the URL and its redaction), `read_at` (the seam and the local
//! file), `client` (the object-store client, one per process, safe under fork),
//! `cache` (the optional record cache with a size cap), `publication` (the record and
//! `push`), `mirror` (a remote dataset opened).

mod cache;
mod client;
mod location;
mod mirror;
mod publication;
pub(crate) mod read_at;

pub use self::{
    cache::RecordCache,
    client::{RemoteObject, RemoteStore},
    location::{DatasetLocation, RemoteUrl},
    mirror::{MirrorSet, RemoteDataset, RemoteOptions, open_remote},
    publication::{PUBLICATION_FILE, Publication, PublishedObject, PushOptions, PushSummary, push},
    read_at::{LocalFile, ReadAt},
};
