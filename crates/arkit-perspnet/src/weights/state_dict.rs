//! PyTorch `state_dict`s of the official network (`models/network.py` `DeformNetUV2`):
//! the names and shapes its strict `load_state_dict` asks for, written from a
//! [`VarMap`] built by [`crate::PerspNet::new`] and read back into one.
//!
//! Our variables carry the official names already. The official `state_dict` differs
//! from them in two ways only: the per-point `Conv1d(c_in, c_out, 1)` weights are
//! `c_out x c_in x 1` (ours `c_out x c_in`), and every batch norm has a
//! `num_batches_tracked` buffer (an `i64` scalar that PyTorch reads only when the
//! momentum is `None`, never in the official model). The `paper` configuration has 206
//! entries: 144 parameters, 31 batch norms' running mean and variance and their 31
//! counters.
//!
//! Reading checks every name and shape before any value is read (so a file that
//! declares a huge tensor under a name we expect with another shape is refused without
//! reading it), and reports every missing, extra and misshapen entry at once.

use std::cell::RefCell;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use super::safetensors_file::{self, SafetensorsFile};
use arkit_core::torch_pickle::{self, TorchDType, TorchZip};

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;

/// The batch-norm step counter PyTorch keeps beside the running statistics.
pub(crate) const NUM_BATCHES_TRACKED: &str = "num_batches_tracked";

/// Prefixes of the per-point `Conv1d` layers (stored as linear weights here).
const POINT_LAYERS: [&str; 4] = [
    "instance_color.",
    "instance_global.",
    "category_global.",
    "assignment.",
];

/// One entry of the official `state_dict`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StateEntry {
    /// The official name.
    pub name: String,
    /// The official shape.
    pub shape: Vec<usize>,
    /// `F32` for parameters and running statistics, `I64` for the counters.
    pub dtype: DType,
}

fn is_point_weight(name: &str, rank: usize) -> bool {
    rank == 2 && name.ends_with(".weight") && POINT_LAYERS.iter().any(|p| name.starts_with(p))
}

/// The official name and shape of one of our variables.
fn official_shape(name: &str, shape: &[usize]) -> Vec<usize> {
    let mut s = shape.to_vec();
    if is_point_weight(name, shape.len()) {
        s.push(1);
    }
    s
}

/// The official `state_dict` entries of the network whose variables are in `varmap`,
/// sorted by name.
pub fn state_dict_entries(varmap: &VarMap) -> Vec<StateEntry> {
    let data = varmap.data().lock().expect("varmap lock");
    let mut out = Vec::with_capacity(data.len() * 5 / 4);
    for (name, var) in data.iter() {
        out.push(StateEntry {
            name: name.clone(),
            shape: official_shape(name, var.dims()),
            dtype: DType::F32,
        });
        if let Some(prefix) = name.strip_suffix("running_mean") {
            out.push(StateEntry {
                name: format!("{prefix}{NUM_BATCHES_TRACKED}"),
                shape: vec![],
                dtype: DType::I64,
            });
        }
    }
    out.sort_by(|a, b| a.name.cmp(&b.name));
    out
}

/// The network's weights as the official `state_dict`: names, shapes and buffers,
/// every batch norm's `num_batches_tracked` set to `num_batches` (the training steps).
pub fn export_state_dict(
    varmap: &VarMap,
    num_batches: i64,
) -> candle_core::Result<Vec<(String, Tensor)>> {
    let data = varmap.data().lock().expect("varmap lock");
    let mut out = Vec::with_capacity(data.len() * 5 / 4);
    for (name, var) in data.iter() {
        let t = var.as_tensor().to_dtype(DType::F32)?;
        let t = t.reshape(official_shape(name, t.dims()))?;
        out.push((name.clone(), t));
        if let Some(prefix) = name.strip_suffix("running_mean") {
            out.push((
                format!("{prefix}{NUM_BATCHES_TRACKED}"),
                Tensor::new(num_batches, &Device::Cpu)?,
            ));
        }
    }
    out.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(out)
}

