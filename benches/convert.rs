//! Convert benchmark: synthesises N samples at 800x800, then times, as child processes,
//! `arkit-tool convert` with 1 and 2 threads against decoding the same JPEGs alone (the
//! floor of this work), and compares peak memory for N/10 and N samples (it must stay
//! flat: memory is bounded by one shard). Prints ratios.
//! Run: `cargo bench --bench convert` (N = 2000; `ARKIT_BENCH_SAMPLES` to change).

use arkit_data::ingest::synth::{self, FaceSource, SynthOptions};
use rayon::prelude::*;
use std::path::Path;
use std::process::Command;
use std::time::Instant;

fn child_peak_rss_kib() -> i64 {
    // Largest resident set of any waited-for child so far.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_CHILDREN, &mut usage) };
    usage.ru_maxrss
}

fn convert(input: &Path, output: &Path, jobs: usize, rows_per_shard: usize) -> (f64, i64) {
    let _ = std::fs::remove_dir_all(output);
    let t = Instant::now();
    let status = Command::new(env!("CARGO_BIN_EXE_arkit-tool"))
        .args([
            "convert",
            "--jobs",
            &jobs.to_string(),
            "--rows-per-shard",
            &rows_per_shard.to_string(),
            "--input",
        ])
        .arg(input)
        .arg("--output")
        .arg(output)
        .stderr(std::process::Stdio::null())
        .status()
        .expect("run arkit-tool");
    assert!(status.success());
    (t.elapsed().as_secs_f64(), child_peak_rss_kib())
}

fn jpegs(root: &Path) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "jpg") {
                out.push(std::fs::read(&p).unwrap());
            }
        }
    }
    out
}

fn decode_all(bytes: &[Vec<u8>], threads: usize) -> f64 {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let t = Instant::now();
    pool.install(|| {
        bytes.par_iter().for_each(|b| {
            let img = image::load_from_memory_with_format(b, image::ImageFormat::Jpeg).unwrap();
            std::hint::black_box(img.width());
        })
    });
    t.elapsed().as_secs_f64()
}

fn main() {
    let n: usize = std::env::var("ARKIT_BENCH_SAMPLES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2000);
    let dir = tempfile::tempdir().unwrap();
    let big = dir.path().join("big");
    let small = dir.path().join("small");
    let subjects = (n / 50).max(2);
    let make = |root: &Path, subjects: usize| {
        let o = SynthOptions {
            subjects,
            images_per_subject: 50,
            width: 800,
            height: 800,
            seed: 1,
            ..SynthOptions::default()
        };
        synth::generate(&FaceSource::builtin(), &o, root, &|| {}).unwrap();
        subjects * 50
    };
    let t = Instant::now();
    let n_big = make(&big, subjects);
    let n_small = make(&small, (subjects / 10).max(1));
    eprintln!(
        "synthesised {} + {} samples in {:.1} s",
        n_big,
        n_small,
        t.elapsed().as_secs_f64()
    );
    let bytes = jpegs(&big);
    let decode1 = decode_all(&bytes, 1);
    let decode2 = decode_all(&bytes, 2);
    let out = dir.path().join("out");
    let (small_t, small_rss) = convert(&small, &out, 2, 512);
    let (t1, _) = convert(&big, &out, 1, 512);
    let (t2, big_rss) = convert(&big, &out, 2, 512);
    println!("convert benchmark: {n_big} samples of 800x800, rows per shard 512");
    println!(
        "{:<34} {:>10} {:>14} {:>16}",
        "", "seconds", "samples/s", "ratio to decode"
    );
    println!(
        "{:<34} {:>10.2} {:>14.0} {:>16}",
        "JPEG decode alone, 1 thread",
        decode1,
        n_big as f64 / decode1,
        "1.00x"
    );
    println!(
        "{:<34} {:>10.2} {:>14.0} {:>16}",
        "JPEG decode alone, 2 threads",
        decode2,
        n_big as f64 / decode2,
        "1.00x"
    );
    println!(
        "{:<34} {:>10.2} {:>14.0} {:>15.2}x",
        "convert, 1 thread",
        t1,
        n_big as f64 / t1,
        t1 / decode1
    );
    println!(
        "{:<34} {:>10.2} {:>14.0} {:>15.2}x",
        "convert, 2 threads",
        t2,
        n_big as f64 / t2,
        t2 / decode2
    );
    println!("scaling 1 -> 2 threads: {:.2}x", t1 / t2);
    println!(
        "ratio: convert / JPEG decode alone (the floor) = {:.2}x on 1 thread, {:.2}x on 2",
        t1 / decode1,
        t2 / decode2
    );
    println!(
        "peak memory: {:.0} MiB for {} samples, {:.0} MiB for {} samples ({:.2}x for {:.0}x the input)",
        small_rss as f64 / 1024.0,
        n_small,
        big_rss as f64 / 1024.0,
        n_big,
        big_rss as f64 / small_rss.max(1) as f64,
        n_big as f64 / n_small as f64
    );
    let _ = small_t;
}
