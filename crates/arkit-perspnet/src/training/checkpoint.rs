//! A checkpoint folder holds `perspnet.json` (the network config and how it was
//! trained), `model.safetensors` (the weights, batch-norm statistics included),
//! `adam.safetensors` (the optimiser's state), `loss.csv` (one row per step) and,
//! written last, `checkpoint.json` (the size and SHA-256 of each). Files are written
//! atomically; `train --resume` checks them against the record first. A model folder
//! is loaded for prediction by [`load`]; the shipped model is compiled in.

use super::data::Augmentation;
use crate::adam::Adam;
use crate::candle_error::candle_err;
use crate::config::{Architecture, PerspNetConfig};
use crate::loss::LossWeights;
use crate::network::{Network, vertex_uv};
use crate::weights::load_weights;
use crate::weights::open_weights;
use crate::weights::safetensors_file::SafetensorsFile;
use arkit_core::{Error, Result};
use arkit_data::mesh::FaceTopology;
use candle_core::{DType, Device};
use candle_nn::{VarBuilder, VarMap};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// One step's losses (weighted, as summed into the total).
#[derive(Clone, Copy, Debug, Serialize)]
pub struct StepLoss {
    /// Step number (0-based).
    pub step: usize,
    /// Epoch.
    pub epoch: usize,
    /// Total.
    pub total: f32,
    /// Correspondence smooth L1.
    pub corr: f32,
    /// Shape L1.
    pub shape: f32,
    /// KL to the barycentric targets.
    pub kl: f32,
    /// Entropy.
    pub entropy: f32,
    /// Segmentation.
    pub seg: f32,
}

/// How a checkpoint was made (`perspnet.json`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Checkpoint {
    /// The network.
    pub config: PerspNetConfig,
    /// Topology source (the vertex UVs come from it).
    pub topology: String,
    /// Epochs run.
    pub epochs: usize,
    /// Batch size.
    pub batch: usize,
    /// Learning rate.
    pub learning_rate: f64,
    /// Share of the steps at the full learning rate before the linear decay (older
    /// checkpoints: 1, a constant rate).
    #[serde(default = "constant_rate")]
    pub lr_hold: f64,
    /// Training-time augmentation (older checkpoints: none).
    #[serde(default = "no_augmentation")]
    pub augmentation: Augmentation,
    /// Whether the loss started at the lowered weights.
    #[serde(default)]
    pub lowered_start: bool,
    /// The step budget, when the run had one (`train --steps`).
    #[serde(default)]
    pub max_steps: Option<usize>,
    /// Seed.
    pub seed: u64,
    /// The loss weights when this checkpoint was written (the official schedule lowers
    /// them as `L_corr` falls; a resumed run goes on from these). Older checkpoints:
    /// none, the run's starting weights.
    #[serde(default)]
    pub loss_weights: Option<LossWeights>,
    /// Epochs finished when this checkpoint was written (`epochs` once training is
    /// done; a checkpoint is written after every epoch).
    #[serde(default)]
    pub epochs_done: usize,
    /// Training examples.
    pub examples: usize,
    /// Shards the examples were taken from, one at a time (1: all in memory; `train
    /// --stream`: the dataset's shards with examples of the split). The sample order
    /// depends on it, so a resumed run must match.
    #[serde(default = "one_shard")]
    pub example_shards: usize,
    /// Steps run.
    pub steps: usize,
    /// Total loss of the first and last step (NaN, written `null`, without steps).
    #[serde(deserialize_with = "nan_if_null")]
    pub first_loss: f32,
    /// Total loss of the last step.
    #[serde(deserialize_with = "nan_if_null")]
    pub last_loss: f32,
    /// The weights file this model was imported from (`import-weights`), if it was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub imported_from: Option<String>,
}

/// A loss written as `null` (JSON has no NaN) reads back as NaN.
fn nan_if_null<'de, D: serde::Deserializer<'de>>(d: D) -> std::result::Result<f32, D::Error> {
    Ok(Option::<f32>::deserialize(d)?.unwrap_or(f32::NAN))
}

fn one_shard() -> usize {
    1
}

fn constant_rate() -> f64 {
    1.0
}

fn no_augmentation() -> Augmentation {
    Augmentation::NONE
}

