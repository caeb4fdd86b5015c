//! The S3 operations the server answers: s3s-fs for every operation, except object
//! reads (`GetObject`), which are served here with one file read each.
//!
//! s3s-fs 0.14 reads an object through `tokio::fs` in 4 KiB pieces, each piece a hop
//! to a blocking thread, and reads two JSON side files per request. A 45 KiB ranged
//! GET costs it about 17 thread hops and 12 socket writes. On a two-core machine that
//! runs the client too, that cost is taken from the client under test: the server
//! took about 0.45 ms of CPU per 45 KiB record, against 1.1 ms for the whole item the
//! client computes from it. A cloud bucket costs the client's machine nothing.
//!
//! [`Backend::get_object`] keeps the protocol's answer (status, headers, `ETag`,
//! `Content-Range`, user metadata, the S3 error codes) and reads the bytes asked for
//! in one blocking call: the object's size and modification time first, then the
//! range. The object's `HEAD` answer from s3s-fs (its `ETag` and attributes) is kept
//! per key and used again while the file's size and modification time are unchanged;
//! every write through the server forgets it. It also honours `If-Match`, which
//! s3s-fs 0.14 ignores, with S3's `412 Precondition Failed`.

use std::collections::HashMap;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Component, Path, PathBuf};
use std::pin::Pin;
use std::sync::Mutex;
use std::task::{Context, Poll};
use std::time::SystemTime;

use bytes::Bytes;
use s3s::dto::*;
use s3s::stream::{ByteStream, RemainingLength};
use s3s::{S3, S3Error, S3ErrorCode, S3Request, S3Response, S3Result, StdError};

/// Objects larger than this are read by s3s-fs's own `GetObject` (streamed from the
/// file) instead of being read whole into memory.
const WHOLE_READ_LIMIT: u64 = 256 << 20;

/// Pieces of a body sent at once (so that the proxy's bandwidth cap interleaves the
/// connections as it does for s3s-fs's stream).
const PIECE: usize = 1 << 20;

/// One object's `HEAD` answer, valid while its file keeps this size and time.
#[derive(Clone)]
struct KnownHead {
    len: u64,
    modified: SystemTime,
    head: HeadObjectOutput,
}

/// s3s-fs with object reads served by one file read (see the module's docs).
pub(crate) struct Backend {
    fs: s3s_fs::FileSystem,
    root: PathBuf,
    heads: Mutex<HashMap<(String, String), KnownHead>>,
}

impl Backend {
    /// The backend over `root` (canonical, as s3s-fs resolves it).
    pub(crate) fn new(root: &Path) -> std::io::Result<Backend> {
        let fs = s3s_fs::FileSystem::new(root)
            .map_err(|err| std::io::Error::other(format!("{err:?}")))?;
        Ok(Backend {
            fs,
            root: std::env::current_dir()?.join(root).canonicalize()?,
            heads: Mutex::new(HashMap::new()),
        })
    }

    /// The file holding `bucket`/`key`, or `None` for a name this path does not serve
    /// (a component that is not a plain name): s3s-fs answers those.
    fn object_path(&self, bucket: &str, key: &str) -> Option<PathBuf> {
        let plain = |s: &str| {
            !s.is_empty()
                && Path::new(s)
                    .components()
                    .all(|c| matches!(c, Component::Normal(_)))
        };
        (plain(bucket) && plain(key) && !key.ends_with('/'))
            .then(|| self.root.join(bucket).join(key))
    }

    fn forget_heads(&self) {
        self.heads.lock().unwrap_or_else(|e| e.into_inner()).clear();
    }

    /// The object's `HEAD` answer for this file state, from s3s-fs the first time.
    async fn head_for(
        &self,
        req: &S3Request<GetObjectInput>,
        len: u64,
        modified: SystemTime,
    ) -> S3Result<HeadObjectOutput> {
        let key = (req.input.bucket.clone(), req.input.key.clone());
        if let Some(known) = self
            .heads
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get(&key)
            && known.len == len
            && known.modified == modified
        {
            return Ok(known.head.clone());
        }
        let head_req = S3Request {
            input: HeadObjectInput {
                bucket: key.0.clone(),
                key: key.1.clone(),
                ..Default::default()
            },
            method: http::Method::HEAD,
            uri: req.uri.clone(),
            headers: req.headers.clone(),
            extensions: http::Extensions::new(),
            credentials: req.credentials.clone(),
            region: req.region.clone(),
            service: req.service.clone(),
            trailing_headers: None,
        };
        let head = self.fs.head_object(head_req).await?.output;
        self.heads.lock().unwrap_or_else(|e| e.into_inner()).insert(
            key,
            KnownHead {
                len,
                modified,
                head: head.clone(),
            },
        );
        Ok(head)
    }
}

