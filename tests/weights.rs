//! `import-weights` / `export-weights`: the official `state_dict` names, shapes and
//! buffers; a bit-exact round trip; mismatched files refused with the list of what is
//! wrong; and (when a Python with torch is at hand) a file written by `torch.save`.

use crate::support::tool;
use arkit_perspnet::{PerspNet, PerspNetConfig, export_state_dict, state_dict_entries};
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Runs `cmd` and asserts that it succeeded, showing its stderr otherwise.
fn run_ok(cmd: &mut Command) {
    let out = cmd.output().unwrap();
    assert!(
        out.status.success(),
        "{cmd:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// `import-weights FILE --config tiny --output MODEL`, then checks that the model folder
/// holds `vm`'s weights and records `steps`.
fn import_tiny(file: &Path, model: &Path, vm: &VarMap, steps: u64) {
    run_ok(
        tool()
            .args(["import-weights", file.to_str().unwrap(), "--config", "tiny"])
            .args(["--output", model.to_str().unwrap()]),
    );
    same_weights(model, vm);
    let c: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(model.join("perspnet.json")).unwrap())
            .unwrap();
    assert_eq!(c["steps"], steps);
}

/// A tiny network with seeded weights and batch-norm statistics that are not the
/// defaults (so the buffers are carried, not re-created).
fn random_varmap(cfg: &PerspNetConfig, seed: u64) -> VarMap {
    let vm = VarMap::new();
    let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
    let topo = &arkit_data::mesh::builtin().topology;
    PerspNet::new(
        cfg,
        &arkit_perspnet::vertex_uv(topo, &Device::Cpu).unwrap(),
        vb,
    )
    .unwrap();
    arkit_perspnet::reseed(&vm, seed, 0.05).unwrap();
    let data = vm.data().lock().unwrap();
    let mut k = 0f32;
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    for name in names {
        if name.contains("running_") {
            let v = &data[name];
            let n = v.elem_count();
            let vals: Vec<f32> = (0..n)
                .map(|i| 0.5 + ((i as f32 + k) * 0.37).sin().abs())
                .collect();
            v.set(&Tensor::from_vec(vals, n, &Device::Cpu).unwrap())
                .unwrap();
            k += 1.0;
        }
    }
    drop(data);
    vm
}

fn save(entries: &[(String, Tensor)], path: &Path) {
    let map: HashMap<String, Tensor> = entries.iter().cloned().collect();
    candle_core::safetensors::save(&map, path).unwrap();
}

fn bits(t: &Tensor) -> Vec<u8> {
    match t.dtype() {
        DType::I64 => t
            .flatten_all()
            .unwrap()
            .to_vec1::<i64>()
            .unwrap()
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect(),
        _ => t
            .to_dtype(DType::F32)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap()
            .iter()
            .flat_map(|v| v.to_bits().to_le_bytes())
            .collect(),
    }
}

fn same_files(a: &Path, b: &Path) {
    let x = candle_core::safetensors::load(a, &Device::Cpu).unwrap();
    let y = candle_core::safetensors::load(b, &Device::Cpu).unwrap();
    assert_eq!(x.len(), y.len());
    for (k, t) in &x {
        let u = &y[k];
        assert_eq!((t.dims(), t.dtype()), (u.dims(), u.dtype()), "{k}");
        assert!(bits(t) == bits(u), "{k} differs");
    }
}

/// The model folder's weights equal `vm`'s, bit for bit.
fn same_weights(dir: &Path, vm: &VarMap) {
    let got = candle_core::safetensors::load(dir.join("model.safetensors"), &Device::Cpu).unwrap();
    let data = vm.data().lock().unwrap();
    assert_eq!(got.len(), data.len());
    for (k, v) in data.iter() {
        assert!(bits(&got[k]) == bits(v.as_tensor()), "{k} differs");
    }
}

#[test]
fn export_import_export_is_bit_exact() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = PerspNetConfig::tiny();
    let vm = random_varmap(&cfg, 7);
    let first = dir.path().join("first.safetensors");
    let entries = export_state_dict(&vm, 1234).unwrap();
    assert_eq!(entries.len(), state_dict_entries(&vm).len());
    save(&entries, &first);
    let model = dir.path().join("model");
    import_tiny(&first, &model, &vm, 1234);
    let second = dir.path().join("second.safetensors");
    run_ok(
        tool()
            .args(["export-weights", model.to_str().unwrap(), "--output"])
            .arg(&second),
    );
    same_files(&first, &second);
    // The imported folder predicts like any other: it loads as a trained model.
    let topo = &arkit_data::mesh::builtin().topology;
    arkit_perspnet::load(&model, topo).unwrap();
}