/// Writes `path` through `save` under a temporary name in the same folder, then
/// publishes it (flushed to the disk, then renamed: `atomic_file::publish`).
///
/// The safetensors library that `save` calls writes a temporary of its own beside the
/// file it is given (`.tmpXXXXXX`) and renames it: so it is given a file inside a
/// temporary folder of ours (`.NAME.tmp-TOKEN/`, owned while this process lives), and a run killed at any
/// point leaves only what `atomic_file::remove_stale_temporaries` removes.
pub(crate) fn save_renamed(
    path: &Path,
    save: &dyn Fn(&Path) -> candle_core::Result<()>,
) -> Result<()> {
    let scratch = arkit_core::atomic_file::TemporaryDir::create(path)?;
    let tmp = scratch.path().join(path.file_name().unwrap_or_default());
    let published = match save(&tmp) {
        Err(e) => Err(Error::format(path, e.to_string())),
        Ok(()) => arkit_core::atomic_file::publish_written(&tmp, path),
    };
    // The folder (with what the library left in it) and its owner file go.
    drop(scratch);
    published
}

/// The optimiser's state in a checkpoint folder ([`Adam::save`]).
pub const ADAM_FILE: &str = "adam.safetensors";

pub(crate) fn write_checkpoint(
    dir: &Path,
    c: &Checkpoint,
    varmap: &VarMap,
    opt: &Adam,
    log: &[StepLoss],
) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    // Weights and optimiser state first, each under a temporary name then renamed;
    // perspnet.json last, so a folder whose json says N steps has both files of step N.
    save_renamed(&dir.join("model.safetensors"), &|p| varmap.save(p))?;
    save_renamed(&dir.join(ADAM_FILE), &|p| opt.save(p))?;
    // The direct model's two terms take the first two loss columns.
    let mut csv = String::from(match c.config.architecture {
        Architecture::PerspNet => "step,epoch,total,corr,shape,kl,entropy,seg\n",
        Architecture::Direct => "step,epoch,total,rotation,translation,unused,unused,unused\n",
    });
    for s in log {
        csv += &format!(
            "{},{},{},{},{},{},{},{}\n",
            s.step, s.epoch, s.total, s.corr, s.shape, s.kl, s.entropy, s.seg
        );
    }
    arkit_core::atomic_file::write_bytes(&dir.join("loss.csv"), csv.as_bytes())?;
    let json = serde_json::to_string_pretty(c).expect("checkpoint json");
    arkit_core::atomic_file::write_bytes(&dir.join("perspnet.json"), json.as_bytes())?;
    // Last, the record of what was written: a folder whose files do not all match it
    // (a run stopped between two renames) is refused by --resume.
    write_checkpoint_record(dir)
}

/// The record a checkpoint folder's files are checked against on `train --resume`:
/// written last, after every other file, it holds the size and SHA-256 of each.
pub const CHECKPOINT_RECORD: &str = "checkpoint.json";

/// The files of a checkpoint folder that [`CHECKPOINT_RECORD`] covers.
pub(crate) const CHECKPOINT_FILES: [&str; 4] =
    ["model.safetensors", ADAM_FILE, "loss.csv", "perspnet.json"];

/// One file of a checkpoint, as its record holds it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
struct RecordedFile {
    name: String,
    bytes: u64,
    sha256: String,
}

#[derive(Debug, Serialize, Deserialize)]
struct CheckpointRecord {
    files: Vec<RecordedFile>,
}

/// The size and SHA-256 (lowercase hex) of `path`, read in pieces.
fn file_digest(path: &Path) -> Result<(u64, String)> {
    use sha2::Digest;
    use std::io::Read;
    let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut h = sha2::Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    let mut n = 0u64;
    loop {
        let k = f.read(&mut buf).map_err(|e| Error::io(path, e))?;
        if k == 0 {
            break;
        }
        h.update(&buf[..k]);
        n += k as u64;
    }
    let hex = h.finalize().iter().map(|b| format!("{b:02x}")).collect();
    Ok((n, hex))
}

fn write_checkpoint_record(dir: &Path) -> Result<()> {
    write_record(dir, &CHECKPOINT_FILES)
}

/// The files a model folder needs for prediction and export: the weights and the
/// config they were made with.
pub(crate) const MODEL_FILES: [&str; 2] = ["model.safetensors", "perspnet.json"];

/// Writes `dir`'s record ([`CHECKPOINT_RECORD`]) of the files `names`, after them: the
/// writers of model folders (`train`, `import-weights`, `half-model`) end with it.
pub(crate) fn write_record(dir: &Path, names: &[&str]) -> Result<()> {
    let mut files = Vec::new();
    for &name in names {
        let (bytes, sha256) = file_digest(&dir.join(name))?;
        files.push(RecordedFile {
            name: name.to_string(),
            bytes,
            sha256,
        });
    }
    let json = serde_json::to_string_pretty(&CheckpointRecord { files }).expect("record json");
    arkit_core::atomic_file::write_bytes(&dir.join(CHECKPOINT_RECORD), json.as_bytes())
}