/// A file's size, modification time and the bytes of one range of it.
struct Read {
    len: u64,
    modified: SystemTime,
    range: std::ops::Range<u64>,
    pieces: Vec<Bytes>,
}

/// Reads `range` (all of it when `None`) of the file at `path` in one pass.
fn read_range(path: &Path, range: Option<Range>) -> Result<Option<Read>, S3Error> {
    let file = match File::open(path) {
        Ok(file) => file,
        Err(_) => return Ok(None),
    };
    let meta = file.metadata().map_err(internal)?;
    if !meta.is_file() {
        return Ok(None);
    }
    let (len, modified) = (meta.len(), meta.modified().map_err(internal)?);
    let range = match range {
        Some(r) => r.check(len)?,
        None => 0..len,
    };
    if range.end - range.start > WHOLE_READ_LIMIT {
        return Ok(None);
    }
    let mut pieces = Vec::new();
    let mut at = range.start;
    while at < range.end {
        let n = ((range.end - at) as usize).min(PIECE);
        let mut buf = vec![0u8; n];
        file.read_exact_at(&mut buf, at).map_err(internal)?;
        pieces.push(Bytes::from(buf));
        at += n as u64;
    }
    Ok(Some(Read {
        len,
        modified,
        range,
        pieces,
    }))
}

fn internal(err: std::io::Error) -> S3Error {
    S3Error::with_source(S3ErrorCode::InternalError, Box::new(err))
}

/// A body of pieces already in memory, with its exact length.
struct Pieces {
    pieces: std::collections::VecDeque<Bytes>,
    remaining: usize,
}

impl futures::Stream for Pieces {
    type Item = Result<Bytes, StdError>;

    fn poll_next(mut self: Pin<&mut Self>, _cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        let piece = self.pieces.pop_front();
        if let Some(p) = &piece {
            self.remaining -= p.len();
        }
        Poll::Ready(piece.map(Ok))
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        (self.pieces.len(), Some(self.pieces.len()))
    }
}

impl ByteStream for Pieces {
    fn remaining_length(&self) -> RemainingLength {
        RemainingLength::new_exact(self.remaining)
    }
}

/// Whether the `If-Match` condition `cond` holds for the object's `etag`.
fn if_match_holds(cond: &ETagCondition, etag: Option<&ETag>) -> bool {
    match cond {
        ETagCondition::Any => true,
        ETagCondition::ETag(want) => etag.is_some_and(|have| match (want, have) {
            (ETag::Strong(a), ETag::Strong(b)) => a == b,
            _ => false,
        }),
    }
}

#[async_trait::async_trait]
impl S3 for Backend {
    async fn get_object(
        &self,
        req: S3Request<GetObjectInput>,
    ) -> S3Result<S3Response<GetObjectOutput>> {
        let input = &req.input;
        let served_here = input.part_number.is_none() && input.version_id.is_none();
        let path = match self.object_path(&input.bucket, &input.key) {
            Some(path) if served_here => path,
            _ => return self.fs.get_object(req).await,
        };
        let range = input.range;
        // A range of at most a piece is read on the server's thread (from the page
        // cache, a few microseconds); a larger one on a blocking thread.
        let small = matches!(range, Some(Range::Int { first, last: Some(last) }) if last - first < PIECE as u64)
            || matches!(range, Some(Range::Suffix { length }) if length <= PIECE as u64);
        let read = if small {
            read_range(&path, range)?
        } else {
            tokio::task::spawn_blocking(move || read_range(&path, range))
                .await
                .map_err(|err| S3Error::with_source(S3ErrorCode::InternalError, Box::new(err)))??
        };
        // A missing object, a folder, or a body too large to hold: s3s-fs answers.
        let Some(read) = read else {
            return self.fs.get_object(req).await;
        };
        let head = self.head_for(&req, read.len, read.modified).await?;
        if let Some(cond) = &req.input.if_match
            && !if_match_holds(cond, head.e_tag.as_ref())
        {
            return Err(S3Error::new(S3ErrorCode::PreconditionFailed));
        }
        let length = read.range.end - read.range.start;
        let content_range = req.input.range.map(|_| {
            format!(
                "bytes {}-{}/{}",
                read.range.start,
                read.range.end - 1,
                read.len
            )
        });
        let whole = content_range.is_none();
        let body = Pieces {
            pieces: read.pieces.into(),
            remaining: length as usize,
        };
        let output = GetObjectOutput {
            body: Some(StreamingBlob::new(body)),
            content_length: Some(length as i64),
            content_range,
            last_modified: Some(Timestamp::from(read.modified)),
            metadata: head.metadata,
            content_encoding: head.content_encoding,
            content_type: head.content_type,
            content_disposition: head.content_disposition,
            content_language: head.content_language,
            cache_control: head.cache_control,
            expires: head.expires,
            website_redirect_location: head.website_redirect_location,
            e_tag: head.e_tag,
            // As S3 (and s3s-fs): the object's checksums only with the whole object.
            checksum_crc32: head.checksum_crc32.filter(|_| whole),
            checksum_crc32c: head.checksum_crc32c.filter(|_| whole),
            checksum_sha1: head.checksum_sha1.filter(|_| whole),
            checksum_sha256: head.checksum_sha256.filter(|_| whole),
            checksum_crc64nvme: head.checksum_crc64nvme.filter(|_| whole),
            ..Default::default()
        };
        Ok(S3Response::new(output))
    }

