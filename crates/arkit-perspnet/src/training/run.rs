//! The training loop: options, the learning-rate schedule, seeded initial weights, the
//! shuffled order of shards and examples, one optimiser step per batch, a checkpoint
//! after every epoch, and `--resume`.

use super::checkpoint::{
    ADAM_FILE, Checkpoint, StepLoss, holds_checkpoint, verify_checkpoint, write_checkpoint,
};
use super::data::{Augmentation, Example, ExampleShards, batch};
use crate::adam::Adam;
use crate::candle_error::candle_err;
use crate::config::PerspNetConfig;
use crate::loss::LossTargets;
use crate::loss::PerspNetLoss;
use crate::model::named_trainable_vars;
use crate::network::{Network, vertex_uv};
use crate::weights::{load_weights, open_weights};
use arkit_core::Rng;
use arkit_core::{Error, Result};
use arkit_data::loader::LoaderItem;
use arkit_data::mesh::FaceTopology;
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use std::path::{Path, PathBuf};

/// The learning rate of `step` of `total`: `base` for the first `hold` share of the
/// run, then falling linearly to zero at the end (the paper's schedule, scaled to the
/// run's length).
pub fn learning_rate_at(step: usize, total: usize, base: f64, hold: f64) -> f64 {
    let hold_steps = (hold.clamp(0.0, 1.0) * total as f64).round() as usize;
    if step < hold_steps || total <= hold_steps {
        base
    } else {
        base * (total - step) as f64 / (total - hold_steps) as f64
    }
}

/// Training options.
#[derive(Clone, Debug)]
pub struct TrainOptions {
    /// Network.
    pub config: PerspNetConfig,
    /// Passes over the examples.
    pub epochs: usize,
    /// A step budget instead: stop after this many steps (the last epoch may end part
    /// way; the schedule is scaled to the budget). `epochs` must cover it.
    pub max_steps: Option<usize>,
    /// Examples per step.
    pub batch: usize,
    /// AdamW learning rate (the official Adam uses 1e-4 at batch 32 on GPUs; small
    /// CPU runs learn faster with more).
    pub learning_rate: f64,
    /// Share of the steps at the full rate; the rate then falls linearly to zero
    /// ([`learning_rate_at`]).
    pub lr_hold: f64,
    /// Augmentation drawn per example and step.
    pub augmentation: Augmentation,
    /// Start the loss at the weights the official schedule lowers to once `L_corr`
    /// falls below 0.1 (KL and segmentation 0.01) instead of waiting for a batch to get
    /// there: short CPU runs otherwise spend most steps with the KL term dominating.
    pub lowered_start: bool,
    /// Seed of the weights and the shuffling.
    pub seed: u64,
    /// Checkpoint folder.
    pub output: PathBuf,
    /// Continue from the checkpoint in `output` (written after each epoch) when there is
    /// one made with the same settings: its weights, Adam's moments (`adam.safetensors`),
    /// the loss weights, its loss log, the same sample order, augmentation and
    /// learning-rate schedule from the next epoch on, so the resumed run is step for
    /// step the uninterrupted one. (A checkpoint written before the optimiser state
    /// was stored has no `adam.safetensors`: its moments restart from zero.)
    pub resume: bool,
}