#[test]
fn mismatched_files_are_refused_with_the_list() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = PerspNetConfig::tiny();
    let vm = random_varmap(&cfg, 3);
    let mut entries = export_state_dict(&vm, 0).unwrap();
    entries.retain(|(n, _)| n != "cnn.seg.bias");
    for (n, t) in entries.iter_mut() {
        if n == "assignment.4.weight" {
            *t = t.squeeze(2).unwrap();
        }
    }
    entries.push((
        "cnn.extra.weight".into(),
        Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap(),
    ));
    let bad = dir.path().join("bad.safetensors");
    save(&entries, &bad);
    let model = dir.path().join("model");
    let run = |file: &Path, config: &str| {
        tool()
            .args(["import-weights", file.to_str().unwrap(), "--config", config])
            .args(["--output", model.to_str().unwrap()])
            .output()
            .unwrap()
    };
    let out = run(&bad, "tiny");
    assert!(!out.status.success());
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(e.contains("1 missing: cnn.seg.bias"), "{e}");
    assert!(e.contains("1 extra: cnn.extra.weight"), "{e}");
    assert!(
        e.contains("assignment.4.weight is [1220, 64], expected [1220, 64, 1]"),
        "{e}"
    );
    assert!(!model.exists(), "nothing is written");
    // The right file for another network: every shape that differs is listed.
    let good = dir.path().join("good.safetensors");
    save(&export_state_dict(&vm, 0).unwrap(), &good);
    let e = String::from_utf8_lossy(&run(&good, "paper").stderr).into_owned();
    assert!(
        e.contains("misshapen: ") && e.contains("expected [512, 2176, 1]"),
        "{e}"
    );
    assert!(!model.exists());
    // Not weights at all.
    let junk = dir.path().join("junk.pth");
    std::fs::write(&junk, b"PK\x03\x04 this is no zip archive").unwrap();
    let e = String::from_utf8_lossy(&run(&junk, "tiny").stderr).into_owned();
    assert!(e.contains("not a PyTorch state_dict"), "{e}");
    std::fs::write(&junk, [7u8; 64]).unwrap();
    let e = String::from_utf8_lossy(&run(&junk, "tiny").stderr).into_owned();
    assert!(e.contains("neither a PyTorch zip"), "{e}");
    assert!(!model.exists());
}

/// A Python with torch: `ARKIT_TORCH_PYTHON`, else /tmp/tv2/bin/python, else python3.
fn torch_python() -> Option<PathBuf> {
    let candidates = [
        std::env::var_os("ARKIT_TORCH_PYTHON").map(PathBuf::from),
        Some(PathBuf::from("/tmp/tv2/bin/python")),
        Some(PathBuf::from("python3")),
    ];
    candidates.into_iter().flatten().find(|p| {
        Command::new(p)
            .args(["-c", "import torch"])
            .output()
            .is_ok_and(|o| o.status.success())
    })
}