/// What a `state_dict` has that the network does not expect, and the reverse.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct Mismatch {
    /// Expected names the file does not have.
    pub missing: Vec<String>,
    /// Names in the file the network does not have.
    pub extra: Vec<String>,
    /// `(name, expected shape, the file's shape)`, and entries of the wrong kind
    /// (a float where a counter is expected, or the reverse), reported with their shapes.
    pub misshapen: Vec<(String, Vec<usize>, Vec<usize>)>,
}

impl Mismatch {
    /// Whether everything matched.
    pub fn is_empty(&self) -> bool {
        self.missing.is_empty() && self.extra.is_empty() && self.misshapen.is_empty()
    }
}

impl std::fmt::Display for Mismatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let mut parts = Vec::new();
        if !self.missing.is_empty() {
            parts.push(format!(
                "{} missing: {}",
                self.missing.len(),
                self.missing.join(", ")
            ));
        }
        if !self.extra.is_empty() {
            parts.push(format!(
                "{} extra: {}",
                self.extra.len(),
                self.extra.join(", ")
            ));
        }
        if !self.misshapen.is_empty() {
            let list: Vec<String> = self
                .misshapen
                .iter()
                .map(|(n, want, got)| format!("{n} is {got:?}, expected {want:?}"))
                .collect();
            parts.push(format!(
                "{} misshapen: {}",
                self.misshapen.len(),
                list.join(", ")
            ));
        }
        write!(f, "{}", parts.join("; "))
    }
}

fn is_float(d: DType) -> bool {
    matches!(d, DType::F16 | DType::BF16 | DType::F32 | DType::F64)
}

fn is_integer(d: DType) -> bool {
    matches!(d, DType::I64 | DType::U32 | DType::U8)
}

/// Compares a file's `(name, shape, dtype)` list with the expected entries.
pub(crate) fn match_entries(
    expected: &[StateEntry],
    found: &[(String, Vec<usize>, DType)],
) -> Mismatch {
    let want: BTreeMap<&str, &StateEntry> = expected.iter().map(|e| (e.name.as_str(), e)).collect();
    let have: BTreeMap<&str, (&Vec<usize>, DType)> = found
        .iter()
        .map(|(n, s, d)| (n.as_str(), (s, *d)))
        .collect();
    let mut m = Mismatch::default();
    for (name, e) in &want {
        match have.get(name) {
            None => m.missing.push(name.to_string()),
            Some((shape, dtype)) => {
                let kind_ok = if e.dtype == DType::I64 {
                    is_integer(*dtype)
                } else {
                    is_float(*dtype)
                };
                if **shape != e.shape || !kind_ok {
                    m.misshapen
                        .push((name.to_string(), e.shape.clone(), (*shape).clone()));
                }
            }
        }
    }
    m.extra = have
        .keys()
        .filter(|n| !want.contains_key(*n))
        .map(|n| n.to_string())
        .collect();
    m
}

/// A file of weights read for import: the tensors by their names (a `module.` prefix,
/// which `DataParallel` adds, removed). Opening reads the names, types and shapes only;
/// [`WeightFile::load_into`] matches them with the network before it reads any data,
/// then reads the tensors one at a time.
pub(crate) struct WeightFile {
    names: Vec<(String, Vec<usize>, DType)>,
    rename: HashMap<String, String>,
    source: RefCell<Source>,
}

enum Source {
    Pth(TorchZip<std::fs::File>),
    Safetensors(SafetensorsFile<std::io::BufReader<std::fs::File>>),
}

/// Reading a weights file failed: the file could not be read, or did not match.
#[derive(Debug)]
pub(crate) enum WeightError {
    /// The file is not a PyTorch zip or a safetensors file, or could not be read.
    Read(String),
    /// Names or shapes differ from the network's.
    Mismatch(Mismatch),
}

impl std::fmt::Display for WeightError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            WeightError::Read(m) => write!(f, "{m}"),
            WeightError::Mismatch(m) => write!(f, "the weights do not match the network: {m}"),
        }
    }
}

fn strip_module(name: &str) -> String {
    name.strip_prefix("module.").unwrap_or(name).to_string()
}