impl TrainOptions {
    /// Checks the options a caller (the CLI, or code using the library) can get wrong:
    /// at least one epoch and one sample per batch, a positive finite learning rate, a
    /// hold fraction in [0, 1], a colour jitter in [0, 1], no `--lowered-start` with the
    /// paper's loss (its weights are fixed).
    pub fn validate(&self) -> Result<()> {
        let bad = |what: &str, why: String| Err(Error::invalid(what, why));
        if self.epochs == 0 {
            return bad("--epochs", "must be at least 1".into());
        }
        if self.batch == 0 {
            return bad("--batch", "must be at least 1".into());
        }
        if self.max_steps == Some(0) {
            return bad("--steps", "must be at least 1".into());
        }
        if !(self.learning_rate.is_finite() && self.learning_rate > 0.0) {
            return bad(
                "--lr",
                format!("{} is not a positive learning rate", self.learning_rate),
            );
        }
        if !(0.0..=1.0).contains(&self.lr_hold) {
            return bad(
                "--lr-hold",
                format!("{} is not a fraction in [0, 1]", self.lr_hold),
            );
        }
        if self.lowered_start && self.config.loss == crate::config::LossVariant::Paper {
            return bad(
                "--lowered-start",
                "lowers the official schedule's weights; --loss paper holds the paper's fixed weights".into(),
            );
        }
        if let Some(c) = self.augmentation.legacy_colour {
            return bad(
                "augmentation",
                format!(
                    "colour {c} is the older colour jitter's strength, which `train` no longer applies: set `colour_jitter` (the loader's jitter) instead"
                ),
            );
        }
        if !(0.0..=1.0).contains(&self.augmentation.colour) {
            return bad(
                "--colour-jitter",
                format!("{} is not in [0, 1]", self.augmentation.colour),
            );
        }
        Ok(())
    }
}

/// Optimiser steps of a run: `epochs` passes over `examples` in batches of `batch`
/// (the last batch of an epoch may be short).
pub fn total_steps(examples: usize, epochs: usize, batch: usize) -> usize {
    epochs * examples.div_ceil(batch.max(1))
}

/// Optimiser steps of one pass over `source`: its shards' examples in batches of
/// `batch`, a shard's last batch possibly short (for one shard, [`total_steps`] of one
/// epoch).
pub fn steps_per_epoch<S: ExampleShards + ?Sized>(source: &S, batch: usize) -> usize {
    (0..source.shards())
        .map(|k| source.shard_len(k).div_ceil(batch.max(1)))
        .sum()
}

/// Fisher-Yates with our own generator: the same order for a seed everywhere.
fn shuffle(order: &mut [usize], rng: &mut Rng) {
    for i in (1..order.len()).rev() {
        order.swap(i, rng.below(i as u64 + 1) as usize);
    }
}