/// `torch.save` of a state_dict (PyTorch's zip and pickle, with a `module.` prefix as
/// DataParallel writes it) imports to the same weights, bit for bit.
#[test]
fn a_torch_saved_state_dict_imports() {
    let Some(python) = torch_python() else {
        eprintln!(
            "SKIPPED a_torch_saved_state_dict_imports: no Python with torch (set ARKIT_TORCH_PYTHON)"
        );
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let cfg = PerspNetConfig::tiny();
    let vm = random_varmap(&cfg, 11);
    let st = dir.path().join("w.safetensors");
    save(&export_state_dict(&vm, 42).unwrap(), &st);
    let pth = dir.path().join("w.pth");
    let script =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/torch_save_state_dict.py");
    run_ok(Command::new(&python).arg(&script).arg(&st).arg(&pth));
    import_tiny(&pth, &dir.path().join("model"), &vm, 42);
}

/// `predict --dump`: every predicted sample's inputs and raw outputs, consistent with
/// each other (rows of M sum to 1, `points` is `M X`), and the dumped inputs fed to the
/// network again give the dumped outputs.
#[test]
fn predict_dump_holds_inputs_and_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n).to_str().unwrap().to_string();
    let ok = |args: &[&str]| run_ok(tool().args(args));
    let cfg = PerspNetConfig::tiny();
    let vm = random_varmap(&cfg, 5);
    let w = dir.path().join("w.safetensors");
    save(&export_state_dict(&vm, 0).unwrap(), &w);
    ok(&[
        "import-weights",
        w.to_str().unwrap(),
        "--config",
        "tiny",
        "--output",
        &p("model"),
    ]);
    ok(&[
        "synth",
        "--output",
        &p("synth"),
        "--subjects",
        "2",
        "--images-per-subject",
        "2",
        "--size",
        "128x128",
    ]);
    ok(&["convert", "--input", &p("synth"), "--output", &p("pq")]);
    // --dump needs a network.
    let out = tool()
        .args([
            "predict",
            "--oracle",
            "--dataset",
            &p("pq"),
            "--output",
            &p("o.parquet"),
            "--dump",
            &p("x.npz"),
        ])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("invalid --dump"));
    ok(&[
        "predict",
        "--model",
        &p("model"),
        "--dataset",
        &p("pq"),
        "--split",
        "all",
        "--output",
        &p("pred.parquet"),
        "--dump",
        &p("dump.npz"),
    ]);
    let npz = arkit_core::read_npz(&dir.path().join("dump.npz")).unwrap();
    let samples: std::collections::BTreeSet<String> = npz
        .keys()
        .filter_map(|k| k.strip_suffix("/image").map(str::to_string))
        .collect();
    assert_eq!(samples.len(), 4);
    assert_eq!(npz.require("vertex_uv").unwrap().shape(), &[1220, 2]);
    let (s, m, v) = (cfg.input_size, cfg.points, cfg.vertices);
    let topo = &arkit_data::mesh::builtin().topology;
    let model = arkit_perspnet::load(&dir.path().join("model"), topo).unwrap();
    for key in &samples {
        let get = |n: &str| npz.require(&format!("{key}/{n}")).unwrap();
        assert_eq!(get("image").shape(), &[3, s, s]);
        assert_eq!(get("seg_logits").shape(), &[2, s, s]);
        assert_eq!(get("uv_map").shape(), &[3, s, s]);
        assert_eq!(get("assignment").shape(), &[m, v]);
        assert_eq!(get("points").shape(), &[m, 3]);
        let a = get("assignment").to_f32_vec();
        let x = get("vertices").to_f32_vec();
        let pts = get("points").to_f32_vec();
        for i in 0..m {
            let row = &a[i * v..(i + 1) * v];
            assert!((row.iter().sum::<f32>() - 1.0).abs() < 1e-4);
            for c in 0..3 {
                let mx: f32 = row.iter().enumerate().map(|(j, r)| r * x[j * 3 + c]).sum();
                assert!(
                    (mx - pts[i * 3 + c]).abs() < 1e-4 * (1.0 + mx.abs()),
                    "{key} point {i}"
                );
            }
        }
        let choose: Vec<u32> = match get("choose").data() {
            arkit_core::ArrayData::I64(c) => c.iter().map(|&c| c as u32).collect(),
            other => panic!("choose is {other:?}"),
        };
        assert!(choose.iter().all(|&c| (c as usize) < s * s));
        // The dumped inputs reproduce the dumped outputs.
        let img = Tensor::from_vec(get("image").to_f32_vec(), (1, 3, s, s), &Device::Cpu).unwrap();
        let ch = Tensor::from_vec(choose, (1, m), &Device::Cpu).unwrap();
        let out = model
            .net
            .perspnet("test")
            .unwrap()
            .forward(&img, &ch, false)
            .unwrap();
        let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(
            flat(&out.dense.seg_logits),
            get("seg_logits").to_f32_vec(),
            "{key}"
        );
        assert_eq!(flat(&out.dense.uv_map), get("uv_map").to_f32_vec(), "{key}");
        assert_eq!(flat(&out.assignment().unwrap()), a, "{key}");
    }
}