/// Whether `dir` holds any file of a checkpoint (its record or one it covers): what
/// `train --resume` must then resume, or refuse, rather than train over.
pub(crate) fn holds_checkpoint(dir: &Path) -> bool {
    std::iter::once(CHECKPOINT_RECORD)
        .chain(CHECKPOINT_FILES)
        .any(|name| dir.join(name).exists())
}

/// Checks that every file of the checkpoint in `dir` is the one its record
/// ([`CHECKPOINT_RECORD`]) describes; the error names the first that differs and how.
/// Nothing in the folder is changed.
pub fn verify_checkpoint(dir: &Path) -> Result<()> {
    let torn = "the checkpoint is torn (a run was stopped while writing it) and is left as it is: train into another --output, or run again without --resume to start over";
    verify_record(dir, &CHECKPOINT_FILES, torn)
}

/// Checks, before a model folder is read for prediction or export, that its weights
/// and `perspnet.json` are the ones its record ([`CHECKPOINT_RECORD`]) describes: a
/// folder a run was stopped in while writing (the weights of one epoch beside the
/// config of the one before) is refused, naming the file that differs. A folder with
/// no record (written before records were kept, or by hand) is read as it is.
pub fn verify_model(dir: &Path) -> Result<()> {
    if !dir.join(CHECKPOINT_RECORD).exists() {
        return Ok(());
    }
    let torn = "the model folder is torn (a run was stopped while writing it): rerun the command that wrote it (`train` without --resume or into another --output, `import-weights`, `half-model`), or use another model folder";
    verify_record(dir, &MODEL_FILES, torn)
}

/// Checks that each of `required` is listed in `dir`'s record and is the file the
/// record describes (size, then SHA-256); `torn` is the way out the error gives.
fn verify_record(dir: &Path, required: &[&str], torn: &str) -> Result<()> {
    let rec = dir.join(CHECKPOINT_RECORD);
    let meta = std::fs::metadata(&rec).map_err(|e| {
        Error::format(
            &rec,
            format!("cannot be read ({e}): without this record of the checkpoint's files, it cannot be told whole; {torn}"),
        )
    })?;
    if meta.len() > 1 << 16 {
        return Err(Error::format(
            &rec,
            format!("{} bytes: not a checkpoint record", meta.len()),
        ));
    }
    let text = std::fs::read_to_string(&rec).map_err(|e| Error::io(&rec, e))?;
    let record: CheckpointRecord = serde_json::from_str(&text)
        .map_err(|e| Error::format(&rec, format!("not a checkpoint record: {e}")))?;
    for &name in required {
        let Some(want) = record.files.iter().find(|f| f.name == name) else {
            return Err(Error::format(&rec, format!("does not list {name}")));
        };
        let p = dir.join(name);
        // The size first: a file of another size is told without reading it.
        let (bytes, sha256) = match std::fs::metadata(&p) {
            Ok(m) if m.len() != want.bytes => (m.len(), String::new()),
            Ok(_) => file_digest(&p)?,
            Err(e) => {
                return Err(Error::format(
                    &p,
                    format!("missing ({e}), but {CHECKPOINT_RECORD} records it; {torn}"),
                ));
            }
        };
        if bytes != want.bytes {
            return Err(Error::format(
                &p,
                format!(
                    "{bytes} bytes, but {CHECKPOINT_RECORD} records {} for it: {torn}",
                    want.bytes
                ),
            ));
        }
        if sha256 != want.sha256 {
            return Err(Error::format(
                &p,
                format!(
                    "its SHA-256 is {sha256}, but {CHECKPOINT_RECORD} records {} (same size, other content): {torn}",
                    want.sha256
                ),
            ));
        }
    }
    Ok(())
}

/// Reads a checkpoint's `perspnet.json` at `path`: parsed, its network config checked
/// ([`PerspNetConfig::validate`]: sizes a network can be built with) before anything is
/// built from it. Errors name the file.
pub(crate) fn read_checkpoint_info(path: &Path) -> Result<Checkpoint> {
    let meta = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    if meta.len() > 1 << 20 {
        return Err(Error::format(
            path,
            format!("{} bytes: not a checkpoint's perspnet.json", meta.len()),
        ));
    }
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let checkpoint: Checkpoint =
        serde_json::from_str(&text).map_err(|e| Error::format(path, e.to_string()))?;
    checkpoint
        .config
        .validate()
        .map_err(|e| Error::format(path, format!("its network config: {e}")))?;
    Ok(checkpoint)
}

/// A trained network loaded from a checkpoint folder.
pub struct TrainedModel {
    /// How it was made.
    pub checkpoint: Checkpoint,
    /// The network.
    pub net: Network,
    /// Its variables.
    pub varmap: VarMap,
}