/// Trains a fresh network on `examples` (in memory, or [`crate::ShardedExamples`] loaded one
/// shard at a time: each epoch visits the shards in a shuffled order and each shard's
/// examples in a shuffled order); writes the checkpoint folder. `on_step` sees every
/// step's losses (for progress).
pub fn train<S: ExampleShards + ?Sized>(
    examples: &S,
    topology: &FaceTopology,
    options: &TrainOptions,
    on_step: &dyn Fn(&StepLoss),
) -> Result<(Checkpoint, Vec<StepLoss>)> {
    let cfg = &options.config;
    options.validate()?;
    // One run per model folder; a killed run's temporaries go.
    let _lock = arkit_core::atomic_file::FolderLock::acquire(&options.output, "train", "train")?;
    arkit_core::atomic_file::remove_stale_temporaries(&options.output, false)?;
    if examples.total() == 0 {
        return Err(Error::invalid("train", "no training examples"));
    }
    let device = Device::Cpu;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &device);
    let net = Network::new(cfg, &vertex_uv(topology, &device)?, vb)
        .map_err(|e| candle_err("network", e))?;
    reseed(&varmap, options.seed, cfg.init_std).map_err(|e| candle_err("initial weights", e))?;
    let total_steps = step_budget(
        options.epochs * steps_per_epoch(examples, options.batch),
        options,
    )?;
    let mut checkpoint = fresh_checkpoint(topology, options, examples.total(), examples.shards());
    let mut log = Vec::new();
    let mut start_epoch = 0;
    let mut opt = Adam::new(named_trainable_vars(&varmap), options.learning_rate)
        .map_err(|e| candle_err("optimizer", e))?;
    let mut loss = PerspNetLoss::for_config(cfg);
    if options.lowered_start {
        // The weights the official schedule reaches once L_corr < 0.1.
        loss.weights.update_schedule(0.05);
    }
    // Any file of a checkpoint is resumed from, or refused naming what is wrong (a
    // folder missing its `perspnet.json` but holding weights was trained over before);
    // a folder without one starts the run.
    if options.resume && holds_checkpoint(&options.output) {
        let resumed = resume_from(&options.output, &checkpoint, &varmap, &mut opt)?;
        start_epoch = resumed.checkpoint.epochs_done;
        log = resumed.log;
        if let Some(w) = resumed.checkpoint.loss_weights {
            loss.weights = w;
        }
        checkpoint.epochs_done = start_epoch;
        checkpoint.steps = log.len();
        checkpoint.first_loss = log.first().map_or(f32::NAN, |s| s.total);
        checkpoint.last_loss = log.last().map_or(f32::NAN, |s| s.total);
    }
    let mut rng = Rng::new(options.seed);
    let mut shard_order: Vec<usize> = (0..examples.shards()).collect();
    let mut orders: Vec<Vec<usize>> = (0..examples.shards())
        .map(|k| (0..examples.shard_len(k)).collect())
        .collect();
    for epoch in 0..options.epochs {
        // The shards' order, then each shard's samples, from our generator (replayed for
        // the epochs a resumed run skips). With one shard this draws exactly what a
        // single shuffle of all examples does.
        shuffle(&mut shard_order, &mut rng);
        for &k in &shard_order {
            shuffle(&mut orders[k], &mut rng);
        }
        if epoch < start_epoch {
            continue;
        }
        if log.len() >= total_steps {
            // A step budget spent before the last epoch: nothing more to write.
            break;
        }
        // The next shard is read on its own thread while this one trains.
        std::thread::scope(|scope| -> Result<()> {
            let mut next = None;
            for (pos, &k) in shard_order.iter().enumerate() {
                if log.len() >= total_steps {
                    break;
                }
                let shard = match next.take() {
                    Some(h) => std::thread::ScopedJoinHandle::join(h).expect("shard reader")?,
                    None => examples.load(k)?,
                };
                // Read ahead only when the budget reaches past this shard (no read of
                // a shard the run will not train on).
                let this_shard_steps = orders[k].len().div_ceil(options.batch.max(1));
                if let Some(&after) = shard_order.get(pos + 1)
                    && log.len() + this_shard_steps < total_steps
                {
                    next = Some(scope.spawn(move || examples.load(after)));
                }
                for chunk in orders[k].chunks(options.batch.max(1)) {
                    if log.len() >= total_steps {
                        break;
                    }
                    let refs: Vec<&Example> = chunk.iter().map(|&i| &shard[i]).collect();
                    // Each step's augmentation has its own stream: the same views for a seed
                    // whatever else changes.
                    let mut aug_rng = Rng::for_stream(options.seed, 1 << 40 | log.len() as u64);
                    let items: Vec<LoaderItem> = refs
                        .iter()
                        .map(|e| e.item(cfg.points, &options.augmentation, &mut aug_rng))
                        .collect();
                    let b = batch(&refs, &items, cfg, &device)?;
                    if let Network::PerspNet(net) = &net {
                        net.seed_dropout(
                            Rng::for_stream(options.seed, 2 << 40 | log.len() as u64).next_u64(),
                        );
                    }
                    opt.learning_rate = learning_rate_at(
                        log.len(),
                        total_steps,
                        options.learning_rate,
                        options.lr_hold,
                    );
                    let step = training_step(&net, &mut opt, &mut loss, &b, log.len(), epoch)
                        .map_err(|e| candle_err("training step", e))?;
                    if !step.total.is_finite() {
                        return Err(Error::invalid(
                            "train",
                            format!(
                                "the loss is {} at step {}: lower --lr",
                                step.total, step.step
                            ),
                        ));
                    }
                    on_step(&step);
                    log.push(step);
                }
            }
            Ok(())
        })?;
        checkpoint.epochs_done = epoch + 1;
        checkpoint.steps = log.len();
        checkpoint.first_loss = log.first().map_or(f32::NAN, |s| s.total);
        checkpoint.last_loss = log.last().map_or(f32::NAN, |s| s.total);
        checkpoint.loss_weights = Some(loss.weights);
        write_checkpoint(&options.output, &checkpoint, &varmap, &opt, &log)?;
    }
    Ok((checkpoint, log))
}

