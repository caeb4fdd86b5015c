//! The crop store's codecs measured on real windows: bytes per sample and time to encode
//! and decode one window, for every candidate, lossless and lossy, beside the raw bytes.
//!
//!     cargo bench --bench crop_codecs [-- SAMPLES]    (default 96)
//!
//! Makes an 800x800 synthetic release (the real topology from ARKIT_RESOURCES, default
//! ../shared/arkitface-resources, when it is there; the built-in face otherwise),
//! converts it, computes each sample's crop window and mesh as `arkit-tool crops` does
//! (192-pixel crops, `exact` rules: 244x244 windows), then per codec prints the mean
//! bytes of a window, the median encode and decode time of one window on one thread,
//! and for lossy codecs the mean and largest difference from the raw window in grey
//! levels. Lossless codecs are checked to round-trip bit for bit. Then the store's mesh
//! codec on these meshes and on the real face of the resources (bytes, decode time).
//! The `ratio:` lines compare each codec's record (window plus raw mesh, as format 3
//! stored it) with the raw record's bytes, with the release's JPEG, and (window plus the
//! mesh codec's bytes, format 4 on) with the JPEG again, and its decode time with the
//! `png` codec's; the last ones are whole stores written by `crops` with each of the
//! store's codecs, bytes a sample against the JPEG.

mod timing;

use arkit_data::crop::RuleSet;
use arkit_data::loader::{FaceLoader, LoaderMode, LoaderOptions};
use arkit_data::store::crop_store::{self, WindowCodec, WindowPart};
use image::ImageEncoder;
use std::path::PathBuf;

/// The window codecs a store can have.
const STORE_CODECS: [WindowCodec; 3] = [WindowCodec::Raw, WindowCodec::Png, WindowCodec::PredZstd];

struct Measured {
    name: String,
    bytes: f64,
    encode_ms: f64,
    decode_ms: f64,
    /// Mean and largest absolute difference from the raw window (lossy codecs).
    error: Option<(f64, u8)>,
}