/// `half-model` writes float16 weights that load back as float32 within float16's
/// rounding of the originals, at half the size; a weights file missing a tensor is
/// refused with the tensor and the file named.
#[test]
fn half_model_loads_within_float16_rounding() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = PerspNetConfig::tiny();
    let vm = random_varmap(&cfg, 11);
    let file = dir.path().join("w.safetensors");
    save(&export_state_dict(&vm, 5).unwrap(), &file);
    let model = dir.path().join("model");
    let half = dir.path().join("half");
    for args in [
        vec![
            "import-weights",
            file.to_str().unwrap(),
            "--config",
            "tiny",
            "--output",
            model.to_str().unwrap(),
        ],
        vec![
            "half-model",
            model.to_str().unwrap(),
            "--output",
            half.to_str().unwrap(),
        ],
    ] {
        run_ok(tool().args(&args));
    }
    let size = |d: &Path| {
        std::fs::metadata(d.join("model.safetensors"))
            .unwrap()
            .len()
    };
    let (full, small) = (size(&model), size(&half));
    assert!(
        small * 2 <= full + 64 * 1024 && small * 2 >= full - 64 * 1024,
        "{small} vs {full}"
    );
    let stored =
        candle_core::safetensors::load(half.join("model.safetensors"), &Device::Cpu).unwrap();
    assert!(stored.values().all(|t| t.dtype() == DType::F16));
    assert_eq!(
        std::fs::read(model.join("perspnet.json")).unwrap(),
        std::fs::read(half.join("perspnet.json")).unwrap()
    );
    let topo = &arkit_data::mesh::builtin().topology;
    let (a, b) = (
        arkit_perspnet::load(&model, topo).unwrap(),
        arkit_perspnet::load(&half, topo).unwrap(),
    );
    let (da, db) = (
        a.varmap.data().lock().unwrap(),
        b.varmap.data().lock().unwrap(),
    );
    let mut changed = 0;
    for (k, v) in da.iter() {
        let x = v
            .as_tensor()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let w = db[k].as_tensor();
        assert_eq!(w.dtype(), DType::F32, "{k}");
        let y = w.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        for (p, q) in x.iter().zip(&y) {
            // float16: 11 significant bits; below 2^-14 a fixed step of 2^-24.
            assert!((p - q).abs() <= p.abs() / 2048.0 + 6e-8, "{k}: {p} -> {q}");
            changed += (p != q) as usize;
        }
    }
    assert!(changed > 0, "nothing was rounded: the file was not float16");
    drop((da, db));

    // Both writers end with a record of their files: weights swapped in afterwards
    // (the float32 ones beside the float16 folder's config and record) are refused by
    // every reader of the folder, naming the weights.
    std::fs::copy(
        model.join("model.safetensors"),
        half.join("model.safetensors"),
    )
    .unwrap();
    let e = arkit_perspnet::load(&half, topo).err().unwrap().to_string();
    assert!(
        e.contains("model.safetensors: ")
            && e.contains("but checkpoint.json records")
            && e.contains("the model folder is torn"),
        "{e}"
    );
    let out = tool()
        .args(["half-model", half.to_str().unwrap(), "--output"])
        .arg(dir.path().join("half2"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(
        e.contains("model.safetensors: ") && e.contains("checkpoint.json records"),
        "{e}"
    );
    assert!(!dir.path().join("half2").exists());

    // A weights file without one of the network's tensors names it and the file (the
    // folder edited by hand, without a record).
    std::fs::remove_file(model.join(arkit_perspnet::CHECKPOINT_RECORD)).unwrap();
    let mut tensors =
        candle_core::safetensors::load(model.join("model.safetensors"), &Device::Cpu).unwrap();
    tensors.remove("cnn.seg.bias");
    candle_core::safetensors::save(&tensors, model.join("model.safetensors")).unwrap();
    let e = arkit_perspnet::load(&model, topo)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("cnn.seg.bias") && e.contains("model.safetensors"),
        "{e}"
    );
}

