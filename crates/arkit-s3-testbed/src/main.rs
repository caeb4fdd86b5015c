//! `arkit-s3-testbed`: a real S3 server (s3s-fs, SigV4 on) and a fault proxy in front
//! of it, on 127.0.0.1, for tests written in any language. See `--help`.

use std::io::{Read, Write};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use arkit_s3_testbed::{FaultPlan, FaultProxy, S3Server};
use clap::Parser;

/// A real S3 server (s3s-fs, with AWS SigV4 authentication enforced) over the folder
/// ROOT, and a fault-injecting HTTP proxy in front of it, both on 127.0.0.1 at ports
/// the system picks.
///
/// Once both are up it prints one line of JSON on stdout,
/// `{"s3":"http://127.0.0.1:P","proxy":"http://127.0.0.1:Q"}`, then serves until its
/// standard input reaches end of file (start it with a pipe on stdin and close the
/// pipe, or let the test die) or it gets SIGTERM or SIGINT.
///
/// The proxy forwards every request unchanged and is steered through its control
/// endpoints (JSON): POST /__testbed/faults {"rules":[{"method":"GET",
/// "key_contains":"part-0","times":2,"fault":{"status":503}}]} (faults: {"status":N},
/// {"reset":true}, {"truncate":BYTES}, {"stall_ms":N}); GET /__testbed/stats;
/// POST /__testbed/reset; POST /__testbed/config {"latency_ms":N,
/// "bandwidth_bytes_per_sec":N}.
#[derive(Debug, Parser)]
#[command(name = "arkit-s3-testbed", version)]
struct Args {
    /// The folder served: each bucket is a subfolder (created if missing).
    #[arg(long, value_name = "DIR")]
    root: PathBuf,
    /// The access key requests must be signed with.
    #[arg(long, value_name = "KEY")]
    access_key: String,
    /// The secret key requests must be signed with.
    #[arg(long, value_name = "SECRET")]
    secret_key: String,
    /// A bucket to create (repeatable).
    #[arg(long = "bucket", value_name = "NAME")]
    buckets: Vec<String>,
    /// The proxy's delay added to each request, in milliseconds.
    #[arg(long, value_name = "N", default_value_t = 0)]
    latency_ms: u64,
    /// The proxy's cap on response bandwidth, in Mbit/s (shared by all connections);
    /// 0 for none.
    #[arg(long, value_name = "N", default_value_t = 0.0)]
    bandwidth_mbit: f64,
    /// Do not stop at the end of stdin (only on SIGTERM or SIGINT).
    #[arg(long)]
    ignore_stdin: bool,
}

fn main() -> ExitCode {
    let args = Args::parse();
    match run(args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("arkit-s3-testbed: {err}");
            ExitCode::FAILURE
        }
    }
}

fn run(args: Args) -> Result<(), Box<dyn std::error::Error>> {
    if !(args.bandwidth_mbit.is_finite() && args.bandwidth_mbit >= 0.0) {
        return Err(format!("--bandwidth-mbit must be >= 0, not {}", args.bandwidth_mbit).into());
    }
    std::fs::create_dir_all(&args.root)
        .map_err(|err| format!("cannot create {}: {err}", args.root.display()))?;
    let server = S3Server::start(&args.root, &args.access_key, &args.secret_key)?;
    for bucket in &args.buckets {
        server
            .create_bucket(bucket)
            .map_err(|err| format!("bucket {bucket:?}: {err}"))?;
    }
    let plan = FaultPlan {
        latency: Duration::from_millis(args.latency_ms),
        bandwidth_bytes_per_sec: (args.bandwidth_mbit * 1e6 / 8.0).round() as u64,
        rules: Vec::new(),
    };
    let proxy = FaultProxy::start(server.addr(), plan)?;

    let line = serde_json::json!({ "s3": server.endpoint(), "proxy": proxy.endpoint() });
    wait_for_stop(args.ignore_stdin, || {
        let mut stdout = std::io::stdout().lock();
        writeln!(stdout, "{line}")?;
        stdout.flush()
    })?;
    drop(proxy);
    drop(server);
    Ok(())
}

/// Calls `announce` once SIGTERM and SIGINT are caught, then returns at the end of
/// stdin (unless ignored), or on SIGTERM or SIGINT.
fn wait_for_stop(
    ignore_stdin: bool,
    announce: impl FnOnce() -> std::io::Result<()>,
) -> std::io::Result<()> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        use tokio::signal::unix::{SignalKind, signal};
        let mut term = signal(SignalKind::terminate())?;
        let mut int = signal(SignalKind::interrupt())?;
        announce()?;
        let (eof_tx, eof_rx) = tokio::sync::oneshot::channel::<()>();
        if !ignore_stdin {
            // A plain thread: it blocks in read until the writer closes the pipe.
            std::thread::spawn(move || {
                let mut stdin = std::io::stdin().lock();
                let mut buf = [0u8; 4096];
                while let Ok(n) = stdin.read(&mut buf) {
                    if n == 0 {
                        break;
                    }
                }
                let _ = eof_tx.send(());
            });
        }
        let eof = async {
            if ignore_stdin {
                std::future::pending::<()>().await;
            } else {
                let _ = eof_rx.await;
            }
        };
        tokio::select! {
            _ = term.recv() => {},
            _ = int.recv() => {},
            () = eof => {},
        }
        Ok(())
    })
}