fn main() {
    let samples: usize = std::env::args()
        .skip(1)
        .find_map(|a| a.parse().ok())
        .unwrap_or(96);
    let resources = PathBuf::from(
        std::env::var("ARKIT_RESOURCES").unwrap_or_else(|_| "../shared/arkitface-resources".into()),
    );
    let (topology, source) = if resources.join("triangles.npy").exists() {
        let t = arkit_data::mesh::FaceTopology::from_resources(&resources).expect("resources");
        (
            t.clone(),
            arkit_data::ingest::synth::FaceSource::new(t).expect("face"),
        )
    } else {
        eprintln!("no resources at {}: the built-in face", resources.display());
        (
            arkit_data::mesh::builtin().topology.clone(),
            arkit_data::ingest::synth::FaceSource::builtin(),
        )
    };
    let tmp = tempfile::tempdir().unwrap();
    let (release, data) = (tmp.path().join("release"), tmp.path().join("data"));
    let per_subject = 16;
    let options = arkit_data::ingest::synth::SynthOptions {
        subjects: samples.div_ceil(per_subject),
        images_per_subject: per_subject,
        seed: 1,
        test_fraction: 0.0,
        ..Default::default()
    };
    arkit_data::ingest::synth::generate(&source, &options, &release, &|| {}).unwrap();
    let ctx = arkit_data::ingest::ValidationContext {
        projection: arkit_core::conventions::Camera::release_projection(),
        topology: topology.clone(),
        embed_images: false,
    };
    let copts = arkit_data::ingest::ConvertOptions {
        input: release.clone(),
        output: data.clone(),
        resources: None,
        rows_per_shard: 4096,
        embed_images: false,
        shard_index: 0,
        shard_count: 1,
        overwrite: false,
    };
    arkit_data::ingest::convert(&copts, &ctx, &|_| {}).unwrap();
    let loader = FaceLoader::open(
        &data,
        topology,
        None,
        LoaderOptions {
            split: None,
            mode: LoaderMode::Eval,
            rules: RuleSet::Exact,
            img_size: 192,
            n_pts: 1,
            seed: 0,
        },
    )
    .unwrap();
    let crops: Vec<_> = (0..loader.len())
        .map(|i| loader.stored_crop(i).unwrap())
        .collect();
    let jpeg_bytes: u64 = walk(&release.join("ARKitFace_image_train"));
    let w = crop_store::window_side(192) as u32;
    let raw_window = (3 * w * w) as f64;
    let mesh_raw = 12.0 * crops[0].verts.len() as f64;
    println!(
        "{} samples, 800x800 JPEGs of {:.1} KiB on average; {w}x{w} windows ({:.1} KiB raw), meshes of {} vertices ({:.1} KiB raw)",
        crops.len(),
        jpeg_bytes as f64 / crops.len() as f64 / 1024.0,
        raw_window / 1024.0,
        crops[0].verts.len(),
        mesh_raw / 1024.0
    );

    let mut rows = Vec::new();
    // The store's own codecs, through its own encode and decode.
    for codec in STORE_CODECS {
        rows.push(measure(
            codec.name(),
            &crops,
            |c| {
                let bytes = crop_store::encode_window(codec, &c.window, 192).unwrap();
                let back = crop_store::decode_window(codec, &bytes, 192, WindowPart::Whole);
                assert_eq!(
                    back.unwrap(),
                    *c.window.as_raw(),
                    "{} round trip",
                    codec.name()
                );
                bytes
            },
            |b| {
                let whole = crop_store::decode_window(codec, b, 192, WindowPart::Whole);
                std::hint::black_box(whole.unwrap());
            },
        ));
    }
    // The default codec's centre alone, as evaluation decodes it.
    rows.push(measure(
        "pred-zstd, the centre alone",
        &crops,
        |c| {
            let bytes = crop_store::encode_window(WindowCodec::PredZstd, &c.window, 192).unwrap();
            let centre =
                crop_store::decode_window(WindowCodec::PredZstd, &bytes, 192, WindowPart::Centre);
            assert_eq!(centre.unwrap(), c.centre(), "the centre");
            bytes
        },
        |b| {
            let centre =
                crop_store::decode_window(WindowCodec::PredZstd, b, 192, WindowPart::Centre);
            std::hint::black_box(centre.unwrap());
        },
    ));
    // PNG at the other compression settings and filters.
    use image::codecs::png::{CompressionType, FilterType};
    for (name, comp, filter) in [
        ("png-fast", CompressionType::Fast, FilterType::Adaptive),
        ("png-best", CompressionType::Best, FilterType::Adaptive),
        ("png-best-sub", CompressionType::Best, FilterType::Sub),
        ("png-best-up", CompressionType::Best, FilterType::Up),
        ("png-best-avg", CompressionType::Best, FilterType::Avg),
        ("png-best-paeth", CompressionType::Best, FilterType::Paeth),
    ] {
        rows.push(measure(
            name,
            &crops,
            |c| {
                let mut out = Vec::new();
                image::codecs::png::PngEncoder::new_with_quality(&mut out, comp, filter)
                    .write_image(c.window.as_raw(), w, w, image::ExtendedColorType::Rgb8)
                    .unwrap();
                out
            },
            |b| {
                std::hint::black_box(image::load_from_memory(b).unwrap());
            },
        ));
    }
    // The store's prediction over the whole window in one frame (format 5's layout),
    // at the store's level and at zstd's highest but the "ultra" ones.
    let whole = crop_store::PixelRect {
        x: 0,
        y: 0,
        width: w as usize,
        height: w as usize,
    };
    for level in [15, 19] {
        rows.push(measure(
            &format!("pred-zstd-{level}, one frame"),
            &crops,
            |c| {
                let errors = crop_store::predict_rect(c.window.as_raw(), w as usize, whole);
                zstd::bulk::compress(&errors, level).unwrap()
            },
            |b| {
                let mut d = zstd::bulk::decompress(b, raw_window as usize).unwrap();
                crop_store::unpredict_in_place(&mut d, w as usize, w as usize);
                std::hint::black_box(d);
            },
        ));
    }
    // Lossless WebP (image's encoder), decoded by image's decoder.
    rows.push(measure(
        "webp-lossless",
        &crops,
        |c| {
            let mut out = Vec::new();
            image::codecs::webp::WebPEncoder::new_lossless(&mut out)
                .write_image(c.window.as_raw(), w, w, image::ExtendedColorType::Rgb8)
                .unwrap();
            let back = image::load_from_memory_with_format(&out, image::ImageFormat::WebP)
                .unwrap()
                .to_rgb8();
            assert_eq!(back.as_raw(), c.window.as_raw(), "webp round trip");
            out
        },
        |b| {
            std::hint::black_box(
                image::load_from_memory_with_format(b, image::ImageFormat::WebP).unwrap(),
            );
        },
    ));
    // zstd of the raw bytes, and of the bytes after a left-neighbour delta (PNG's Sub
    // filter) and after the median-edge predictor (LOCO-I): both undone in one pass.
    for level in [3, 19] {
        rows.push(measure(
            &format!("zstd-{level}"),
            &crops,
            |c| zstd::bulk::compress(c.window.as_raw(), level).unwrap(),
            |b| {
                std::hint::black_box(zstd::bulk::decompress(b, raw_window as usize).unwrap());
            },
        ));
        rows.push(measure(
            &format!("sub+zstd-{level}"),
            &crops,
            |c| zstd::bulk::compress(&sub(c.window.as_raw(), w as usize), level).unwrap(),
            |b| {
                let d = zstd::bulk::decompress(b, raw_window as usize).unwrap();
                std::hint::black_box(unsub(d, w as usize));
            },
        ));
        rows.push(measure(
            &format!("med+zstd-{level}"),
            &crops,
            |c| {
                let f = med(c.window.as_raw(), w as usize);
                assert_eq!(unmed(f.clone(), w as usize), *c.window.as_raw());
                zstd::bulk::compress(&f, level).unwrap()
            },
            |b| {
                let d = zstd::bulk::decompress(b, raw_window as usize).unwrap();
                std::hint::black_box(unmed(d, w as usize));
            },
        ));
    }
    // Lossy: JPEG of the window (encoded once), decoded as the loader would.
    for q in [90u8, 95, 98, 100] {
        let mut m = measure(
            &format!("jpeg-q{q} (lossy)"),
            &crops,
            |c| {
                let mut out = Vec::new();
                image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, q)
                    .write_image(c.window.as_raw(), w, w, image::ExtendedColorType::Rgb8)
                    .unwrap();
                out
            },
            |b| {
                std::hint::black_box(image::load_from_memory(b).unwrap());
            },
        );
        let (mut sum, mut n, mut worst) = (0u64, 0u64, 0u8);
        for c in &crops {
            let mut out = Vec::new();
            image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, q)
                .write_image(c.window.as_raw(), w, w, image::ExtendedColorType::Rgb8)
                .unwrap();
            let back = image::load_from_memory(&out).unwrap().to_rgb8();
            for (a, b) in c.window.as_raw().iter().zip(back.as_raw()) {
                let d = a.abs_diff(*b);
                sum += d as u64;
                n += 1;
                worst = worst.max(d);
            }
        }
        m.error = Some((sum as f64 / n as f64, worst));
        rows.push(m);
    }

    // The mesh: raw float32, or zstd (of the bytes, and of its byte planes).
    let mesh_bytes = |c: &crop_store::StoredCrop| -> Vec<u8> {
        c.verts
            .iter()
            .flat_map(|p| [p.x, p.y, p.z])
            .flat_map(f32::to_le_bytes)
            .collect()
    };
    let mut mesh_z = 0.0;
    let mut mesh_planes = 0.0;
    for c in &crops {
        let b = mesh_bytes(c);
        mesh_z += zstd::bulk::compress(&b, 19).unwrap().len() as f64;
        let planes: Vec<u8> = (0..4)
            .flat_map(|k| b.iter().skip(k).step_by(4).copied())
            .collect();
        mesh_planes += zstd::bulk::compress(&planes, 19).unwrap().len() as f64;
    }
    let n = crops.len() as f64;
    println!(
        "mesh: raw {:.1} KiB, zstd-19 {:.1} KiB, byte planes + zstd-19 {:.1} KiB",
        mesh_raw / 1024.0,
        mesh_z / n / 1024.0,
        mesh_planes / n / 1024.0
    );
    // The store's mesh codec (coordinate and byte planes, zstd): on these synthetic
    // meshes and on the real face of the resources, which may compress otherwise.
    let verts: Vec<Vec<_>> = crops.iter().map(|c| c.verts.clone()).collect();
    let (mesh_stored, mesh_us) = mesh_codec(&verts);
    println!(
        "mesh codec (synthetic, {} meshes): {:.1} KiB ({:.1}% of raw), decode {:.1} us",
        verts.len(),
        mesh_stored / 1024.0,
        100.0 * mesh_stored / mesh_raw,
        mesh_us
    );
    let real = resources.join("template_verts.npy");
    if real.exists() {
        let v = arkit_core::read_npy(&real).unwrap().to_f32_vec();
        let face = [v
            .chunks_exact(3)
            .map(|c| nalgebra::Point3::new(c[0], c[1], c[2]))
            .collect::<Vec<_>>()];
        let (bytes, us) = mesh_codec(&face);
        println!(
            "mesh codec (the real face, {} vertices): {:.1} KiB ({:.1}% of raw), decode {:.1} us",
            face[0].len(),
            bytes / 1024.0,
            100.0 * bytes / (12.0 * face[0].len() as f64),
            us
        );
    }

    println!(
        "{:<20} {:>12} {:>9} {:>11} {:>11} {:>16}",
        "codec", "KiB/window", "of raw", "encode ms", "decode ms", "error (mean/max)"
    );
    for r in &rows {
        println!(
            "{:<20} {:>12.1} {:>8.1}% {:>11.3} {:>11.3} {:>16}",
            r.name,
            r.bytes / 1024.0,
            100.0 * r.bytes / raw_window,
            r.encode_ms,
            r.decode_ms,
            r.error
                .map(|(m, x)| format!("{m:.2} / {x}"))
                .unwrap_or_else(|| "lossless".into())
        );
    }
    let png = rows.iter().find(|r| r.name == "png").unwrap().decode_ms;
    let jpeg_kib = jpeg_bytes as f64 / n / 1024.0;
    // Window plus raw mesh (the records of format 3), then window plus the mesh codec's
    // bytes (format 4 on), each against the release's JPEG.
    for r in &rows {
        let record = r.bytes + mesh_raw;
        let stored = r.bytes + mesh_stored;
        println!(
            "ratio: {} record / raw record = {:.3} ({:.1} KiB; the release's JPEG {:.1} KiB: {:.2}x; with the mesh codec {:.1} KiB: {:.2}x); decode {:.3} ms / png's = {:.2}",
            r.name,
            record / (raw_window + mesh_raw),
            record / 1024.0,
            jpeg_kib,
            record / 1024.0 / jpeg_kib,
            stored / 1024.0,
            stored / 1024.0 / jpeg_kib,
            r.decode_ms,
            r.decode_ms / png
        );
    }
    // Whole stores, as `arkit-tool crops` writes them (headers, keys, boxes and indexes
    // included), per sample against the release's JPEG.
    for codec in STORE_CODECS {
        let out = tmp.path().join(format!("store-{}", codec.name()));
        let summary =
            arkit_data::loader::write_crop_store_with(&loader, &out, codec, &|_| {}).unwrap();
        println!(
            "ratio: store {} / JPEG = {:.3} ({:.1} KiB a sample, the release's JPEG {:.1} KiB)",
            codec.name(),
            summary.bytes_per_sample / 1024.0 / jpeg_kib,
            summary.bytes_per_sample / 1024.0,
            jpeg_kib
        );
    }
}