/// Runs `cmd`; returns whether it succeeded, its stderr, its wall time and its peak
/// resident memory in KiB, or None when it cannot be measured here.
///
/// The peak is the tool's own: a child started straight from this test process would
/// report this process's high-water mark (Linux carries it over on exec, and the other
/// tests of this binary grow it), so the tool is started by a small Python process
/// that forks it and reports its `ru_maxrss` from `wait4`. Without python3 the peak is
/// not measured (and the caller says so).
fn run_measured(cmd: &mut Command) -> (bool, String, Duration, Option<i64>) {
    const REPORT: &str = "\narkit-test-maxrss-kib ";
    let script = "import os, sys\n\
        pid = os.fork()\n\
        if pid == 0:\n    os.execv(sys.argv[1], sys.argv[1:])\n\
        _, status, ru = os.wait4(pid, 0)\n\
        sys.stderr.write('\\narkit-test-maxrss-kib %d\\n' % ru.ru_maxrss)\n\
        sys.exit(os.waitstatus_to_exitcode(status))\n";
    let python = Command::new("python3")
        .args(["-c", "pass"])
        .output()
        .is_ok_and(|o| o.status.success());
    let mut run = if python {
        let mut w = Command::new("python3");
        w.args(["-c", script])
            .arg(cmd.get_program())
            .args(cmd.get_args());
        for (k, v) in cmd.get_envs() {
            match v {
                Some(v) => w.env(k, v),
                None => w.env_remove(k),
            };
        }
        if let Some(d) = cmd.get_current_dir() {
            w.current_dir(d);
        }
        w
    } else {
        let mut w = Command::new(cmd.get_program());
        w.args(cmd.get_args());
        w
    };
    let t = Instant::now();
    let out = run
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .output()
        .unwrap();
    let dt = t.elapsed();
    let mut e = String::from_utf8_lossy(&out.stderr).into_owned();
    let mut rss = None;
    if python {
        let at = e.rfind(REPORT).expect("the measuring wrapper's report");
        rss = Some(e[at + REPORT.len()..].trim().parse().unwrap());
        e.truncate(at);
    }
    (out.status.success(), e, dt, rss)
}

/// A zip laid out as `torch.save` lays it out, with `pickle` as its `data.pkl`.
fn torch_zip(path: &Path, pickle: &[u8]) {
    let mut z = zip::ZipWriter::new(std::fs::File::create(path).unwrap());
    let o =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for (name, data) in [
        ("archive/data.pkl", pickle),
        ("archive/byteorder", b"little".as_slice()),
        ("archive/version", b"3\n".as_slice()),
    ] {
        z.start_file(name, o).unwrap();
        z.write_all(data).unwrap();
    }
    z.finish().unwrap();
}

fn import_args(file: &Path, model: &Path) -> Command {
    let mut c = tool();
    c.args(["import-weights", file.to_str().unwrap(), "--config", "tiny"])
        .args(["--output", model.to_str().unwrap()]);
    c
}

/// What a refused file may cost: well under a second, and 150 MiB at most (the tool's
/// own footprint is about 20 MiB).
fn refused_cheaply(cmd: &mut Command, wanted: &str) {
    let (ok, e, dt, rss) = run_measured(cmd);
    assert!(!ok, "accepted: {cmd:?}");
    assert!(e.contains(wanted), "{e}");
    assert!(dt < Duration::from_millis(1500), "{dt:?}: {e}");
    match rss {
        Some(rss) => {
            assert!(rss < 150 * 1024, "peak {rss} KiB: {e}");
            eprintln!("refused in {dt:?}, peak {} MiB: {}", rss / 1024, e.trim());
        }
        None => eprintln!(
            "refused in {dt:?} (peak memory not measured: no python3): {}",
            e.trim()
        ),
    }
}

