//! The test bed against the client arkit-tool ships: `object_store`'s S3 client, over
//! real HTTP, signing every request (SigV4).

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use arkit_s3_testbed::{Fault, FaultPlan, FaultProxy, FaultRule, S3Server};
use object_store::aws::{AmazonS3, AmazonS3Builder};
use object_store::path::Path;
use object_store::{
    BackoffConfig, GetOptions, GetRange, ObjectStore, ObjectStoreExt, PutPayload, RetryConfig,
};

const ACCESS: &str = "testbed-access";
const SECRET: &str = "testbed-secret-key";
const BUCKET: &str = "faces";

/// A server over a fresh folder, with the bucket created.
fn server() -> (tempfile::TempDir, S3Server) {
    let dir = tempfile::tempdir().unwrap();
    let server = S3Server::start(dir.path(), ACCESS, SECRET).unwrap();
    server.create_bucket(BUCKET).unwrap();
    (dir, server)
}

/// The server and a proxy in front of it.
fn proxied(plan: FaultPlan) -> (tempfile::TempDir, S3Server, FaultProxy) {
    let (dir, server) = server();
    let proxy = FaultProxy::start(server.addr(), plan).unwrap();
    (dir, server, proxy)
}

/// The S3 client, path style, retrying `max_retries` times with a short backoff.
fn client(endpoint: &str, secret: &str, max_retries: usize) -> AmazonS3 {
    AmazonS3Builder::new()
        .with_endpoint(endpoint)
        .with_allow_http(true)
        .with_region("us-east-1")
        .with_access_key_id(ACCESS)
        .with_secret_access_key(secret)
        .with_bucket_name(BUCKET)
        .with_virtual_hosted_style_request(false)
        .with_retry(RetryConfig {
            backoff: BackoffConfig {
                init_backoff: Duration::from_millis(10),
                max_backoff: Duration::from_millis(50),
                base: 2.0,
            },
            max_retries,
            retry_timeout: Duration::from_secs(30),
        })
        .build()
        .unwrap()
}

/// Deterministic, non-repeating-looking bytes.
fn payload(len: usize, seed: u8) -> Vec<u8> {
    (0..len)
        .map(|i| (i as u32).wrapping_mul(2_654_435_761).to_le_bytes()[2] ^ seed)
        .collect()
}

async fn put(store: &AmazonS3, key: &str, data: &[u8]) -> object_store::PutResult {
    store
        .put(&Path::from(key), PutPayload::from(data.to_vec()))
        .await
        .unwrap()
}

async fn get(store: &AmazonS3, key: &str) -> object_store::Result<Vec<u8>> {
    Ok(store.get(&Path::from(key)).await?.bytes().await?.to_vec())
}

/// One raw HTTP/1.1 request (Connection: close): the status and the body.
fn raw_http(addr: SocketAddr, method: &str, path: &str, body: &str) -> (u16, String) {
    let mut stream = TcpStream::connect(addr).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    write!(
        stream,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut answer = String::new();
    stream.read_to_string(&mut answer).unwrap();
    let status = answer.split(' ').nth(1).unwrap().parse().unwrap();
    let body = answer.split_once("\r\n\r\n").unwrap().1.to_owned();
    (status, body)
}

#[tokio::test]
async fn direct_round_trip_range_list_head_etag() {
    let (_dir, server) = server();
    assert!(server.endpoint().starts_with("http://127.0.0.1:"));
    let store = client(&server.endpoint(), SECRET, 0);
    let data = payload(100_000, 1);
    let first = put(&store, "shards/part-0.bin", &data).await;
    put(&store, "shards/part-1.bin", &payload(10, 2)).await;

    assert_eq!(get(&store, "shards/part-0.bin").await.unwrap(), data);
    let slice = store
        .get_range(&Path::from("shards/part-0.bin"), 1_000..5_123)
        .await
        .unwrap();
    assert_eq!(&slice[..], &data[1_000..5_123]);

    let listed = store
        .list_with_delimiter(Some(&Path::from("shards")))
        .await
        .unwrap();
    let mut names: Vec<(String, u64)> = listed
        .objects
        .iter()
        .map(|o| (o.location.to_string(), o.size))
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            ("shards/part-0.bin".to_owned(), 100_000),
            ("shards/part-1.bin".to_owned(), 10)
        ]
    );

    let head = store.head(&Path::from("shards/part-0.bin")).await.unwrap();
    assert_eq!(head.size, 100_000);
    let etag = head.e_tag.expect("an ETag");
    assert!(!etag.is_empty());
    assert_eq!(first.e_tag.as_deref(), Some(etag.as_str()));

    put(&store, "shards/part-0.bin", &payload(100_000, 3)).await;
    let head = store.head(&Path::from("shards/part-0.bin")).await.unwrap();
    assert_ne!(head.e_tag.as_deref(), Some(etag.as_str()));

    let missing = get(&store, "shards/none.bin").await.unwrap_err();
    assert!(
        matches!(missing, object_store::Error::NotFound { .. }),
        "{missing}"
    );
    // The objects are files in the bucket's folder.
    assert!(
        server
            .root()
            .join(BUCKET)
            .join("shards/part-1.bin")
            .is_file()
    );
}