/// The candle type of a PyTorch one; `None` for the types no network weight has.
fn candle_dtype(d: TorchDType) -> Option<DType> {
    Some(match d {
        TorchDType::F64 => DType::F64,
        TorchDType::F32 => DType::F32,
        TorchDType::F16 => DType::F16,
        TorchDType::BF16 => DType::BF16,
        TorchDType::I64 => DType::I64,
        TorchDType::U8 => DType::U8,
        _ => return None,
    })
}

impl WeightFile {
    /// Opens `path`: a `torch.save` zip (PyTorch 1.6 and later), read by our bounded
    /// reader of a `state_dict`'s pickle ([`arkit_core::torch_pickle`]: no code from
    /// the file is run, and an entry that is not a tensor is refused by name), or a
    /// safetensors file (as [`export_state_dict`] is written), told apart by their
    /// first bytes. Only the names, types and shapes are read here.
    pub fn open(path: &Path) -> Result<Self, WeightError> {
        let read =
            |e: &dyn std::fmt::Display| WeightError::Read(format!("{}: {e}", path.display()));
        let mut head = [0u8; 4];
        {
            use std::io::Read;
            let mut f = std::fs::File::open(path).map_err(|e| read(&e))?;
            f.read_exact(&mut head).map_err(|e| read(&e))?;
        }
        let mut names = Vec::new();
        let mut rename = HashMap::new();
        let mut add = |name: &str, shape: Vec<usize>, dtype: DType| {
            let ours = strip_module(name);
            names.push((ours.clone(), shape, dtype));
            rename.insert(ours, name.to_string());
        };
        let source = if &head == b"PK\x03\x04" {
            let zip = torch_pickle::open(path).map_err(|e| {
                let e = e.to_string();
                let prefix = format!("{}: ", path.display());
                let e = e.strip_prefix(&prefix).unwrap_or(&e);
                if e.contains("not a PyTorch state_dict") {
                    read(&e)
                } else {
                    read(&format!(
                        "not a PyTorch state_dict (torch.save zip format): {e}"
                    ))
                }
            })?;
            for t in zip.tensors() {
                let dtype = candle_dtype(t.dtype).ok_or_else(|| {
                    read(&format!(
                        "'{}' is {}, a type no weight of the network has",
                        t.name,
                        t.dtype.name()
                    ))
                })?;
                add(&t.name, t.shape.clone(), dtype);
            }
            if zip.tensors().is_empty() {
                return Err(read(&"no tensors: not a state_dict saved with torch.save"));
            }
            Source::Pth(zip)
        } else {
            let st = safetensors_file::open(path).map_err(|e| {
                read(&format!(
                    "neither a PyTorch zip (torch.save) nor a safetensors file: {e}"
                ))
            })?;
            for e in st.entries() {
                add(&e.name, e.shape.clone(), e.dtype);
            }
            Source::Safetensors(st)
        };
        let mut seen = std::collections::HashSet::new();
        for (n, _, _) in &names {
            if !seen.insert(n) {
                return Err(read(&format!(
                    "'{n}' is there twice (with and without the module. prefix)"
                )));
            }
        }
        Ok(Self {
            names,
            rename,
            source: RefCell::new(source),
        })
    }

    fn get(&self, name: &str) -> candle_core::Result<Tensor> {
        let key = self.rename.get(name).map_or(name, |s| s.as_str());
        match &mut *self.source.borrow_mut() {
            Source::Safetensors(st) => st.read(key).map_err(candle_core::Error::Msg),
            Source::Pth(zip) => {
                let i = zip
                    .tensors()
                    .iter()
                    .position(|t| t.name == key)
                    .ok_or_else(|| candle_core::Error::Msg(format!("no tensor {name}")))?;
                let t = zip.tensors()[i].clone();
                let bytes = zip
                    .read(i)
                    .map_err(|e| candle_core::Error::Msg(e.reason()))?;
                let dtype = candle_dtype(t.dtype).expect("checked on open");
                Tensor::from_raw_buffer(&bytes, dtype, &t.shape, &Device::Cpu)
            }
        }
    }