/// Pickle bombs in a torch.save archive: 10^6 nested tuples (1 MB, which overflowed
/// the stack) and a memo entry doubled 40 times (a few hundred bytes, which grew
/// without bound when memo entries were copied) are refused at once in little memory;
/// doubled 30 times (2^30 leaves if copied) it is read in no time, and refused for what
/// it is. An entry that is not a tensor is refused by name. Nothing is written.
#[test]
fn pickle_bombs_and_non_tensors_are_refused_quickly() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("model");
    let nested = dir.path().join("nested.pth");
    let mut p = b"\x80\x02)".to_vec();
    p.extend(std::iter::repeat_n(0x85u8, 1_000_000));
    p.push(b'.');
    torch_zip(&nested, &p);
    assert!(std::fs::metadata(&nested).unwrap().len() > 1_000_000);
    refused_cheaply(
        &mut import_args(&nested, &model),
        "nested more than 32 deep",
    );
    let double = |n: usize| {
        let mut p = b"\x80\x02X\x01\x00\x00\x00aq\x000".to_vec();
        for _ in 0..n {
            p.extend(b"h\x00h\x00\x86q\x000");
        }
        p.extend(b"h\x00.");
        p
    };
    let memo = dir.path().join("memo.pth");
    torch_zip(&memo, &double(40));
    refused_cheaply(&mut import_args(&memo, &model), "nested more than 32 deep");
    torch_zip(&memo, &double(30));
    refused_cheaply(
        &mut import_args(&memo, &model),
        "the pickle holds a tuple, not a state_dict",
    );
    let extra =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus/torch_pickle/non_tensor_entry.pth");
    refused_cheaply(
        &mut import_args(&extra, &model),
        "entry 'epoch' is an integer, not a tensor",
    );
    assert!(!model.exists(), "nothing is written");
}

/// A safetensors header of `entries` (name, shape of float32) over sparse data: the
/// file is as long as the header says, but holds no data on disk.
fn sparse_safetensors(path: &Path, entries: &[(&str, u64)]) {
    let mut at = 0u64;
    let mut fields = Vec::new();
    for (name, n) in entries {
        fields.push(format!(
            r#""{name}":{{"dtype":"F32","shape":[{n}],"data_offsets":[{at},{}]}}"#,
            at + 4 * n
        ));
        at += 4 * n;
    }
    let header = format!("{{{}}}", fields.join(","));
    let mut f = std::fs::File::create(path).unwrap();
    f.write_all(&(header.len() as u64).to_le_bytes()).unwrap();
    f.write_all(header.as_bytes()).unwrap();
    f.set_len(8 + header.len() as u64 + at).unwrap();
}

/// A 1.2 GiB sparse safetensors file with the wrong names, as an import and as a model
/// folder's weights (read by export-weights, half-model and predict's loader), is
/// refused from its header in well under a second without reading its data; a header
/// declaring 100 GB in a small file is refused without the allocation.
#[test]
fn safetensors_headers_are_checked_before_any_data_is_read() {
    let dir = tempfile::tempdir().unwrap();
    let huge = dir.path().join("huge.safetensors");
    sparse_safetensors(&huge, &[("cnn.wrong.weight", 322_122_547)]);
    assert!(std::fs::metadata(&huge).unwrap().len() > 1_288_000_000);
    let model = dir.path().join("imported");
    refused_cheaply(&mut import_args(&huge, &model), "1 extra: cnn.wrong.weight");
    assert!(!model.exists());
    // A good model folder whose weights are then replaced by the huge file.
    let vm = random_varmap(&PerspNetConfig::tiny(), 5);
    let good = dir.path().join("good.safetensors");
    save(&export_state_dict(&vm, 0).unwrap(), &good);
    import_tiny(&good, &model, &vm, 0);
    // Without the folder's record (which would refuse any other weights by their
    // size), so that the weights' own header checks are what is tried.
    std::fs::remove_file(model.join(arkit_perspnet::CHECKPOINT_RECORD)).unwrap();
    std::fs::copy(&huge, model.join("model.safetensors")).unwrap();
    let out = dir.path().join("out.safetensors");
    refused_cheaply(
        tool()
            .args(["export-weights", model.to_str().unwrap(), "--output"])
            .arg(&out),
        "no tensor ",
    );
    refused_cheaply(
        tool()
            .args(["half-model", model.to_str().unwrap(), "--output"])
            .arg(dir.path().join("half")),
        "no tensor ",
    );
    assert!(!out.exists());
    // 100 GB declared, 16 bytes there.
    let liar = dir.path().join("liar.safetensors");
    let header = r#"{"w":{"dtype":"F32","shape":[25000000000],"data_offsets":[0,100000000000]}}"#;
    let mut b = (header.len() as u64).to_le_bytes().to_vec();
    b.extend(header.as_bytes());
    b.extend([0u8; 16]);
    std::fs::write(&liar, &b).unwrap();
    refused_cheaply(
        &mut import_args(&liar, &dir.path().join("m2")),
        "declares 100000000000 bytes of tensor data, the file holds 16",
    );
    std::fs::copy(&liar, model.join("model.safetensors")).unwrap();
    refused_cheaply(
        tool()
            .args(["export-weights", model.to_str().unwrap(), "--output"])
            .arg(&out),
        "declares 100000000000 bytes of tensor data",
    );
}