/// The run's optimiser steps: `options.max_steps`, which must fit in the `epoch_steps`
/// of `options.epochs` passes, or all of those.
fn step_budget(epoch_steps: usize, options: &TrainOptions) -> Result<usize> {
    match options.max_steps {
        Some(n) if n > epoch_steps => Err(Error::invalid(
            "train",
            format!("{n} steps need more than {} epochs", options.epochs),
        )),
        Some(n) => Ok(n),
        None => Ok(epoch_steps),
    }
}

/// The checkpoint record of a run starting now (no epoch done, no loss yet) on `examples`
/// examples in `example_shards` shards.
fn fresh_checkpoint(
    topology: &FaceTopology,
    options: &TrainOptions,
    examples: usize,
    example_shards: usize,
) -> Checkpoint {
    Checkpoint {
        config: options.config.clone(),
        topology: topology.source.clone(),
        epochs: options.epochs,
        batch: options.batch,
        learning_rate: options.learning_rate,
        lr_hold: options.lr_hold,
        augmentation: options.augmentation,
        lowered_start: options.lowered_start,
        max_steps: options.max_steps,
        seed: options.seed,
        loss_weights: None,
        epochs_done: 0,
        examples,
        example_shards,
        steps: 0,
        first_loss: f32::NAN,
        last_loss: f32::NAN,
        imported_from: None,
    }
}

/// One optimiser step (number `step`, in `epoch`) on batch `b`: the forward pass, the
/// loss (PerspNet's terms, or the direct regressor's rotation and translation), the
/// backward pass and Adam's update; returns the step's losses.
fn training_step(
    net: &Network,
    opt: &mut Adam,
    loss: &mut PerspNetLoss,
    b: &super::data::Batch,
    step: usize,
    epoch: usize,
) -> candle_core::Result<StepLoss> {
    let net = match net {
        Network::PerspNet(net) => net,
        Network::Direct(direct) => {
            let out = direct.forward(&b.image, true)?;
            let target = b.direct.as_ref().expect("direct targets");
            let (total, rot, trans) = crate::direct::direct_loss(&out, target)?;
            opt.backward_step(&total)?;
            let v = |t: &Tensor| t.to_scalar::<f32>();
            return Ok(StepLoss {
                step,
                epoch,
                total: v(&total)?,
                corr: v(&rot)?,
                shape: v(&trans)?,
                kl: 0.0,
                entropy: 0.0,
                seg: 0.0,
            });
        }
    };
    let out = net.forward(&b.image, &b.choose, true)?;
    let terms = loss.compute(
        &out,
        &LossTargets {
            nocs: &b.nocs,
            model: &b.model,
            seg_mask: &b.mask,
            corr: &b.corr,
            uv_map: None,
        },
    )?;
    opt.backward_step(&terms.total)?;
    let v = terms.values()?;
    Ok(StepLoss {
        step,
        epoch,
        total: v[0],
        corr: v[1],
        shape: v[2],
        kl: v[3],
        entropy: v[4],
        seg: v[5],
    })
}

/// What a resumed run picks up besides the weights.
struct Resumed {
    checkpoint: Checkpoint,
    log: Vec<StepLoss>,
}

