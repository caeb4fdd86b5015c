//! Timing of forward (batch 1) and a full training step (batch 4) for the
//! `tiny` and `paper` configurations. Run with
//! `cargo bench --bench perspnet -- [tiny|paper|both] [reps]`.
//!
//! `cargo bench --bench perspnet -- network MODEL_DIR [reps]` times inference alone on
//! a model folder (built-in topology): milliseconds a crop (the best of `reps`) for the network as
//! `predict --image` ran it before (the dense network once for the mask, then the whole
//! network), as it runs now (`predict_crops`: the dense network once), for one crop and
//! for three in one batch. `python/bench/predict.py` runs it beside onnxruntime and
//! PyTorch.

use std::time::Instant;

use arkit_perspnet::Adam;
use arkit_perspnet::{CorrTarget, LossTargets, PerspNet, PerspNetConfig};
use arkit_perspnet::{LossWeights, perspnet_loss};
use arkit_perspnet::{named_trainable_vars, parameter_count, synthetic_vertex_uv, trainable_vars};
use candle_core::{DType, Device, Result, Tensor};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarBuilder, VarMap};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    v[v.len() / 2]
}

fn run(name: &str, cfg: &PerspNetConfig, reps: usize) -> Result<()> {
    let dev = Device::Cpu;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &dev);
    let uv = synthetic_vertex_uv(cfg.vertices, &dev)?;
    let net = PerspNet::new(cfg, &uv, vb)?;
    println!(
        "{name}: {:.3} M parameters ({:.3} M encoder+decoders)",
        parameter_count(&varmap, "") as f64 / 1e6,
        parameter_count(&varmap, "cnn.") as f64 / 1e6
    );
    let (s, m, v) = (cfg.input_size, cfg.points, cfg.vertices);
    let mk = |b: usize| -> Result<(Tensor, Tensor)> {
        let img = Tensor::randn(0f32, 1., (b, 3, s, s), &dev)?;
        let ch: Vec<u32> = (0..b * m).map(|i| ((i * 37) % (s * s)) as u32).collect();
        Ok((img, Tensor::from_vec(ch, (b, m), &dev)?))
    };

    let (img1, ch1) = mk(1)?;
    let _ = net.forward(&img1, &ch1, false)?; // warm-up
    let mut fwd = Vec::new();
    let mut dense = Vec::new();
    for _ in 0..reps {
        let t = Instant::now();
        let _ = net.forward_dense(&img1, false)?;
        dense.push(t.elapsed().as_secs_f64());
        let t = Instant::now();
        let _ = net.forward(&img1, &ch1, false)?;
        fwd.push(t.elapsed().as_secs_f64());
    }

    let b = 4;
    let (img, ch) = mk(b)?;
    let ids: Vec<u32> = (0..b * m * 3).map(|i| (i % v) as u32).collect();
    let ids = Tensor::from_vec(ids, (b, m, 3), &dev)?;
    let wts = Tensor::full(1f32 / 3., (b, m, 3), &dev)?;
    let corr = CorrTarget::Sparse { ids, weights: wts };
    let nocs = Tensor::zeros((b, m, 3), DType::F32, &dev)?;
    let model = Tensor::zeros((b, v, 3), DType::F32, &dev)?;
    let mask = Tensor::zeros((b, s, s), DType::F32, &dev)?;
    let targets = LossTargets {
        nocs: &nocs,
        model: &model,
        seg_mask: &mask,
        corr: &corr,
        uv_map: None,
    };
    let mut opt = Adam::new(named_trainable_vars(&varmap), 1e-4)?;
    let weights = LossWeights::default();
    let mut steps = Vec::new();
    let mut fwd_train = Vec::new();
    let mut bwd = Vec::new();
    for _ in 0..reps.max(2) {
        let t = Instant::now();
        let out = net.forward(&img, &ch, true)?;
        let terms = perspnet_loss(&out, &targets, &weights)?;
        fwd_train.push(t.elapsed().as_secs_f64());
        let grads = terms.total.backward()?;
        bwd.push(t.elapsed().as_secs_f64());
        opt.step(&grads)?;
        steps.push(t.elapsed().as_secs_f64());
    }
    // The optimiser step alone, ours against candle's AdamW on the same gradients.
    let grads = perspnet_loss(&net.forward(&img, &ch, true)?, &targets, &weights)?
        .total
        .backward()?;
    let mut candle_opt = AdamW::new(
        trainable_vars(&varmap),
        ParamsAdamW {
            lr: 1e-4,
            weight_decay: 0.0,
            ..Default::default()
        },
    )?;
    let (mut ours_s, mut candle_s) = (Vec::new(), Vec::new());
    for _ in 0..reps.max(3) {
        let t = Instant::now();
        opt.step(&grads)?;
        ours_s.push(t.elapsed().as_secs_f64());
        let t = Instant::now();
        candle_opt.step(&grads)?;
        candle_s.push(t.elapsed().as_secs_f64());
    }
    let (ours_ms, candle_ms) = (median(ours_s) * 1e3, median(candle_s) * 1e3);
    println!("{name}: optimiser step: ours {ours_ms:.2} ms, candle AdamW {candle_ms:.2} ms");
    println!(
        "ratio: adam {name}: ours / candle AdamW = {:.2}x",
        ours_ms / candle_ms
    );
    let (fwd_s, step_s) = (median(fwd.clone()), median(steps.clone()));
    println!(
        "{name}: forward b=1 eval: full {:.1} ms, encoder+decoders {:.1} ms | train step b=4: {:.3} s (forward+loss {:.3} s, +backward {:.3} s)",
        median(fwd) * 1e3,
        median(dense) * 1e3,
        median(steps),
        median(fwd_train),
        median(bwd)
    );
    // The official PyTorch model on this machine's CPU (../shared/measurements.md).
    let (torch_fwd_ms, torch_step_s) = match name {
        "paper" => (81.0, 1.0),
        _ => (f64::NAN, 0.036),
    };
    let forward = if torch_fwd_ms.is_finite() {
        format!("{:.1}x forward", fwd_s * 1e3 / torch_fwd_ms)
    } else {
        "forward: no PyTorch figure".to_string()
    };
    println!(
        "ratio: perspnet {name}: candle / PyTorch = {forward}, {:.1}x training step",
        step_s / torch_step_s
    );
    Ok(())
}

