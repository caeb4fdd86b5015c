//! `arkit_tool.ConvertedDataset` and `read_image` (`_converted.py`): a converted
//! dataset's samples by position (`Dataset`), an image decoded as the loader decodes it,
//! and the face topology a dataset was converted with (`topology`, for `view.py`).

use crate::errors::run;
use arkit_core::{Error, SampleKey};
use arkit_data::mesh::FaceTopology;
use arkit_data::store::SampleRecord;
use numpy::{IntoPyArray, PyArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// The topology a dataset was converted with: `resources` when given, else the folder
/// its manifest names when that is a resources folder, else the built-in face.
pub(crate) fn topology_for(
    dir: &Path,
    resources: Option<&Path>,
) -> arkit_core::Result<(FaceTopology, Option<PathBuf>)> {
    let from = match resources {
        Some(r) => Some(r.to_path_buf()),
        None => {
            let data = arkit_data::store::Dataset::open(dir)?;
            let recorded = PathBuf::from(&data.manifest().topology);
            recorded.join("triangles.npy").is_file().then_some(recorded)
        }
    };
    match from {
        Some(r) => Ok((FaceTopology::from_resources(&r)?, Some(r))),
        None => Ok((arkit_data::mesh::builtin().topology.clone(), None)),
    }
}

/// Where each sample is: its shard and its row in the shard.
struct Located {
    key: SampleKey,
    split: String,
    shard: usize,
    row: usize,
}

/// A converted dataset's samples, read shard by shard (the last shard read is kept).
#[pyclass(module = "arkit_tool._native", frozen)]
pub(crate) struct Dataset {
    inner: arkit_data::store::Dataset,
    rows: Vec<Located>,
    cache: Mutex<Option<(usize, Vec<SampleRecord>)>>,
}

#[pymethods]
impl Dataset {
    #[new]
    /// `dir`: a dataset folder, or the URL of a published one (`s3://bucket/prefix`:
    /// its tables mirrored in the cache folder).
    #[pyo3(signature = (dir, cache_dir=None, storage_options=None))]
    fn new(
        py: Python<'_>,
        dir: String,
        cache_dir: Option<PathBuf>,
        storage_options: Option<std::collections::BTreeMap<String, String>>,
    ) -> PyResult<Self> {
        let (inner, rows) = run(py, || {
            use arkit_data::storage::{DatasetLocation, MirrorSet, RemoteOptions, open_remote};
            let dir = match DatasetLocation::parse(&dir)? {
                DatasetLocation::Local(p) => p,
                DatasetLocation::Remote(url) => open_remote(
                    &url,
                    &MirrorSet::Loader { crop_store: None },
                    &RemoteOptions {
                        cache_dir,
                        cache_bytes: None,
                        settings: storage_options.unwrap_or_default().into_iter().collect(),
                    },
                )?
                .local_dir()
                .to_path_buf(),
            };
            let data = arkit_data::store::Dataset::open(&dir)?;
            let splits = arkit_data::store::SplitLookup::read(&dir)?;
            let mut rows = Vec::new();
            for (k, shard) in data.shards().iter().enumerate() {
                for (row, (key, listed)) in data.read_sample_keys(shard)?.into_iter().enumerate() {
                    let split = splits.of_key(&key, &listed);
                    rows.push(Located {
                        key,
                        split,
                        shard: k,
                        row,
                    });
                }
            }
            Ok((data, rows))
        })?;
        Ok(Dataset {
            inner,
            rows,
            cache: Mutex::new(None),
        })
    }

    fn __len__(&self) -> usize {
        self.rows.len()
    }

    /// `(subject_id, facial_action, img_id, split)` per sample, in order.
    fn keys(&self) -> Vec<(String, String, String, String)> {
        self.rows
            .iter()
            .map(|r| {
                (
                    r.key.subject_id.clone(),
                    r.key.facial_action.clone(),
                    r.key.img_id.clone(),
                    r.split.clone(),
                )
            })
            .collect()
    }

    /// The samples tables' files, in shard order.
    fn shard_files(&self) -> Vec<String> {
        self.inner
            .shards()
            .iter()
            .map(|s| {
                self.inner
                    .dir()
                    .join(&s.samples_file)
                    .to_string_lossy()
                    .into_owned()
            })
            .collect()
    }

    /// The manifest (`dataset.json`) as JSON text.
    fn manifest_json(&self) -> String {
        serde_json::to_string(self.inner.manifest()).expect("the manifest serialises")
    }

    /// Sample `index` as a dict.
    fn sample<'py>(&self, py: Python<'py>, index: usize) -> PyResult<Bound<'py, PyDict>> {
        let loc = self.rows.get(index).ok_or_else(|| {
            pyo3::exceptions::PyIndexError::new_err(format!(
                "index {index} out of range for {} samples",
                self.rows.len()
            ))
        })?;
        let (shard, row) = (loc.shard, loc.row);
        let r = run(py, || {
            let mut cache = self.cache.lock().unwrap_or_else(|e| e.into_inner());
            if cache.as_ref().map(|c| c.0) != Some(shard) {
                let rows = self.inner.read_samples(&self.inner.shards()[shard])?;
                *cache = Some((shard, rows));
            }
            let rows = &cache.as_ref().expect("just filled").1;
            rows.get(row).cloned().ok_or_else(|| {
                Error::invalid(
                    "dataset",
                    format!("shard {shard} has no row {row}: it changed"),
                )
            })
        })?;
        let d = PyDict::new(py);
        d.set_item("subject_id", &r.key.subject_id)?;
        d.set_item("facial_action", &r.key.facial_action)?;
        d.set_item("img_id", &r.key.img_id)?;
        d.set_item("split", &loc.split)?;
        d.set_item("listed_split", &r.split)?;
        d.set_item(
            "image_path",
            self.inner
                .image_path(&r)
                .map(|p| p.to_string_lossy().into_owned()),
        )?;
        d.set_item("image_width", r.image_width)?;
        d.set_item("image_height", r.image_height)?;
        let v = r.verts.len() / 3;
        d.set_item("verts", r.verts.into_pyarray(py).reshape([v, 3])?)?;
        d.set_item("R_t", r.rt.to_vec().into_pyarray(py).reshape([4, 4])?)?;
        d.set_item("yaw_deg", r.yaw_deg)?;
        d.set_item("pitch_deg", r.pitch_deg)?;
        d.set_item("roll_deg", r.roll_deg)?;
        d.set_item("translation_m", r.translation_m.to_vec().into_pyarray(py))?;
        let l = r.landmarks_2d.len() / 2;
        d.set_item(
            "landmarks_2d",
            r.landmarks_2d.into_pyarray(py).reshape([l, 2])?,
        )?;
        d.set_item("face_box", r.face_box.to_vec().into_pyarray(py))?;
        Ok(d)
    }
}