    async fn head_object(
        &self,
        req: S3Request<HeadObjectInput>,
    ) -> S3Result<S3Response<HeadObjectOutput>> {
        self.fs.head_object(req).await
    }

    async fn put_object(
        &self,
        req: S3Request<PutObjectInput>,
    ) -> S3Result<S3Response<PutObjectOutput>> {
        let out = self.fs.put_object(req).await;
        self.forget_heads();
        out
    }

    async fn copy_object(
        &self,
        req: S3Request<CopyObjectInput>,
    ) -> S3Result<S3Response<CopyObjectOutput>> {
        let out = self.fs.copy_object(req).await;
        self.forget_heads();
        out
    }

    async fn delete_object(
        &self,
        req: S3Request<DeleteObjectInput>,
    ) -> S3Result<S3Response<DeleteObjectOutput>> {
        let out = self.fs.delete_object(req).await;
        self.forget_heads();
        out
    }

    async fn delete_objects(
        &self,
        req: S3Request<DeleteObjectsInput>,
    ) -> S3Result<S3Response<DeleteObjectsOutput>> {
        let out = self.fs.delete_objects(req).await;
        self.forget_heads();
        out
    }

    async fn complete_multipart_upload(
        &self,
        req: S3Request<CompleteMultipartUploadInput>,
    ) -> S3Result<S3Response<CompleteMultipartUploadOutput>> {
        let out = self.fs.complete_multipart_upload(req).await;
        self.forget_heads();
        out
    }

    async fn create_multipart_upload(
        &self,
        req: S3Request<CreateMultipartUploadInput>,
    ) -> S3Result<S3Response<CreateMultipartUploadOutput>> {
        self.fs.create_multipart_upload(req).await
    }

    async fn upload_part(
        &self,
        req: S3Request<UploadPartInput>,
    ) -> S3Result<S3Response<UploadPartOutput>> {
        self.fs.upload_part(req).await
    }

    async fn upload_part_copy(
        &self,
        req: S3Request<UploadPartCopyInput>,
    ) -> S3Result<S3Response<UploadPartCopyOutput>> {
        self.fs.upload_part_copy(req).await
    }

    async fn abort_multipart_upload(
        &self,
        req: S3Request<AbortMultipartUploadInput>,
    ) -> S3Result<S3Response<AbortMultipartUploadOutput>> {
        self.fs.abort_multipart_upload(req).await
    }

    async fn list_parts(
        &self,
        req: S3Request<ListPartsInput>,
    ) -> S3Result<S3Response<ListPartsOutput>> {
        self.fs.list_parts(req).await
    }

    async fn list_objects(
        &self,
        req: S3Request<ListObjectsInput>,
    ) -> S3Result<S3Response<ListObjectsOutput>> {
        self.fs.list_objects(req).await
    }

    async fn list_objects_v2(
        &self,
        req: S3Request<ListObjectsV2Input>,
    ) -> S3Result<S3Response<ListObjectsV2Output>> {
        self.fs.list_objects_v2(req).await
    }

    async fn create_bucket(
        &self,
        req: S3Request<CreateBucketInput>,
    ) -> S3Result<S3Response<CreateBucketOutput>> {
        self.fs.create_bucket(req).await
    }

    async fn delete_bucket(
        &self,
        req: S3Request<DeleteBucketInput>,
    ) -> S3Result<S3Response<DeleteBucketOutput>> {
        self.forget_heads();
        self.fs.delete_bucket(req).await
    }

    async fn head_bucket(
        &self,
        req: S3Request<HeadBucketInput>,
    ) -> S3Result<S3Response<HeadBucketOutput>> {
        self.fs.head_bucket(req).await
    }

    async fn list_buckets(
        &self,
        req: S3Request<ListBucketsInput>,
    ) -> S3Result<S3Response<ListBucketsOutput>> {
        self.fs.list_buckets(req).await
    }

    async fn get_bucket_location(
        &self,
        req: S3Request<GetBucketLocationInput>,
    ) -> S3Result<S3Response<GetBucketLocationOutput>> {
        self.fs.get_bucket_location(req).await
    }
}