    /// Sets every variable of `varmap` from this file after checking that the names
    /// and shapes are exactly the official `state_dict`'s for that network; returns
    /// the batch norms' `num_batches_tracked` (the largest, 0 without any).
    pub(crate) fn load_into(&self, varmap: &VarMap) -> Result<i64, WeightError> {
        let expected = state_dict_entries(varmap);
        let m = match_entries(&expected, &self.names);
        if !m.is_empty() {
            return Err(WeightError::Mismatch(m));
        }
        let err = |n: &str, e: candle_core::Error| WeightError::Read(format!("{n}: {e}"));
        let mut counter = 0i64;
        for e in expected.iter().filter(|e| e.dtype == DType::I64) {
            let t = self.get(&e.name).map_err(|x| err(&e.name, x))?;
            let v = t
                .to_dtype(DType::I64)
                .and_then(|t| t.to_scalar::<i64>())
                .map_err(|x| err(&e.name, x))?;
            counter = counter.max(v);
        }
        let data = varmap.data().lock().expect("varmap lock");
        for (name, var) in data.iter() {
            let t = self
                .get(name)
                .and_then(|t| t.to_dtype(DType::F32))
                .and_then(|t| t.reshape(var.dims()))
                .map_err(|x| err(name, x))?;
            var.set(&t).map_err(|x| err(name, x))?;
        }
        Ok(counter)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::PerspNetConfig;
    use crate::model::{PerspNet, synthetic_vertex_uv};
    use candle_nn::VarBuilder;

    fn varmap(cfg: &PerspNetConfig) -> VarMap {
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
        let uv = synthetic_vertex_uv(cfg.vertices, &Device::Cpu).unwrap();
        PerspNet::new(cfg, &uv, vb).unwrap();
        vm
    }

    /// The paper configuration's entries: 206, the official count, with the counters
    /// and the three-axis point-layer weights.
    #[test]
    fn paper_state_dict_has_the_official_entries() {
        let e = state_dict_entries(&varmap(&PerspNetConfig::paper()));
        assert_eq!(e.len(), 206);
        let counters = e.iter().filter(|x| x.dtype == DType::I64).count();
        assert_eq!(counters, 31);
        let get = |n: &str| e.iter().find(|x| x.name == n).unwrap().shape.clone();
        assert_eq!(get("assignment.0.weight"), vec![512, 2176, 1]);
        assert_eq!(get("cnn.resnet18_8s.conv1.weight"), vec![64, 3, 7, 7]);
        assert_eq!(get("cnn.seg.weight"), vec![2, 32, 1, 1]);
        assert_eq!(get("cnn.final.1.num_batches_tracked"), Vec::<usize>::new());
    }

    #[test]
    fn mismatch_lists_missing_extra_and_misshapen() {
        let expected = vec![
            StateEntry {
                name: "a.weight".into(),
                shape: vec![2, 3],
                dtype: DType::F32,
            },
            StateEntry {
                name: "b.weight".into(),
                shape: vec![4],
                dtype: DType::F32,
            },
            StateEntry {
                name: "b.num_batches_tracked".into(),
                shape: vec![],
                dtype: DType::I64,
            },
        ];
        let found = vec![
            ("a.weight".to_string(), vec![3, 2], DType::F32),
            ("b.num_batches_tracked".to_string(), vec![], DType::F32),
            ("c.bias".to_string(), vec![1], DType::F32),
        ];
        let m = match_entries(&expected, &found);
        assert_eq!(m.missing, vec!["b.weight".to_string()]);
        assert_eq!(m.extra, vec!["c.bias".to_string()]);
        assert_eq!(
            m.misshapen,
            vec![
                ("a.weight".to_string(), vec![2, 3], vec![3, 2]),
                ("b.num_batches_tracked".to_string(), vec![], vec![]),
            ]
        );
        let s = m.to_string();
        assert!(s.contains("1 missing: b.weight"), "{s}");
        assert!(s.contains("1 extra: c.bias"), "{s}");
        assert!(s.contains("a.weight is [3, 2], expected [2, 3]"), "{s}");
        assert!(match_entries(&expected[..1], &found[..0]).missing.len() == 1);
    }
}
