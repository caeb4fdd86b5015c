//! Augment benchmark: face profiling of 800x800 synthetic samples on one thread, stage
//! by stage: triangulation (contour hull, rings, anchors, Delaunay), texture rendering
//! (band warp, depth-tested face layer, bilinear reads) and JPEG encoding (quality 95,
//! as `augment` writes). The target: JPEG encoding is the largest share.
//! Also mirroring and roll for comparison. Run: `cargo bench --bench augment`.

use arkit_data::augment::{Axis, FaceImage};
use arkit_data::ingest::synth::{self, FaceSource, SynthOptions};
use std::time::Instant;

fn main() {
    let source = FaceSource::builtin();
    let options = SynthOptions {
        subjects: 8,
        images_per_subject: 5,
        width: 800,
        height: 800,
        seed: 9,
        ..SynthOptions::default()
    };
    let topo = &source.topology;
    let plan = synth::plan(&options);
    let faces: Vec<FaceImage> = plan
        .iter()
        .map(|p| {
            let s = synth::render_sample(&source, &options, p).unwrap();
            FaceImage {
                image: s.image,
                verts: s.info.verts.clone(),
                pose: s.info.pose().unwrap(),
            }
        })
        .collect();
    let map = topo.mirror_map().unwrap();
    let (mut tri, mut render, mut jpeg, mut mirror, mut roll) = (0.0, 0.0, 0.0, 0.0, 0.0);
    let (mut done, mut skipped) = (0usize, 0usize);
    let reps = 3;
    for _ in 0..reps {
        for f in &faces {
            let e = f.pose.euler();
            // 15 degrees away from zero, as the rule enlarges already-turned faces.
            let change = if e.yaw_deg >= 0.0 { 15.0 } else { -15.0 };
            let cam = arkit_core::conventions::Camera::release(800, 800);
            let t0 = Instant::now();
            let mesh = arkit_data::augment::profile_mesh(topo, &f.verts, &f.pose, &cam);
            let t1 = Instant::now();
            let out = arkit_data::augment::profile(topo, f, Axis::Yaw, change);
            let t2 = Instant::now();
            let (Ok(_), Ok(out)) = (mesh, out) else {
                skipped += 1;
                continue;
            };
            let bytes = arkit_data::picture::jpeg_bytes(&out.image, 95).unwrap();
            let t3 = Instant::now();
            std::hint::black_box(bytes);
            let m = arkit_data::augment::mirror(f, &map).unwrap();
            let t4 = Instant::now();
            let r = arkit_data::augment::roll(f, 10.0);
            let t5 = Instant::now();
            std::hint::black_box((m, r.ok()));
            let tri_s = (t1 - t0).as_secs_f64();
            tri += tri_s;
            // profile() builds the same mesh again: its rendering is the rest.
            render += (t2 - t1).as_secs_f64() - tri_s;
            jpeg += (t3 - t2).as_secs_f64();
            mirror += (t4 - t3).as_secs_f64();
            roll += (t5 - t4).as_secs_f64();
            done += 1;
        }
    }
    let per = |s: f64| 1e3 * s / done.max(1) as f64;
    let total = tri + render + jpeg;
    println!(
        "profiling 800x800, one thread, {done} augmentations ({skipped} skipped: face would leave the image)"
    );
    println!(
        "  triangulation  {:>7.2} ms  {:>5.1}%",
        per(tri),
        100.0 * tri / total
    );
    println!(
        "  rendering      {:>7.2} ms  {:>5.1}%",
        per(render),
        100.0 * render / total
    );
    println!(
        "  JPEG encoding  {:>7.2} ms  {:>5.1}%",
        per(jpeg),
        100.0 * jpeg / total
    );
    println!(
        "  total          {:>7.2} ms  = {:.0} augmented samples per second per thread",
        per(total),
        done as f64 / total
    );
    println!(
        "mirror {:.2} ms, roll {:.2} ms per sample (before encoding)",
        per(mirror),
        per(roll)
    );
    let largest = if jpeg >= render && jpeg >= tri {
        "JPEG encoding"
    } else if render >= tri {
        "rendering"
    } else {
        "triangulation"
    };
    println!("largest share: {largest}");
    println!(
        "ratio: augment per sample / its JPEG encoding alone (the output's floor) = {:.2}x",
        total / jpeg
    );
}