/// The server's own object reads: every range of an object (suffix, open end, one
/// byte, pieces over 1 MiB) is the file's bytes, the GET's `ETag` is the HEAD's, a
/// rewritten object is read anew, and `If-Match` with another `ETag` is refused with
/// 412 (which the client reports as a changed precondition).
#[tokio::test]
async fn get_ranges_etag_and_if_match() {
    let (_dir, server) = server();
    let store = client(&server.endpoint(), SECRET, 0);
    let key = Path::from("crops/part-0.bin");
    let data = payload(3 * 1024 * 1024 + 17, 5);
    put(&store, "crops/part-0.bin", &data).await;
    let n = data.len() as u64;
    for range in [
        GetRange::Bounded(0..1),
        GetRange::Bounded(4_096..53_000),
        GetRange::Bounded(1_000_000..n),
        GetRange::Offset(n - 5),
        GetRange::Suffix(70_000),
    ] {
        let got = store
            .get_opts(
                &key,
                GetOptions {
                    range: Some(range.clone()),
                    ..GetOptions::default()
                },
            )
            .await
            .unwrap();
        let want = match &range {
            GetRange::Bounded(r) => r.start as usize..r.end as usize,
            GetRange::Offset(o) => *o as usize..data.len(),
            GetRange::Suffix(s) => data.len() - *s as usize..data.len(),
        };
        assert_eq!(got.meta.size, n, "{range:?}");
        assert_eq!(&got.bytes().await.unwrap()[..], &data[want], "{range:?}");
    }
    assert_eq!(get(&store, "crops/part-0.bin").await.unwrap(), data);

    let etag = store.head(&key).await.unwrap().e_tag.unwrap();
    let read = |if_match: Option<String>| {
        let store = &store;
        let key = &key;
        async move {
            store
                .get_opts(
                    key,
                    GetOptions {
                        range: Some(GetRange::Bounded(10..20)),
                        if_match,
                        ..GetOptions::default()
                    },
                )
                .await
        }
    };
    let pinned = read(Some(etag.clone())).await.unwrap();
    assert_eq!(pinned.meta.e_tag.as_deref(), Some(etag.as_str()));
    let refused = read(Some("\"0123456789abcdef0123456789abcdef\"".into()))
        .await
        .unwrap_err();
    assert!(
        matches!(refused, object_store::Error::Precondition { .. }),
        "{refused}"
    );

    // Rewritten: the new bytes, a new ETag, and the old ETag refused.
    let again = payload(200_000, 6);
    put(&store, "crops/part-0.bin", &again).await;
    let got = read(None).await.unwrap();
    let new_etag = got.meta.e_tag.clone().unwrap();
    assert_ne!(new_etag, etag);
    assert_eq!(&got.bytes().await.unwrap()[..], &again[10..20]);
    assert!(matches!(
        read(Some(etag)).await.unwrap_err(),
        object_store::Error::Precondition { .. }
    ));
    let beyond = store.get_range(&key, 300_000..300_010).await.unwrap_err();
    assert!(!beyond.to_string().is_empty());
}

#[tokio::test]
async fn wrong_secret_is_refused() {
    let (_dir, server) = server();
    put(&client(&server.endpoint(), SECRET, 0), "a.bin", b"abc").await;
    let intruder = client(&server.endpoint(), "not-the-secret", 0);
    let err = get(&intruder, "a.bin").await.unwrap_err();
    assert!(
        matches!(err, object_store::Error::PermissionDenied { .. }),
        "{err}"
    );
    assert!(err.to_string().contains("403"), "{err}");
    let err = intruder
        .put(&Path::from("b.bin"), PutPayload::from_static(b"x"))
        .await
        .unwrap_err();
    assert!(
        matches!(err, object_store::Error::PermissionDenied { .. }),
        "{err}"
    );
    assert!(!server.root().join(BUCKET).join("b.bin").exists());
}

