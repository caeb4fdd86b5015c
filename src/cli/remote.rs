//! A dataset argument that may be a bucket URL: what the reading commands (`inspect`,
//! `train`, `predict --dataset`, `eval`) open in its place.

use arkit_core::Result;
use arkit_data::storage::{DatasetLocation, MirrorSet, RemoteDataset, RemoteOptions, open_remote};
use std::path::{Path, PathBuf};

/// The local folder to read for the dataset argument `arg`: the folder itself, or, for
/// a URL (`s3://bucket/prefix`), the local mirror of the published dataset's tables
/// (fetched and checked against its publication record; the mirror lives in the cache
/// folder, `$ARKIT_CACHE_DIR` or `~/.cache/arkit-tool`). The remote dataset is returned
/// too, to be kept while the folder is read.
pub(super) fn dataset_folder(arg: &Path) -> Result<(PathBuf, Option<RemoteDataset>)> {
    let Some(text) = arg.to_str() else {
        return Ok((arg.to_path_buf(), None));
    };
    match DatasetLocation::parse(text)? {
        DatasetLocation::Local(p) => Ok((p, None)),
        DatasetLocation::Remote(url) => {
            let remote = open_remote(&url, &MirrorSet::Tables, &RemoteOptions::default())?;
            eprintln!(
                "reading {url} (its {} objects' tables mirrored in {})",
                remote.publication().objects.len(),
                remote.local_dir().display()
            );
            Ok((remote.local_dir().to_path_buf(), Some(remote)))
        }
    }
}