/// An image file decoded as the loader decodes it (`arkit_data::picture::read_rgb8_checked`: PNG,
/// JPEG or WebP, its size checked from the header against the limits before decoding, 16-bit
/// scaled to 8): `(H, W, 3)` uint8 RGB.
#[pyfunction]
pub(crate) fn read_image<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyAny>> {
    let img = run(py, || {
        arkit_data::picture::read_rgb8_checked(&path, |_| Ok(()))
    })?;
    let (w, h) = img.dimensions();
    Ok(img
        .into_raw()
        .into_pyarray(py)
        .reshape([h as usize, w as usize, 3])?
        .into_any())
}

/// The face topology a converted dataset was converted with (see [`topology_for`]):
/// `triangles` (T x 3 uint32), `landmarks` (68 uint32 vertex ids), `uv` (V x 2 float32),
/// `vertex_count` and `source`.
#[pyfunction]
#[pyo3(signature = (dir, resources=None))]
pub(crate) fn topology<'py>(
    py: Python<'py>,
    dir: PathBuf,
    resources: Option<PathBuf>,
) -> PyResult<Bound<'py, PyDict>> {
    let (topo, _) = run(py, || topology_for(&dir, resources.as_deref()))?;
    let d = PyDict::new(py);
    let t = topo.triangles.len();
    let tris: Vec<u32> = topo.triangles.iter().flatten().copied().collect();
    d.set_item("triangles", tris.into_pyarray(py).reshape([t, 3])?)?;
    d.set_item("landmarks", topo.landmarks.clone().into_pyarray(py))?;
    let v = topo.uv.len();
    let uv: Vec<f32> = topo.uv.iter().flatten().copied().collect();
    d.set_item("uv", uv.into_pyarray(py).reshape([v, 2])?)?;
    d.set_item("vertex_count", topo.vertex_count)?;
    d.set_item("source", &topo.source)?;
    Ok(d)
}