#[tokio::test]
async fn proxy_round_trip_and_counters() {
    let (_dir, _server, proxy) = proxied(FaultPlan::default());
    let store = client(&proxy.endpoint(), SECRET, 0);
    let data = payload(300_000, 4);
    put(&store, "x/part-0.bin", &data).await;
    assert_eq!(get(&store, "x/part-0.bin").await.unwrap(), data);
    let slice = store
        .get_range(&Path::from("x/part-0.bin"), 7..70_007)
        .await
        .unwrap();
    assert_eq!(&slice[..], &data[7..70_007]);
    let head = store.head(&Path::from("x/part-0.bin")).await.unwrap();
    assert_eq!(head.size, 300_000);

    let stats = proxy.control().stats();
    assert_eq!(stats.requests, 4, "{stats:?}");
    assert_eq!(stats.requests_by_method.get("PUT"), Some(&1));
    assert_eq!(stats.requests_by_method.get("GET"), Some(&2));
    assert_eq!(stats.requests_by_method.get("HEAD"), Some(&1));
    // The bodies of the two GETs (the PUT's answer has none worth counting).
    assert!(
        (370_000..370_000 + 1_000).contains(&stats.response_body_bytes),
        "{stats:?}"
    );
    assert_eq!(stats.faults_fired, 0);
    // Sequential requests reuse one keep-alive connection.
    assert_eq!(stats.connections, 1, "{stats:?}");
    proxy.control().reset_stats();
    assert_eq!(proxy.control().stats().requests, 0);

    // The client signs the Host header (the proxy's address, not the server's): the
    // requests above passed SigV4 because the proxy forwards it unchanged. A wrong
    // secret through the proxy is still refused by the server.
    let err = get(&client(&proxy.endpoint(), "wrong", 0), "x/part-0.bin")
        .await
        .unwrap_err();
    assert!(
        matches!(err, object_store::Error::PermissionDenied { .. }),
        "{err}"
    );
}

#[tokio::test]
async fn status_rule_fails_the_next_gets_then_is_spent() {
    let (_dir, _server, proxy) = proxied(FaultPlan::default());
    let store = client(&proxy.endpoint(), SECRET, 0);
    put(&store, "s/part-0.bin", b"hello").await;
    put(&store, "s/part-1.bin", b"world").await;
    let control = proxy.control();
    control.push_rule(
        FaultRule::new(Fault::Status(503), 2)
            .method("GET")
            .key_contains("part-0"),
    );
    // Another key and another method do not match.
    assert_eq!(get(&store, "s/part-1.bin").await.unwrap(), b"world");
    assert_eq!(
        store.head(&Path::from("s/part-0.bin")).await.unwrap().size,
        5
    );
    for _ in 0..2 {
        let err = get(&store, "s/part-0.bin").await.unwrap_err();
        assert!(err.to_string().contains("503"), "{err}");
    }
    assert_eq!(get(&store, "s/part-0.bin").await.unwrap(), b"hello");
    assert!(control.rules().is_empty());
    assert_eq!(control.stats().faults_fired, 2);

    // A PUT refused with 503 while its body is being sent: the client sees the 503.
    control.push_rule(FaultRule::new(Fault::Status(503), 1).method("PUT"));
    let err = store
        .put(
            &Path::from("s/big.bin"),
            PutPayload::from(payload(8_000_000, 9)),
        )
        .await
        .unwrap_err();
    assert!(err.to_string().contains("503"), "{err}");

    // With retries, the client gets through, and the proxy saw the retries.
    let patient = client(&proxy.endpoint(), SECRET, 5);
    control.reset();
    control.push_rule(FaultRule::new(Fault::Status(500), 3).method("GET"));
    assert_eq!(get(&patient, "s/part-0.bin").await.unwrap(), b"hello");
    let stats = control.stats();
    assert_eq!(stats.requests_by_method.get("GET"), Some(&4), "{stats:?}");
    assert_eq!(stats.faults_fired, 3);
}

