//! [`S3Server`]: s3s-fs over HTTP/1.1 with SigV4 enforced.

use crate::background::Background;
use std::io;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use hyper_util::rt::TokioIo;

/// A real S3 server (s3s-fs) on `127.0.0.1`, with SigV4 authentication enforced.
///
/// Each bucket is a subfolder of the root directory; objects are files below it
/// (s3s-fs keeps their metadata, such as the ETag, in side files). The server runs
/// on its own thread and tokio runtime and stops, freeing its port, when dropped.
pub struct S3Server {
    pub(crate) root: PathBuf,
    pub(crate) background: Background,
}

impl S3Server {
    /// Serves the directory `root` (which must exist) on `127.0.0.1` at a port the
    /// system picks, accepting only requests signed (AWS SigV4) with this access key
    /// and secret key.
    pub fn start(root: &Path, access_key: &str, secret_key: &str) -> io::Result<S3Server> {
        let backend = crate::backend::Backend::new(root)?;
        let service = {
            let mut builder = s3s::service::S3ServiceBuilder::new(backend);
            builder.set_auth(s3s::auth::SimpleAuth::from_single(access_key, secret_key));
            builder.build()
        };
        let background = Background::start("arkit-s3-server", move |socket| {
            let service = service.clone();
            tokio::spawn(async move {
                let _ = hyper::server::conn::http1::Builder::new()
                    .serve_connection(TokioIo::new(socket), service)
                    .await;
            });
        })?;
        Ok(S3Server {
            root: root.to_path_buf(),
            background,
        })
    }

    /// The server's address (`127.0.0.1:PORT`).
    pub fn addr(&self) -> SocketAddr {
        self.background.addr
    }

    /// The server's endpoint URL, `http://127.0.0.1:PORT` (path-style requests).
    pub fn endpoint(&self) -> String {
        format!("http://{}", self.addr())
    }

    /// The directory served.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Creates the bucket `name` (its folder under the root); creating one that
    /// exists is not an error. The name must be a plain S3 bucket name (lowercase
    /// letters, digits, `-` and `.`, 3 to 63 characters).
    pub fn create_bucket(&self, name: &str) -> io::Result<()> {
        let valid = (3..=63).contains(&name.len())
            && name
                .bytes()
                .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-' || b == b'.')
            && !name.starts_with(['.', '-'])
            && !name.contains("..");
        if !valid {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("not an S3 bucket name: {name:?}"),
            ));
        }
        std::fs::create_dir_all(self.root.join(name))
    }
}

impl std::fmt::Debug for S3Server {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("S3Server")
            .field("addr", &self.addr())
            .field("root", &self.root)
            .finish()
    }
}