/// The release's topology folder ($ARKIT_RESOURCES, default ../shared/arkitface-resources),
/// when present.
fn real_resources() -> Option<PathBuf> {
    let dir = std::env::var_os("ARKIT_RESOURCES")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/arkitface-resources")
        });
    dir.join("triangles.npy").exists().then_some(dir)
}

/// `import-weights --json`: what was imported and what `predict` will need.
fn import_json(
    file: &Path,
    config: &str,
    model: &Path,
    resources: Option<&Path>,
) -> (serde_json::Value, String) {
    let mut cmd = tool();
    cmd.args([
        "import-weights",
        file.to_str().unwrap(),
        "--config",
        config,
        "--json",
    ])
    .args(["--output", model.to_str().unwrap()]);
    if let Some(r) = resources {
        cmd.arg("--resources").arg(r);
    }
    let out = cmd.output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "{cmd:?}: {stderr}");
    (serde_json::from_slice(&out.stdout).unwrap(), stderr)
}

#[test]
fn paper_weights_without_resources_say_what_predict_needs() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = PerspNetConfig::paper();
    let vm = random_varmap(&cfg, 11);
    let file = dir.path().join("paper.safetensors");
    save(&export_state_dict(&vm, 0).unwrap(), &file);
    let builtin = &arkit_data::mesh::builtin().topology;

    // Without --resources: imported, with a warning on stderr and in the JSON.
    let model = dir.path().join("model");
    let (v, stderr) = import_json(&file, "paper", &model, None);
    let warning = v["warning"].as_str().expect("a warning in the JSON");
    assert!(warning.contains("--resources"), "{warning}");
    assert!(stderr.contains(&format!("warning: {warning}")), "{stderr}");
    assert!(v["predict_resources"].is_null(), "{v}");
    assert_eq!(v["topology"], builtin.source.as_str());
    assert!(
        v["predict_needs"]
            .as_str()
            .unwrap()
            .contains("no --resources"),
        "{v}"
    );
    same_weights(&model, &vm);
    // What it says holds: predict's loader takes the model without --resources ...
    arkit_perspnet::load(&model, builtin).unwrap();

    // A tiny model without --resources is the synthetic case: no warning.
    let tiny = random_varmap(&PerspNetConfig::tiny(), 12);
    let tiny_file = dir.path().join("tiny.safetensors");
    save(&export_state_dict(&tiny, 0).unwrap(), &tiny_file);
    let (v, stderr) = import_json(&tiny_file, "tiny", &dir.path().join("tiny"), None);
    assert!(v["warning"].is_null(), "{v}");
    assert!(!stderr.contains("warning"), "{stderr}");

    let Some(r) = real_resources() else {
        eprintln!("SKIPPED: the release's topology folder is absent; the --resources half not run");
        return;
    };
    // ... and refuses it with the release's topology, as the warning says.
    let real = arkit_data::mesh::FaceTopology::from_resources(&r).unwrap();
    let e = arkit_perspnet::load(&model, &real)
        .err()
        .expect("refused with --resources")
        .to_string();
    assert!(e.contains("trained with the topology"), "{e}");
    // With --resources: no warning, and predict needs that folder.
    let with = dir.path().join("with");
    let (v, stderr) = import_json(&file, "paper", &with, Some(&r));
    assert!(v["warning"].is_null(), "{v}");
    assert!(!stderr.contains("warning"), "{stderr}");
    assert_eq!(v["predict_resources"], r.display().to_string());
    arkit_perspnet::load(&with, &real).unwrap();
    assert!(arkit_perspnet::load(&with, builtin).is_err());
}