#[tokio::test]
async fn truncated_body_is_an_error_never_a_short_success() {
    let (_dir, _server, proxy) = proxied(FaultPlan::default());
    let store = client(&proxy.endpoint(), SECRET, 0);
    let data = payload(500_000, 5);
    put(&store, "t/part-0.bin", &data).await;
    let control = proxy.control();
    control.push_rule(
        FaultRule::new(
            Fault::Truncate {
                after_bytes: 123_456,
            },
            1,
        )
        .method("GET"),
    );
    let err = get(&store, "t/part-0.bin").await.unwrap_err();
    assert!(err.to_string().contains("body"), "{err}");
    let stats = control.stats();
    assert_eq!(stats.response_body_bytes, 123_456, "{stats:?}");
    assert_eq!(stats.faults_fired, 1);
    // Spent: the next get is whole.
    assert_eq!(get(&store, "t/part-0.bin").await.unwrap(), data);

    // With retries, object_store resumes the body with a ranged GET of the rest.
    control.reset();
    control.push_rule(FaultRule::new(Fault::Truncate { after_bytes: 1_000 }, 1).method("GET"));
    let patient = client(&proxy.endpoint(), SECRET, 3);
    assert_eq!(get(&patient, "t/part-0.bin").await.unwrap(), data);
    let stats = control.stats();
    assert_eq!(stats.requests_by_method.get("GET"), Some(&2), "{stats:?}");
    assert_eq!(stats.response_body_bytes, 500_000, "{stats:?}");
}

#[tokio::test]
async fn reset_is_a_connection_error() {
    let (_dir, _server, proxy) = proxied(FaultPlan::default());
    let store = client(&proxy.endpoint(), SECRET, 0);
    put(&store, "r/part-0.bin", b"reset me").await;
    proxy
        .control()
        .push_rule(FaultRule::new(Fault::Reset, 1).key_contains("part-0"));
    let err = get(&store, "r/part-0.bin").await.unwrap_err();
    let text = format!("{err:?}");
    assert!(matches!(err, object_store::Error::Generic { .. }), "{text}");
    assert!(!text.contains("status"), "no HTTP answer expected: {text}");
    assert_eq!(get(&store, "r/part-0.bin").await.unwrap(), b"reset me");

    // A raw client sees the connection reset without any byte of an answer.
    proxy.control().push_rule(FaultRule::new(Fault::Reset, 1));
    let mut stream = TcpStream::connect(proxy.addr()).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    write!(
        stream,
        "GET /faces/r/part-0.bin HTTP/1.1\r\nHost: x\r\n\r\n"
    )
    .unwrap();
    let mut answer = Vec::new();
    match stream.read_to_end(&mut answer) {
        Err(err) => assert_eq!(err.kind(), std::io::ErrorKind::ConnectionReset),
        Ok(_) => assert!(answer.is_empty(), "{answer:?}"),
    }
}

#[tokio::test]
async fn latency_and_stall_delay_requests() {
    let plan = FaultPlan {
        latency: Duration::from_millis(50),
        ..FaultPlan::default()
    };
    let (_dir, _server, proxy) = proxied(plan);
    let store = client(&proxy.endpoint(), SECRET, 0);
    put(&store, "l/a.bin", b"slow").await;
    let start = Instant::now();
    store.head(&Path::from("l/a.bin")).await.unwrap();
    assert!(
        start.elapsed() >= Duration::from_millis(50),
        "{:?}",
        start.elapsed()
    );

    proxy.control().set_latency(Duration::ZERO);
    proxy
        .control()
        .push_rule(FaultRule::new(Fault::Stall(Duration::from_millis(300)), 1));
    let start = Instant::now();
    assert_eq!(get(&store, "l/a.bin").await.unwrap(), b"slow");
    assert!(
        start.elapsed() >= Duration::from_millis(300),
        "{:?}",
        start.elapsed()
    );
}

#[tokio::test]
async fn bandwidth_cap_is_shared() {
    let (_dir, server, proxy) = proxied(FaultPlan::default());
    let data = payload(2_000_000, 6);
    put(&client(&server.endpoint(), SECRET, 0), "b/big.bin", &data).await;
    let store = client(&proxy.endpoint(), SECRET, 0);

    let start = Instant::now();
    assert_eq!(get(&store, "b/big.bin").await.unwrap(), data);
    let uncapped = start.elapsed();

    proxy.control().set_bandwidth(1_000_000);
    let start = Instant::now();
    assert_eq!(get(&store, "b/big.bin").await.unwrap(), data);
    let capped = start.elapsed();
    assert!(
        capped >= Duration::from_millis(1_500),
        "{capped:?} (uncapped {uncapped:?})"
    );

    // Two gets at once share the cap: 2 x 1 MB at 4 MB/s take about 0.5 s.
    proxy.control().set_bandwidth(4_000_000);
    let start = Instant::now();
    let big = Path::from("b/big.bin");
    let (a, b) = tokio::join!(
        store.get_range(&big, 0..1_000_000),
        store.get_range(&big, 1_000_000..2_000_000)
    );
    assert_eq!([&a.unwrap()[..], &b.unwrap()[..]].concat(), data);
    assert!(
        start.elapsed() >= Duration::from_millis(400),
        "{:?}",
        start.elapsed()
    );
}