/// `network MODEL_DIR`: inference alone, milliseconds a crop.
fn network(dir: &str, reps: usize) -> std::result::Result<(), Box<dyn std::error::Error>> {
    use arkit_perspnet::{CropInput, predict_crops};
    let topology = arkit_data::mesh::builtin().topology.clone();
    let model = arkit_perspnet::load(std::path::Path::new(dir), &topology)?;
    let net = model.net.perspnet("the network bench")?;
    let s = model.checkpoint.config.input_size;
    let inputs: Vec<Vec<f32>> = (0..3)
        .map(|k| {
            (0..3 * s * s)
                .map(|i| ((i * 7 + k * 131) % 97) as f32 / 48.0 - 1.0)
                .collect()
        })
        .collect();
    let crops: Vec<CropInput> = inputs
        .iter()
        .map(|input| CropInput {
            input,
            seed: 0,
            truth: None,
        })
        .collect();
    let dev = Device::Cpu;
    let img1 = Tensor::from_slice(&inputs[0], (1, 3, s, s), &dev)?;
    predict_crops(&model, &crops, false)?; // warm-up
    let (mut dense, mut one, mut three) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..reps {
        let t = Instant::now();
        net.forward_dense(&img1, false)?;
        dense.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        predict_crops(&model, &crops[..1], false)?;
        one.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        predict_crops(&model, &crops, false)?;
        three.push(t.elapsed().as_secs_f64() * 1e3 / 3.0);
    }
    // The best of the repetitions: on a shared machine a slow one lost its core.
    let best = |v: Vec<f64>| v.into_iter().fold(f64::INFINITY, f64::min);
    let (dense, one, three) = (best(dense), best(one), best(three));
    println!(
        "network {dir}: ms a crop: two passes (before) {:.1}, one pass {one:.1}, 3 crops in one batch {three:.1} (dense part alone {dense:.1})",
        dense + one
    );
    println!(
        "ratio: network {dir}: two passes / one batch of 3 = {:.2}x",
        (dense + one) / three
    );
    Ok(())
}

fn main() -> Result<()> {
    // As the `arkit-tool` binary does (`arkit_tool::allocator`).
    arkit_tool::allocator::keep_freed_memory();
    // `cargo bench` passes `--bench`: keep only our own arguments.
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let which = args.first().map(String::as_str).unwrap_or("both");
    if which == "network" {
        let dir = args.get(1).expect("network MODEL_DIR [reps]");
        let reps = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(5);
        network(dir, reps).map_err(candle_core::Error::msg)?;
        return Ok(());
    }
    let reps: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(5);
    if which == "tiny" || which == "both" {
        run("tiny", &PerspNetConfig::tiny(), reps)?;
    }
    if which == "paper" || which == "both" {
        run("paper", &PerspNetConfig::paper(), reps)?;
    }
    Ok(())
}