/// Loads the checkpoint in `dir` into `varmap` and `opt` for a resumed run with the
/// settings of `wanted`; returns it with its loss log.
fn resume_from(
    dir: &Path,
    wanted: &Checkpoint,
    varmap: &VarMap,
    opt: &mut Adam,
) -> Result<Resumed> {
    verify_checkpoint(dir)?;
    let p = dir.join("perspnet.json");
    let text = std::fs::read_to_string(&p).map_err(|e| Error::io(&p, e))?;
    let old: Checkpoint =
        serde_json::from_str(&text).map_err(|e| Error::format(&p, e.to_string()))?;
    let same = |a: &Checkpoint| {
        let mut a = a.clone();
        a.epochs_done = 0;
        a.steps = 0;
        a.first_loss = f32::NAN;
        a.last_loss = f32::NAN;
        a.loss_weights = None;
        serde_json::to_value(&a).ok()
    };
    if same(&old) != same(wanted) {
        return Err(Error::format(
            &p,
            "made with other settings (config, data, epochs, batch, rate, augmentation or seed): resume only with the same options, or choose another --output",
        ));
    }
    let w = dir.join("model.safetensors");
    load_weights(varmap, &mut open_weights(&w)?, &w)?;
    let adam = dir.join(ADAM_FILE);
    if adam.exists() {
        opt.load(&adam)
            .map_err(|e| Error::format(&adam, e.to_string()))?;
        if opt.steps() != old.steps {
            return Err(Error::format(
                &adam,
                format!(
                    "{} optimiser steps but the checkpoint ran {}",
                    opt.steps(),
                    old.steps
                ),
            ));
        }
    }
    let csv = dir.join("loss.csv");
    let text = std::fs::read_to_string(&csv).map_err(|e| Error::io(&csv, e))?;
    let mut log = Vec::new();
    for (n, line) in text.lines().enumerate().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        let num = |i: usize| -> Result<f32> {
            f.get(i)
                .and_then(|v| v.parse().ok())
                .ok_or_else(|| Error::format(&csv, format!("line {}: bad field {i}", n + 1)))
        };
        log.push(StepLoss {
            step: num(0)? as usize,
            epoch: num(1)? as usize,
            total: num(2)?,
            corr: num(3)?,
            shape: num(4)?,
            kl: num(5)?,
            entropy: num(6)?,
            seg: num(7)?,
        });
    }
    if log.len() != old.steps {
        return Err(Error::format(
            &csv,
            format!(
                "{} rows but the checkpoint ran {} steps",
                log.len(),
                old.steps
            ),
        ));
    }
    Ok(Resumed {
        checkpoint: old,
        log,
    })
}

/// Redraws every randomly initialised variable from our seeded generator (candle's
/// CPU generator cannot be seeded), so the initial weights, and the whole run, follow
/// from the seed: N(0, `init_std`) for convolution and linear weights, N(1, `init_std`)
/// for batch-norm weights (the official `init_weights`). Which of the two a variable
/// is comes from the mean candle's draw gave it (rounded to 0 or 1); the draw's own
/// spread is not used, as it varies from run to run. Constant variables (biases,
/// batch-norm statistics) are left as they are.
pub fn reseed(varmap: &VarMap, seed: u64, init_std: f64) -> candle_core::Result<()> {
    let data = varmap.data().lock().expect("varmap lock");
    let mut named: Vec<(&String, &candle_core::Var)> = data
        .iter()
        .filter(|(k, _)| !k.contains("running_"))
        .collect();
    named.sort_by(|a, b| a.0.cmp(b.0));
    for (i, (_, var)) in named.into_iter().enumerate() {
        let values = var.as_tensor().flatten_all()?.to_vec1::<f32>()?;
        let n = values.len() as f64;
        let mean = values.iter().map(|&v| v as f64).sum::<f64>() / n;
        let var_ = values
            .iter()
            .map(|&v| (v as f64 - mean).powi(2))
            .sum::<f64>()
            / n;
        if var_ <= 0.0 {
            continue;
        }
        let mut rng = Rng::for_stream(seed, i as u64);
        let (mean, sd) = (mean.round(), init_std);
        let fresh: Vec<f32> = (0..values.len())
            .map(|_| (mean + sd * rng.normal()) as f32)
            .collect();
        var.set(&Tensor::from_vec(fresh, var.shape(), var.device())?)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn learning_rate_holds_then_falls_to_zero() {
        // 10 steps, half held: 1 for steps 0-4, then 5/5, 4/5, ... 1/5.
        let lr: Vec<f64> = (0..10).map(|s| learning_rate_at(s, 10, 1.0, 0.5)).collect();
        assert_eq!(&lr[..6], &[1.0; 6]);
        for (s, v) in lr.iter().enumerate().skip(5) {
            assert!((v - (10 - s) as f64 / 5.0).abs() < 1e-12, "{s}: {v}");
        }
        assert_eq!(learning_rate_at(9, 10, 2.0, 1.0), 2.0);
        assert!((learning_rate_at(9, 10, 2.0, 0.0) - 0.2).abs() < 1e-12);
    }
}