#[tokio::test]
async fn many_concurrent_requests() {
    let (_dir, _server, proxy) = proxied(FaultPlan {
        latency: Duration::from_millis(20),
        ..FaultPlan::default()
    });
    let store = client(&proxy.endpoint(), SECRET, 0);
    let data = payload(50_000, 7);
    put(&store, "c/x.bin", &data).await;
    let mut tasks = tokio::task::JoinSet::new();
    for i in 0..48u64 {
        let store = store.clone();
        tasks.spawn(async move {
            let range = i * 1_000..i * 1_000 + 2_000;
            store.get_range(&Path::from("c/x.bin"), range).await
        });
    }
    let mut n = 0;
    while let Some(result) = tasks.join_next().await {
        assert_eq!(result.unwrap().unwrap().len(), 2_000);
        n += 1;
    }
    assert_eq!(n, 48);
    let stats = proxy.control().stats();
    assert_eq!(stats.requests_by_method.get("GET"), Some(&48));
    assert!(stats.connections > 1, "{stats:?}");
}

#[tokio::test]
async fn multipart_upload_through_the_proxy() {
    let (_dir, _server, proxy) = proxied(FaultPlan::default());
    let store = client(&proxy.endpoint(), SECRET, 3);
    let data = payload(6 * 1024 * 1024 + 12_345, 8);
    let path = Path::from("m/big.bin");
    let mut upload = store.put_multipart(&path).await.unwrap();
    // The first part upload fails once with 503; the client retries it.
    proxy
        .control()
        .push_rule(FaultRule::new(Fault::Status(503), 1).method("PUT"));
    upload
        .put_part(PutPayload::from(data[..5 * 1024 * 1024].to_vec()))
        .await
        .unwrap();
    upload
        .put_part(PutPayload::from(data[5 * 1024 * 1024..].to_vec()))
        .await
        .unwrap();
    upload.complete().await.unwrap();
    assert_eq!(get(&store, "m/big.bin").await.unwrap(), data);
    let stats = proxy.control().stats();
    assert_eq!(stats.faults_fired, 1);
    // Create, 2 parts + 1 retry, complete; then the GET.
    assert_eq!(stats.requests_by_method.get("PUT"), Some(&3), "{stats:?}");
    assert_eq!(stats.requests_by_method.get("POST"), Some(&2), "{stats:?}");
}

#[tokio::test]
async fn json_control_endpoints() {
    let (_dir, _server, proxy) = proxied(FaultPlan::default());
    let store = client(&proxy.endpoint(), SECRET, 0);
    put(&store, "j/part-0.bin", b"json").await;
    let addr = proxy.addr();

    let (status, body) = raw_http(
        addr,
        "POST",
        "/__testbed/faults",
        r#"{"rules":[{"method":"GET","key_contains":"part-0","times":2,"fault":{"status":503}}]}"#,
    );
    assert_eq!(status, 200, "{body}");
    for _ in 0..2 {
        let err = get(&store, "j/part-0.bin").await.unwrap_err();
        assert!(err.to_string().contains("503"), "{err}");
    }
    assert_eq!(get(&store, "j/part-0.bin").await.unwrap(), b"json");

    let (status, body) = raw_http(addr, "GET", "/__testbed/stats", "");
    assert_eq!(status, 200);
    let stats: serde_json::Value = serde_json::from_str(&body).unwrap();
    // The PUT and three GETs; control requests are not counted.
    assert_eq!(stats["requests"], 4, "{stats}");
    assert_eq!(stats["requests_by_method"]["GET"], 3, "{stats}");
    assert_eq!(stats["faults_fired"], 2, "{stats}");
    assert_eq!(stats["response_body_bytes"], 4, "{stats}");

    let (status, _) = raw_http(
        addr,
        "POST",
        "/__testbed/faults",
        r#"{"rules":[{"times":1,"fault":{"truncate":1}},{"fault":{"reset":true}},{"fault":{"stall_ms":1}}]}"#,
    );
    assert_eq!(status, 200);
    assert_eq!(proxy.control().rules().len(), 3);
    assert_eq!(
        proxy.control().rules()[0].fault,
        Fault::Truncate { after_bytes: 1 }
    );
    let (status, _) = raw_http(
        addr,
        "POST",
        "/__testbed/faults",
        r#"{"rules":[{"fault":{"status":503,"reset":true}}]}"#,
    );
    assert_eq!(status, 400);
    let (status, _) = raw_http(addr, "POST", "/__testbed/faults", "not json");
    assert_eq!(status, 400);

    let (status, _) = raw_http(addr, "POST", "/__testbed/reset", "");
    assert_eq!(status, 200);
    assert!(proxy.control().rules().is_empty());
    assert_eq!(proxy.control().stats().requests, 0);

    let (status, _) = raw_http(
        addr,
        "POST",
        "/__testbed/config",
        r#"{"latency_ms":60,"bandwidth_bytes_per_sec":125000000}"#,
    );
    assert_eq!(status, 200);
    assert_eq!(proxy.control().latency(), Duration::from_millis(60));
    assert_eq!(proxy.control().bandwidth(), 125_000_000);
    let start = Instant::now();
    assert_eq!(get(&store, "j/part-0.bin").await.unwrap(), b"json");
    assert!(start.elapsed() >= Duration::from_millis(60));

    let (status, _) = raw_http(addr, "GET", "/__testbed/nothing", "");
    assert_eq!(status, 404);
    assert_eq!(proxy.control().stats().requests, 1);
}