/// Loads a checkpoint folder written by [`crate::train`].
/// The folder's weights and config are first checked against its record
/// ([`verify_model`]).
pub fn load(dir: &Path, topology: &FaceTopology) -> Result<TrainedModel> {
    verify_model(dir)?;
    let checkpoint = read_checkpoint_info(&dir.join("perspnet.json"))?;
    if checkpoint.topology != topology.source {
        return Err(Error::invalid(
            "--resources",
            format!(
                "the model was trained with the topology '{}', not '{}'",
                checkpoint.topology, topology.source
            ),
        ));
    }
    let w = dir.join("model.safetensors");
    let mut st = open_weights(&w)?;
    model_from_parts(checkpoint, &mut st, &w, topology)
}

/// Where the shipped model's folder is in the repository: a `tiny` PerspNet trained by
/// `train` on synthetic data (docs/train.md, "The shipped model", has the commands and
/// seed that made it), its weights stored as float16 (`half-model`).
pub const SHIPPED_MODEL_DIR: &str = "models/tiny-synthetic";

/// The shipped model's `perspnet.json` and weights, compiled into the binary so that
/// `demo` needs no path to find them.
const SHIPPED_JSON: &str = include_str!("../../../../models/tiny-synthetic/perspnet.json");
const SHIPPED_WEIGHTS: &[u8] =
    include_bytes!("../../../../models/tiny-synthetic/model.safetensors");

/// How the shipped model was made (its `perspnet.json`).
pub fn shipped_checkpoint() -> Result<Checkpoint> {
    let p = Path::new(SHIPPED_MODEL_DIR).join("perspnet.json");
    serde_json::from_str(SHIPPED_JSON).map_err(|e| Error::format(&p, e.to_string()))
}

/// The shipped model ([`SHIPPED_MODEL_DIR`]), from the copy compiled into the binary;
/// it was trained on the built-in face's topology, and another `topology` is refused
/// as [`load`] refuses it.
pub fn shipped_model(topology: &FaceTopology) -> Result<TrainedModel> {
    let dir = Path::new(SHIPPED_MODEL_DIR);
    let checkpoint = shipped_checkpoint()?;
    if checkpoint.topology != topology.source {
        return Err(Error::invalid(
            "--resources",
            format!(
                "the shipped model was trained with the topology '{}', not '{}'",
                checkpoint.topology, topology.source
            ),
        ));
    }
    let w = dir.join("model.safetensors");
    let mut st = crate::weights::safetensors_file::from_bytes(SHIPPED_WEIGHTS)
        .map_err(|e| Error::format(&w, e))?;
    model_from_parts(checkpoint, &mut st, &w, topology)
}

/// The network of `checkpoint` with the weights of the safetensors file `st` (read
/// from `file`, named in errors), float32 or float16 ([`load_weights`]).
fn model_from_parts<R: std::io::Read + std::io::Seek>(
    checkpoint: Checkpoint,
    st: &mut SafetensorsFile<R>,
    file: &Path,
    topology: &FaceTopology,
) -> Result<TrainedModel> {
    let device = Device::Cpu;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &device);
    let net = Network::new(&checkpoint.config, &vertex_uv(topology, &device)?, vb)
        .map_err(|e| candle_err("network", e))?;
    load_weights(&varmap, st, file)?;
    Ok(TrainedModel {
        checkpoint,
        net,
        varmap,
    })
}

#[cfg(test)]
mod tests {
    use super::save_renamed;

    /// What the writing library leaves beside the file it is given (its own temporary,
    /// `.tmpXXXXXX`, as safetensors makes) stays inside the writer's temporary folder,
    /// which goes whether the write succeeds or fails: the folder then holds the file
    /// alone, or nothing.
    #[test]
    fn a_librarys_own_temporaries_stay_in_the_writers_folder() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model.safetensors");
        let save = |fail: bool| {
            move |p: &std::path::Path| -> candle_core::Result<()> {
                let parent = p.parent().unwrap();
                std::fs::write(parent.join(".tmpAbC123"), b"library scratch")?;
                if fail {
                    return Err(candle_core::Error::Msg("disk full".into()));
                }
                std::fs::write(p, b"weights")?;
                Ok(())
            }
        };
        let names = || {
            let mut v: Vec<String> = std::fs::read_dir(dir.path())
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect();
            v.sort();
            v
        };
        let e = save_renamed(&path, &save(true)).unwrap_err().to_string();
        assert!(
            e.contains("model.safetensors") && e.contains("disk full"),
            "{e}"
        );
        assert!(names().is_empty(), "{:?}", names());
        save_renamed(&path, &save(false)).unwrap();
        assert_eq!(names(), ["model.safetensors"]);
        assert_eq!(std::fs::read(&path).unwrap(), b"weights");
    }
}
