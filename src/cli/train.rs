//! `arkit-tool train`.

use arkit_core::Error;
use arkit_perspnet::{Architecture, LossVariant};
use arkit_perspnet::{ExampleShards, ShardedExamples, TrainOptions};

use arkit_core::Result;
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

/// Train the reference PerspNet (or the paper's direct baseline) on a rendered dataset, CPU.
///
/// Reads the crops, masks, sampled pixels and barycentric correspondences that `render`
/// stored (render at the network's input size and with at least its number of points:
/// `--size 64 --points 256` for `tiny`, the defaults for `paper`), trains with the
/// official losses (smooth-L1 correspondence, shape L1 against 9x the mesh, KL to the
/// barycentric rows with the entropy term, segmentation cross-entropy, and the official
/// schedule that lowers the weights as the correspondence loss falls; `--loss paper`:
/// the paper's loss, plain L1 correspondences and the fixed weights 0.5 / 0.01 / 1 /
/// 0.01 on shape / assignment / correspondence / segmentation) and Adam, and
/// writes DIR/perspnet.json, DIR/model.safetensors, DIR/adam.safetensors and
/// DIR/loss.csv after every epoch, then DIR/checkpoint.json, the size and SHA-256 of
/// each (--resume continues from them exactly). The learning
/// rate is held for --lr-hold of the steps, then falls linearly to zero; each step sees
/// colour- and crop-jittered crops and fresh face pixels, all drawn from --seed. All
/// training samples are read into memory first (the size is printed); --stream holds
/// one shard at a time instead.
///
/// `tiny` trains in minutes on two CPU cores; `paper` has the official shapes (16.97 M
/// parameters) and is for GPUs or patience.
///
/// --architecture direct trains the paper's "Direct 6DoF Regress" baseline instead: the
/// same ResNet-18 encoder (--config's widths and input size) and a head regressing the
/// rotation (6D: two columns of R, made orthonormal) and the translation (where the
/// face's origin is in the crop box, and its depth as the box's width in units of
/// 0.2 m), with an L1 loss on R's entries and on those three numbers. `predict --model`
/// and `eval` score it like any model (no PnP; no mesh or mask, so 3DRecon and the mask
/// scores are '-').
///
/// Example: arkit-tool render --dataset data/pq --size 64 --points 256 --output data/t64
///          arkit-tool train --dataset data/pq --targets data/t64 --config tiny --loss paper --epochs 5 --output model/
#[derive(Args, Debug)]
pub struct TrainArgs {
    /// A folder written by `convert`. Or a dataset published with `arkit-tool push`: s3://BUCKET/PREFIX (its tables
    /// are mirrored in the cache folder, $ARKIT_CACHE_DIR or ~/.cache/arkit-tool).
    #[arg(long)]
    dataset: PathBuf,
    /// Where `render` wrote targets/ (default: the dataset).
    #[arg(long)]
    targets: Option<PathBuf>,
    /// `tiny`, `paper`, or a JSON file of the network's settings.
    #[arg(long, default_value = "tiny")]
    config: String,
    /// The loss: `official` (models/loss.py: smooth-L1 correspondences, weights lowered
    /// as the correspondence loss falls) or `paper` (the paper's text: plain L1, fixed
    /// weights 0.5 L_S + 0.01 L_M + 1.0 L_corr + 0.01 L_seg). Overrides the config
    /// file's `loss`.
    #[arg(long, value_name = "official|paper")]
    loss: Option<LossVariant>,
    /// `perspnet` (correspondences, then PnP) or `direct` (the paper's "Direct 6DoF
    /// Regress" baseline: the encoder and a head regressing the pose; --loss, the
    /// ablation switches and --lowered-start do not apply to it). Overrides the config
    /// file's `architecture`.
    #[arg(long, value_name = "perspnet|direct")]
    architecture: Option<Architecture>,
    /// Train on this split (`all` for every sample).
    #[arg(long, default_value = "train")]
    split: String,
    /// Passes over the training samples, 1..=100000.
    #[arg(long, allow_negative_numbers = true, default_value_t = 5, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=100_000))]
    epochs: usize,
    /// A step budget instead of --epochs: stop after N steps (the learning-rate
    /// schedule is scaled to N; the last pass over the samples may end part way).
    /// N is 1..=100000000.
    #[arg(long, allow_negative_numbers = true, value_name = "N", conflicts_with = "epochs",
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=100_000_000))]
    steps: Option<usize>,
    /// Samples per step, 1..=1024.
    #[arg(long, allow_negative_numbers = true, default_value_t = 4, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=1024))]
    batch: usize,
    /// AdamW learning rate, in (0, 1].
    #[arg(long, allow_negative_numbers = true, default_value_t = 1e-3, value_parser = super::values::learning_rate)]
    lr: f64,
    /// Share of the steps at --lr; the rate then falls linearly to zero at the last
    /// step (the paper's schedule). In [0, 1]; 1 keeps it constant.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.5, value_parser = super::values::unit_interval)]
    lr_hold: f64,
    /// Colour jitter strength c in [0, 1]: torchvision's ColorJitter(c, c, 2c/3, c/30)
    /// on the crop's bytes (brightness, contrast and saturation factors in [1-c, 1+c],
    /// [1-c, 1+c], [1-2c/3, 1+2c/3], a hue shift of up to c/30 of a turn, in a random
    /// order), the Python loader's jitter; 0.3 is the official loader's, 0 turns it off.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.3, value_parser = super::values::unit_interval)]
    colour_jitter: f64,
    /// Crop jitter: shift each crop by up to this many pixels per axis, 0..=64.
    #[arg(long, allow_negative_numbers = true, default_value_t = 2, value_parser = clap::value_parser!(u32).range(0..=64))]
    shift_px: u32,
    /// Train on the M points `render` stored instead of fresh face pixels each step.
    #[arg(long)]
    stored_points: bool,
    /// Hold one shard's samples in memory at a time instead of all of them (for
    /// datasets larger than memory: each epoch then visits the shards in a shuffled
    /// order and each shard's samples in a shuffled order, re-reading a shard's images
    /// and targets when it comes round).
    #[arg(long)]
    stream: bool,
    /// The paper's ablation "w/o PE": the points' local features are the image
    /// features alone, without the 2D position encoding.
    #[arg(long)]
    no_position_encoding: bool,
    /// The paper's ablation "w/o L_M": no assignment loss (KL and entropy); the
    /// assignment matrix is learned through the correspondence loss only.
    #[arg(long)]
    no_assignment_loss: bool,
    /// Start the loss at the weights the official schedule lowers to once the
    /// correspondence loss falls below 0.1 (KL and segmentation 0.01), instead of
    /// waiting for one batch to get there (the official, sticky trigger). Official loss
    /// only.
    #[arg(long)]
    lowered_start: bool,
    /// Continue an interrupted run from the checkpoint in --output (one is written after
    /// every epoch), given the same options: weights, Adam's moments and the loss
    /// weights are restored, so the resumed run is step for step the uninterrupted one.
    /// Each file must match the record DIR/checkpoint.json: a checkpoint left torn by a
    /// run stopped while writing it, or missing one of its files, is refused (naming the
    /// file) and left as it is. A folder with no checkpoint file starts the run.
    #[arg(long)]
    resume: bool,
    /// Seed of the initial weights and the sample order.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// The checkpoint folder to write.
    #[arg(long)]
    output: PathBuf,
    /// The release's resource folder (real topology: its vertex UVs); the built-in face without it.
    #[arg(long)]
    resources: Option<PathBuf>,
    /// Exit with status 1, before training, if any sample's image could not be read
    /// (without it such samples are reported and left out).
    #[arg(long)]
    strict: bool,
    /// Print the checkpoint summary as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(mut a: TrainArgs) -> Result<ExitCode> {
    let (dir, _remote) = super::remote::dataset_folder(&a.dataset)?;
    a.dataset = dir;
    let _remote_targets = match a.targets.take() {
        Some(t) => {
            let (dir, remote) = super::remote::dataset_folder(&t)?;
            a.targets = Some(dir);
            remote
        }
        None => None,
    };
    let mut config = super::setup::config_named(&a.config)?;
    if let Some(loss) = a.loss {
        config.loss = loss;
    }
    if a.no_position_encoding {
        config.position_encoding = false;
    }
    if a.no_assignment_loss {
        config.assignment_loss = false;
    }
    if let Some(arch) = a.architecture {
        config.architecture = arch;
    }
    if config.architecture == Architecture::Direct {
        let perspnet_only = [
            ("--loss", a.loss.is_some()),
            ("--no-position-encoding", a.no_position_encoding),
            ("--no-assignment-loss", a.no_assignment_loss),
            ("--lowered-start", a.lowered_start),
        ];
        if let Some((flag, _)) = perspnet_only.iter().find(|(_, given)| *given) {
            return Err(Error::invalid(
                *flag,
                "is a PerspNet option; the direct baseline has one loss (L1 on the rotation matrix and on the crop-frame translation)",
            ));
        }
    }
    if a.lowered_start && config.loss == LossVariant::Paper {
        return Err(Error::invalid(
            "--lowered-start",
            "lowers the official schedule's weights; --loss paper holds the paper's fixed weights",
        ));
    }
    let topology = super::setup::load_topology(a.resources.as_deref())?;
    let manifest = arkit_data::store::Dataset::read_manifest(&a.dataset)?;
    arkit_data::store::check_topology(&manifest, &topology)?;
    let targets = a.targets.clone().unwrap_or_else(|| a.dataset.clone());
    let split = (a.split != "all").then_some(a.split.as_str());
    let source = ShardedExamples::open(&a.dataset, &targets, &config, split)?;
    let unreadable = source.unreadable().to_vec();
    super::console::report_unreadable(&unreadable, "train");
    if a.strict && !unreadable.is_empty() {
        return Ok(ExitCode::FAILURE);
    }
    let source: Box<dyn ExampleShards> = if a.stream {
        if !a.json {
            eprintln!(
                "streaming {} training samples from {} shards, one shard in memory at a time",
                source.total(),
                source.shards()
            );
        }
        Box::new(source)
    } else {
        let mut examples = Vec::with_capacity(source.total());
        for k in 0..source.shards() {
            examples.extend(source.load(k)?.into_owned());
        }
        let memory: usize = examples.iter().map(|e| e.memory_bytes()).sum();
        if !a.json {
            eprintln!(
                "read {} training samples: {:.1} MiB in memory ({:.1} KiB each; --stream holds one shard at a time)",
                examples.len(),
                memory as f64 / (1 << 20) as f64,
                memory as f64 / 1024.0 / examples.len().max(1) as f64
            );
        }
        Box::new(examples)
    };
    let per_epoch = arkit_perspnet::steps_per_epoch(source.as_ref(), a.batch).max(1);
    let (epochs, steps) = match a.steps {
        Some(n) => (n.div_ceil(per_epoch), n),
        None => (a.epochs, a.epochs * per_epoch),
    };
    let bar = super::console::progress_bar(steps as u64, "train", "steps");
    let options = TrainOptions {
        config,
        epochs,
        max_steps: a.steps,
        batch: a.batch,
        learning_rate: a.lr,
        lr_hold: a.lr_hold,
        augmentation: arkit_perspnet::Augmentation {
            colour: a.colour_jitter as f32,
            shift_px: a.shift_px,
            resample_points: !a.stored_points,
            legacy_colour: None,
        },
        seed: a.seed,
        output: a.output.clone(),
        resume: a.resume,
        lowered_start: a.lowered_start,
    };
    let on_step = |s: &arkit_perspnet::StepLoss| {
        bar.set_message(format!("loss {:.4}", s.total));
        bar.inc(1);
    };
    let (checkpoint, _) = arkit_perspnet::train(source.as_ref(), &topology, &options, &on_step)?;
    bar.finish_and_clear();
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&checkpoint).expect("json")
        );
    } else {
        println!(
            "trained on {} samples, {} steps: loss {:.4} -> {:.4}; wrote {}",
            checkpoint.examples,
            checkpoint.steps,
            checkpoint.first_loss,
            checkpoint.last_loss,
            a.output.display()
        );
    }
    Ok(ExitCode::SUCCESS)
}