#[test]
fn dropping_frees_the_ports() {
    let (_dir, server, proxy) = proxied(FaultPlan::default());
    let (s3, px) = (server.addr(), proxy.addr());
    assert!(s3.ip().is_loopback() && px.ip().is_loopback());
    TcpStream::connect(px).unwrap();
    drop(proxy);
    drop(server);
    for addr in [s3, px] {
        let err = TcpStream::connect(addr).unwrap_err();
        assert_eq!(err.kind(), std::io::ErrorKind::ConnectionRefused);
    }
}

#[test]
fn binary_prints_endpoints_and_stops_at_end_of_stdin() {
    let dir = tempfile::tempdir().unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_arkit-s3-testbed"))
        .args(["--root", dir.path().to_str().unwrap()])
        .args(["--access-key", ACCESS, "--secret-key", SECRET])
        .args(["--bucket", BUCKET, "--bucket", "other", "--latency-ms", "5"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let endpoints: serde_json::Value = serde_json::from_str(&line).unwrap();
    let s3 = endpoints["s3"].as_str().unwrap().to_owned();
    let proxy = endpoints["proxy"].as_str().unwrap().to_owned();
    assert!(s3.starts_with("http://127.0.0.1:") && proxy.starts_with("http://127.0.0.1:"));
    assert!(dir.path().join("other").is_dir());

    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let store = client(&proxy, SECRET, 0);
        put(&store, "bin.bin", b"binary").await;
        assert_eq!(
            get(&client(&s3, SECRET, 0), "bin.bin").await.unwrap(),
            b"binary"
        );
    });
    let addr: SocketAddr = proxy.trim_start_matches("http://").parse().unwrap();
    let (status, body) = raw_http(addr, "GET", "/__testbed/stats", "");
    assert_eq!(status, 200);
    assert!(body.contains("\"requests\":1"), "{body}");

    drop(child.stdin.take());
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            assert!(status.success());
            break;
        }
        assert!(start.elapsed() < Duration::from_secs(10), "still running");
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn binary_stops_on_sigterm() {
    let dir = tempfile::tempdir().unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_arkit-s3-testbed"))
        .args(["--root", dir.path().join("new").to_str().unwrap()])
        .args([
            "--access-key",
            ACCESS,
            "--secret-key",
            SECRET,
            "--ignore-stdin",
        ])
        .args(["--bandwidth-mbit", "8"])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let endpoints: serde_json::Value = serde_json::from_str(&line).unwrap();
    let proxy: SocketAddr = endpoints["proxy"]
        .as_str()
        .unwrap()
        .trim_start_matches("http://")
        .parse()
        .unwrap();
    // Stdin at its end is ignored: it still serves.
    std::thread::sleep(Duration::from_millis(100));
    let (status, body) = raw_http(proxy, "GET", "/__testbed/config", "");
    assert_eq!(status, 200);
    assert!(
        body.contains("\"bandwidth_bytes_per_sec\":1000000"),
        "{body}"
    );

    let killed = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            assert!(status.success(), "{status:?}");
            break;
        }
        assert!(start.elapsed() < Duration::from_secs(10), "still running");
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(TcpStream::connect(proxy).is_err());
}