/// The mean bytes of `meshes` stored by the store's mesh codec (checked to round-trip
/// bit for bit), and the median time to decode one, in microseconds.
fn mesh_codec(meshes: &[Vec<nalgebra::Point3<f32>>]) -> (f64, f64) {
    let stored: Vec<Vec<u8>> = meshes
        .iter()
        .map(|m| crop_store::encode_mesh(m.as_slice()))
        .collect();
    for (m, s) in meshes.iter().zip(&stored) {
        let back = crop_store::decode_mesh(s, m.len()).unwrap();
        let bits = |v: &[nalgebra::Point3<f32>]| -> Vec<u32> {
            v.iter()
                .flat_map(|p| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
                .collect()
        };
        assert_eq!(bits(&back), bits(m), "mesh round trip");
    }
    let mut k = 0;
    let ms = timing::median_ms(
        || {
            let s = &stored[k % stored.len()];
            std::hint::black_box(crop_store::decode_mesh(s, meshes[0].len()).unwrap());
            k += 1;
        },
        (3 * meshes.len()).max(64),
    );
    let bytes = stored.iter().map(|s| s.len() as f64).sum::<f64>() / stored.len() as f64;
    (bytes, 1000.0 * ms)
}

fn measure(
    name: &str,
    crops: &[crop_store::StoredCrop],
    encode: impl Fn(&crop_store::StoredCrop) -> Vec<u8>,
    decode: impl Fn(&[u8]),
) -> Measured {
    let encoded: Vec<Vec<u8>> = crops.iter().map(&encode).collect();
    let bytes = encoded.iter().map(|e| e.len() as f64).sum::<f64>() / crops.len() as f64;
    let mut k = 0;
    let encode_ms = timing::median_ms(
        || {
            std::hint::black_box(encode(&crops[k % crops.len()]));
            k += 1;
        },
        crops.len().min(48),
    );
    let mut k = 0;
    let decode_ms = timing::median_ms(
        || {
            decode(&encoded[k % encoded.len()]);
            k += 1;
        },
        3 * crops.len(),
    );
    Measured {
        name: name.to_string(),
        bytes,
        encode_ms,
        decode_ms,
        error: None,
    }
}

/// Each byte minus the same channel of its left neighbour (PNG's Sub filter).
fn sub(raw: &[u8], w: usize) -> Vec<u8> {
    let mut out = raw.to_vec();
    for row in out.chunks_exact_mut(3 * w) {
        for i in (3..3 * w).rev() {
            row[i] = row[i].wrapping_sub(row[i - 3]);
        }
    }
    out
}

fn unsub(mut d: Vec<u8>, w: usize) -> Vec<u8> {
    for row in d.chunks_exact_mut(3 * w) {
        for i in 3..3 * w {
            row[i] = row[i].wrapping_add(row[i - 3]);
        }
    }
    d
}

/// The median-edge predictor of LOCO-I: from the left `a`, above `b` and above-left `c`.
fn predict(a: u8, b: u8, c: u8) -> u8 {
    if c >= a.max(b) {
        a.min(b)
    } else if c <= a.min(b) {
        a.max(b)
    } else {
        (a as i16 + b as i16 - c as i16) as u8
    }
}

fn med(raw: &[u8], w: usize) -> Vec<u8> {
    let mut out = raw.to_vec();
    let at = |y: usize, x: usize, k: usize| 3 * (y * w + x) + k;
    for y in 0..raw.len() / (3 * w) {
        for x in 0..w {
            for k in 0..3 {
                let a = if x > 0 { raw[at(y, x - 1, k)] } else { 0 };
                let b = if y > 0 { raw[at(y - 1, x, k)] } else { 0 };
                let c = if x > 0 && y > 0 {
                    raw[at(y - 1, x - 1, k)]
                } else {
                    0
                };
                out[at(y, x, k)] = raw[at(y, x, k)].wrapping_sub(predict(a, b, c));
            }
        }
    }
    out
}

fn unmed(mut d: Vec<u8>, w: usize) -> Vec<u8> {
    let at = |y: usize, x: usize, k: usize| 3 * (y * w + x) + k;
    for y in 0..d.len() / (3 * w) {
        for x in 0..w {
            for k in 0..3 {
                let a = if x > 0 { d[at(y, x - 1, k)] } else { 0 };
                let b = if y > 0 { d[at(y - 1, x, k)] } else { 0 };
                let c = if x > 0 && y > 0 {
                    d[at(y - 1, x - 1, k)]
                } else {
                    0
                };
                let i = at(y, x, k);
                d[i] = d[i].wrapping_add(predict(a, b, c));
            }
        }
    }
    d
}

fn walk(dir: &std::path::Path) -> u64 {
    let mut total = 0;
    for e in std::fs::read_dir(dir).unwrap() {
        let e = e.unwrap();
        let t = e.file_type().unwrap();
        if t.is_dir() {
            total += walk(&e.path());
        } else if e.path().extension().is_some_and(|x| x == "jpg") {
            total += e.metadata().unwrap().len();
        }
    }
    total
}
