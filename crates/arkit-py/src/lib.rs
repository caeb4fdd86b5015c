//! `arkit_tool._native`: the Python package's Rust core (pyo3). The Python layer
//! (`python/src/arkit_tool/`) wraps these classes and functions; users import
//! `arkit_tool`, not this module.
//!
//! What crosses the boundary:
//! - `Loader`: `arkit_data::loader::FaceLoader`, one sample as the official PyTorch
//!   loader returns it, as numpy arrays that own the Rust buffers (no copy).
//! - `Dataset`: a converted dataset's samples, by position.
//! - `solve_pnp_ransac`, `project`, `evaluate`: PnP, the release's projection and
//!   the paper's metrics; `topology`: the mesh a dataset was converted with.
//! - `poses_to_opencv`, `poses_from_arkit`, `pose_angles`, ...: the head pose in other
//!   tools' conventions (`arkit_core::conventions::AngleConvention` and `Pose`), on
//!   (N, k) float64 rows; `arkit_tool.conventions` shapes them.
//!
//! Invariants: the GIL is released while Rust works (`Python::detach`); nothing here
//! keeps a thread running (a dataset read from a bucket drives its requests on the
//! calling thread, and makes its client again in a forked child), so a loader is safe
//! to use after `fork` (DataLoader workers); every
//! error, and any panic, reaches Python as `DataError` (a `ValueError`) whose message
//! names the file and the problem, never as a Rust panic. Tested by `python/tests`.

use arkit_core::SampleKey;
use arkit_core::conventions::Camera;
use arkit_data::crop::RuleSet;
use arkit_data::loader::{FaceLoader, LoaderItem, LoaderMode, LoaderOptions};
use arkit_data::loader::{rewrite_correspondence_matrix, write_correspondence_matrix};
use arkit_data::store::SampleRecord;

use arkit_core::Error;

use arkit_data::mesh::FaceTopology;

use arkit_core::conventions::{AngleConvention, Pose};
use nalgebra::{Point2, Point3};
use numpy::{
    IntoPyArray, PyArrayDyn, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2,
    PyUntypedArrayMethods,
};
use pyo3::create_exception;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

create_exception!(
    _native,
    DataError,
    pyo3::exceptions::PyValueError,
    "A dataset, sample or argument that arkit_tool cannot use; the message names the file and the problem."
);

fn py_err(e: Error) -> PyErr {
    DataError::new_err(e.to_string())
}

/// Runs `f` without the GIL, turning an error or a panic into `DataError`.
fn run<T: Send>(py: Python<'_>, f: impl FnOnce() -> arkit_core::Result<T> + Send) -> PyResult<T> {
    py.detach(|| std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)))
        .map_err(|p| {
            let why = p
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_default();
            DataError::new_err(format!("internal error (a bug in arkit_tool): {why}"))
        })?
        .map_err(py_err)
}

/// The topology a dataset was converted with: `resources` when given, else the folder
/// its manifest names when that is a resources folder, else the built-in face.
fn topology_for(
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

/// One sample after another as the official loader returns them.
#[pyclass(module = "arkit_tool._native", frozen)]
struct Loader {
    inner: std::sync::Arc<FaceLoader>,
    /// The published dataset, when read from a bucket (kept for its mirror and client).
    remote: Option<arkit_data::storage::RemoteDataset>,
    /// The crop store as the user knows it: its folder, or its URL.
    store_shown: Option<String>,
}

/// The crop store of a dataset read from a bucket: its folder relative to the dataset,
/// from `crop_store` (`"auto"` or None: the default store's, `crops/<compat>-<S>`; a
/// path relative to the dataset; or a URL inside the dataset's prefix), and whether the
/// user named it.
fn remote_store_relative(
    url: &arkit_data::storage::RemoteUrl,
    crop_store: Option<&str>,
    rules: RuleSet,
    img_size: u32,
) -> arkit_core::Result<(String, bool)> {
    match crop_store {
        None | Some("auto") => Ok((format!("crops/{}-{img_size}", rules.name()), false)),
        Some(s) if arkit_data::storage::DatasetLocation::is_remote_arg(s) => {
            let store = arkit_data::storage::RemoteUrl::parse(s)?;
            let prefix = format!("{}/", url.prefix());
            let inside = store.bucket() == url.bucket()
                && (url.prefix().is_empty() || store.prefix().starts_with(&prefix));
            if !inside {
                return Err(Error::invalid(
                    "crop_store",
                    format!("{store}: not inside the dataset's prefix {url}"),
                ));
            }
            let rel = if url.prefix().is_empty() {
                store.prefix().to_string()
            } else {
                store.prefix()[prefix.len()..].to_string()
            };
            Ok((rel, true))
        }
        Some(s) => Ok((s.trim_matches('/').to_string(), true)),
    }
}

#[pymethods]
impl Loader {
    #[new]
    /// `dir`: a dataset folder, or the URL of a published one (`s3://bucket/prefix`).
    /// `crop_store`: a store folder `arkit-tool crops` wrote (pixels and meshes read
    /// from it), or None (the release's images decoded); for a URL, `"auto"` (the
    /// default store of these rules and size), a path relative to the dataset, or a
    /// URL inside it. `cache_dir` and `cache_bytes`: the local cache of a dataset read
    /// from a bucket (records cached up to `cache_bytes`, 10 GiB by default);
    /// `storage_options`: client settings over the environment's (`aws_endpoint`, ...).
    #[pyo3(signature = (dir, split, mode, compat, img_size, n_pts, seed, resources=None, crop_store=None, cache_dir=None, cache_bytes=None, storage_options=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        dir: String,
        split: Option<String>,
        mode: &str,
        compat: &str,
        img_size: u32,
        n_pts: usize,
        seed: u64,
        resources: Option<PathBuf>,
        crop_store: Option<String>,
        cache_dir: Option<PathBuf>,
        cache_bytes: Option<u64>,
        storage_options: Option<std::collections::BTreeMap<String, String>>,
    ) -> PyResult<Self> {
        let settings: Vec<(String, String)> =
            storage_options.unwrap_or_default().into_iter().collect();
        let options = LoaderOptions {
            split,
            mode: LoaderMode::parse(mode).map_err(py_err)?,
            rules: RuleSet::parse(compat).map_err(py_err)?,
            img_size,
            n_pts,
            seed,
        };
        let (inner, remote, store_shown) = run(py, || {
            use arkit_data::storage::{DatasetLocation, MirrorSet, RemoteOptions, open_remote};
            let (local, remote) = match DatasetLocation::parse(&dir)? {
                DatasetLocation::Local(p) => (p, None),
                DatasetLocation::Remote(url) => {
                    let (rel, named) = remote_store_relative(
                        &url,
                        crop_store.as_deref(),
                        options.rules,
                        img_size,
                    )?;
                    let remote = open_remote(
                        &url,
                        &MirrorSet::Loader {
                            crop_store: Some(rel.clone()),
                        },
                        &RemoteOptions {
                            cache_dir: cache_dir.clone(),
                            cache_bytes,
                            settings: settings.clone(),
                        },
                    )?;
                    (remote.local_dir().to_path_buf(), Some((remote, rel, named)))
                }
            };
            let (topology, from) = topology_for(&local, resources.as_deref())?;
            let uv_triangles = match &from {
                Some(r) => arkit_data::loader::read_uv_triangles(r)?,
                None => None,
            };
            let mut loader = FaceLoader::open(&local, topology, uv_triangles, options)?;
            let mut shown = None;
            let remote = match remote {
                None => {
                    if let Some(store) = &crop_store {
                        loader.open_crop_store(Path::new(store))?;
                        shown = Some(store.clone());
                    }
                    None
                }
                Some((remote, rel, named)) => {
                    let manifest = format!("{rel}/crops.json");
                    if remote.publication().object(&manifest).is_some() {
                        let dir = remote.local_dir().join(&rel);
                        loader.open_remote_crop_store(&dir, &remote, &rel)?;
                        shown = Some(remote.url().join(&rel).to_string());
                    } else if named
                        || (crop_store.as_deref() == Some("auto")
                            && !loader.dataset().manifest().embed_images)
                    {
                        return Err(Error::format(
                            remote.url().shown_path(&manifest),
                            format!(
                                "not in the dataset's publication: a dataset read from a bucket needs a crop store (`arkit-tool crops --dataset DIR --compat {compat} --size {img_size}`, then `arkit-tool push` again) unless its images are embedded"
                            ),
                        ));
                    }
                    Some(remote)
                }
            };
            Ok((loader, remote, shown))
        })?;
        Ok(Loader {
            inner: std::sync::Arc::new(inner),
            remote,
            store_shown,
        })
    }

    /// What this loader serves, as one text: the dataset's fingerprint and a hash of
    /// its crop store's record. A loader opened again (in a spawned worker) that gives
    /// another text is serving another generation of the folder.
    #[getter]
    fn generation(&self) -> String {
        use std::hash::{Hash, Hasher};
        let mut g = self.inner.dataset().manifest().fingerprint.clone();
        if let Some(store) = self.inner.crop_store() {
            let record = serde_json::to_vec(store.manifest()).unwrap_or_default();
            let mut h = std::hash::DefaultHasher::new();
            record.hash(&mut h);
            g.push_str(&format!(":{:016x}", h.finish()));
        }
        g
    }

    /// The URL the dataset is read from, or None for a local folder.
    #[getter]
    fn url(&self) -> Option<String> {
        self.remote.as_ref().map(|r| r.url().to_string())
    }

    /// The crop-store record of sample `index` as stored (bytes): for carrying records
    /// by another transport (the LitData comparison of python/bench/cloud.py).
    fn record<'py>(
        &self,
        py: Python<'py>,
        index: usize,
    ) -> PyResult<Bound<'py, pyo3::types::PyBytes>> {
        let bytes = run(py, || self.inner.record_bytes(index))?;
        Ok(pyo3::types::PyBytes::new(py, &bytes))
    }

    /// Takes `records[k]` (what `record` gave) as the record of sample `indices[k]` for
    /// its next item, each checked as a record read from the store is.
    fn supply(
        &self,
        py: Python<'_>,
        indices: Vec<usize>,
        records: Vec<Bound<'_, pyo3::types::PyBytes>>,
    ) -> PyResult<()> {
        use pyo3::types::PyBytesMethods;
        let records: Vec<Vec<u8>> = records.iter().map(|b| b.as_bytes().to_vec()).collect();
        if indices.len() != records.len() {
            return Err(DataError::new_err(format!(
                "{} indices and {} records",
                indices.len(),
                records.len()
            )));
        }
        run(py, || {
            for (i, r) in indices.into_iter().zip(records) {
                self.inner.supply_record(i, r)?;
            }
            Ok(())
        })
    }

    /// Starts fetching the records of samples `indices` on a thread of its own and
    /// returns at once (a no-op for a local store): the items of those samples wait for
    /// it. For DataLoader workers, which do not fork again; at most 1,024 records kept.
    fn prefetch_async(&self, indices: Vec<usize>) {
        self.inner.prefetch_in_background(&indices);
    }

    /// Fetches the records of samples `indices` ahead (concurrently, from a bucket; a
    /// no-op for a local store), kept for the items that follow (at most 1,024).
    fn prefetch(&self, py: Python<'_>, indices: Vec<usize>) -> PyResult<()> {
        run(py, || {
            self.inner.prefetch(&indices);
            Ok(())
        })
    }

    fn __len__(&self) -> usize {
        self.inner.len()
    }

    /// The crop store items are read from (its folder, or its URL), or None.
    #[getter]
    fn crop_store(&self) -> Option<String> {
        self.store_shown.clone()
    }

    /// `(subject_id, facial_action, img_id, split)` of sample `index`.
    fn key(&self, index: usize) -> PyResult<(String, String, String, String)> {
        let (k, s) = self.inner.key(index).ok_or_else(|| {
            pyo3::exceptions::PyIndexError::new_err(format!(
                "index {index} out of range for {} samples",
                self.inner.len()
            ))
        })?;
        Ok((
            k.subject_id.clone(),
            k.facial_action.clone(),
            k.img_id.clone(),
            s.to_string(),
        ))
    }

    /// Sample `index` of `epoch` as a dict of numpy arrays; `corr` is `"dense"`,
    /// `"sparse"` or `"both"`; `extras` adds the official box and pre-mapping points.
    #[pyo3(signature = (index, epoch=0, corr="dense", eval_keys=false, extras=false))]
    fn item<'py>(
        &self,
        py: Python<'py>,
        index: usize,
        epoch: u64,
        corr: &str,
        eval_keys: bool,
        extras: bool,
    ) -> PyResult<Bound<'py, PyDict>> {
        let (dense, sparse) = corr_forms(corr)?;
        if index >= self.inner.len() {
            return Err(pyo3::exceptions::PyIndexError::new_err(format!(
                "index {index} out of range for {} samples",
                self.inner.len()
            )));
        }
        let (item, corr_mat) = run(py, || {
            let item = self.inner.item(index, epoch)?;
            let corr_mat = dense.then(|| dense_correspondences(&item));
            Ok((item, corr_mat))
        })?;
        item_dict(py, item, corr_mat, sparse, eval_keys, extras)
    }

    /// Samples `indices` of `epoch` as one dict of batch arrays: `item`'s keys, dtypes
    /// and values with a leading batch axis (strings as lists), written in place by
    /// Rust without the GIL, so a batch costs no per-sample array and no stacking copy.
    /// The first sample that fails raises, naming it.
    ///
    /// `reuse`: the arrays of an earlier batch of the same size and options that nobody
    /// holds any more (a dict of this method's array keys; the Python layer keeps a few
    /// and checks that they are free). They are written over, every element, instead of
    /// making new ones: fresh arrays of a batch's size come from the kernel as untouched
    /// pages, and touching them (a page fault per 4 KiB: 80,000 for the dense
    /// `corr_mat` of 64 samples) cost more than computing the samples.
    #[pyo3(signature = (indices, epoch=0, corr="dense", eval_keys=false, reuse=None))]
    fn batch<'py>(
        &self,
        py: Python<'py>,
        indices: Vec<usize>,
        epoch: u64,
        corr: &str,
        eval_keys: bool,
        reuse: Option<Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let (dense, sparse) = corr_forms(corr)?;
        if let Some(&bad) = indices.iter().find(|&&i| i >= self.inner.len()) {
            return Err(pyo3::exceptions::PyIndexError::new_err(format!(
                "index {bad} out of range for {} samples",
                self.inner.len()
            )));
        }
        let loader = &self.inner;
        let (b, s, u) = (
            indices.len(),
            loader.options().img_size as usize,
            loader.uvmap_size() as usize,
        );
        let (n, v) = (loader.options().n_pts, loader.mesh_vertex_count());
        let np = py.import("numpy")?;
        let reuse = reuse.as_ref();
        let img = array_for::<f32>(&np, reuse, "img", "empty", &[b, 3, s, s])?;
        let uvmap = array_for::<f32>(&np, reuse, "uvmap", "empty", &[b, 3, u, u])?;
        let mask = array_for::<i64>(&np, reuse, "mask", "empty", &[b, s, s])?;
        let choose = array_for::<i64>(&np, reuse, "choose", "empty", &[b, n])?;
        let model = array_for::<f32>(&np, reuse, "model", "empty", &[b, v, 3])?;
        let nocs = array_for::<f32>(&np, reuse, "nocs", "empty", &[b, n, 3])?;
        let sparse_n = if sparse { n } else { 0 };
        let ids = array_for::<i64>(&np, reuse, "corr_ids", "empty", &[b, sparse_n, 3])?;
        let weights = array_for::<f32>(&np, reuse, "corr_weights", "empty", &[b, sparse_n, 3])?;
        // Every value of the matrix is written (`write_correspondence_matrix`).
        let dense_n = if dense { n } else { 0 };
        let corr_mat = array_for::<f32>(&np, reuse, "corr_mat", "empty", &[b, dense_n, v])?;
        let tform = new_array::<f64>(&np, "empty", &[b, 2, 3])?;
        let rt = new_array::<f64>(&np, "empty", &[b, 4, 4])?;
        let keys = {
            // SAFETY: the arrays were just made here by numpy, C-contiguous, and nothing
            // else holds them while Rust writes. Every element of the `empty` ones is
            // written before Python sees them (each sample's slices are filled whole, or
            // the batch is dropped on an error).
            let out = unsafe {
                BatchSlices {
                    img: img.as_slice_mut()?,
                    uvmap: uvmap.as_slice_mut()?,
                    mask: mask.as_slice_mut()?,
                    choose: choose.as_slice_mut()?,
                    model: model.as_slice_mut()?,
                    nocs: nocs.as_slice_mut()?,
                    ids: ids.as_slice_mut()?,
                    weights: weights.as_slice_mut()?,
                    corr_mat: corr_mat.as_slice_mut()?,
                    tform: tform.as_slice_mut()?,
                    rt: rt.as_slice_mut()?,
                }
            };
            run(py, || out.fill(loader, &indices, epoch))?
        };
        let d = PyDict::new(py);
        d.set_item("img", img)?;
        d.set_item("choose", choose)?;
        d.set_item("model", model)?;
        d.set_item("uvmap", uvmap)?;
        d.set_item("nocs", nocs)?;
        d.set_item("mask", mask)?;
        if dense {
            d.set_item("corr_mat", corr_mat)?;
        }
        if sparse {
            d.set_item("corr_ids", ids)?;
            d.set_item("corr_weights", weights)?;
        }
        if eval_keys {
            d.set_item("tform_inv", tform)?;
            d.set_item("R_t", rt)?;
            let column = |f: fn(&(PathBuf, SampleKey)) -> String| -> Vec<String> {
                keys.iter().map(f).collect()
            };
            d.set_item("img_path", column(|k| k.0.to_string_lossy().into_owned()))?;
            d.set_item("subjectid", column(|k| k.1.subject_id.clone()))?;
            d.set_item("imgid", column(|k| k.1.img_id.clone()))?;
            d.set_item("facial_action", column(|k| k.1.facial_action.clone()))?;
        }
        Ok(d)
    }
}

/// `reuse[key]` when it is given and holds that key (it must then be a C-contiguous,
/// writeable array of `shape`), else a new array made by numpy's `make`.
fn array_for<'py, T: numpy::Element>(
    np: &Bound<'py, PyModule>,
    reuse: Option<&Bound<'py, PyDict>>,
    key: &str,
    make: &str,
    shape: &[usize],
) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    let Some(given) = reuse.map(|r| r.get_item(key)).transpose()?.flatten() else {
        return new_array(np, make, shape);
    };
    let a = given.cast_into::<PyArrayDyn<T>>().map_err(|_| {
        DataError::new_err(format!(
            "reuse['{key}']: not an array of this batch's dtype"
        ))
    })?;
    let writeable: bool = a.getattr("flags")?.getattr("writeable")?.extract()?;
    if a.shape() != shape || !a.is_c_contiguous() || !writeable {
        return Err(DataError::new_err(format!(
            "reuse['{key}']: shape {:?}, expected a C-contiguous writeable {shape:?}",
            a.shape()
        )));
    }
    Ok(a)
}

/// A new C-ordered array of `shape` made by numpy's `make` (`empty` or `zeros`), so
/// that a batch too large for memory raises `MemoryError` in Python.
fn new_array<'py, T: numpy::Element>(
    np: &Bound<'py, PyModule>,
    make: &str,
    shape: &[usize],
) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    let shape = pyo3::types::PyTuple::new(np.py(), shape)?;
    let array = np.getattr(make)?.call1((shape, T::get_dtype(np.py())))?;
    Ok(array.cast_into::<PyArrayDyn<T>>()?)
}

/// `(dense, sparse)` for the `corr` argument.
fn corr_forms(corr: &str) -> PyResult<(bool, bool)> {
    match corr {
        "dense" => Ok((true, false)),
        "sparse" => Ok((false, true)),
        "both" => Ok((true, true)),
        _ => Err(DataError::new_err(format!(
            "corr: '{corr}': expected 'dense', 'sparse' or 'both'"
        ))),
    }
}

/// A batch's arrays as flat slices, the batch axis first; the correspondence arrays
/// are empty when their form was not asked for.
struct BatchSlices<'a> {
    img: &'a mut [f32],
    uvmap: &'a mut [f32],
    mask: &'a mut [i64],
    choose: &'a mut [i64],
    model: &'a mut [f32],
    nocs: &'a mut [f32],
    ids: &'a mut [i64],
    weights: &'a mut [f32],
    corr_mat: &'a mut [f32],
    tform: &'a mut [f64],
    rt: &'a mut [f64],
}

impl BatchSlices<'_> {
    /// Computes the samples `indices` into the slices, one after another; returns each
    /// sample's image path and key.
    fn fill(
        self,
        loader: &FaceLoader,
        indices: &[usize],
        epoch: u64,
    ) -> arkit_core::Result<Vec<(PathBuf, SampleKey)>> {
        let b = indices.len().max(1);
        let per = |len: usize| len / b;
        let (img_n, uv_n, mask_n) = (
            per(self.img.len()),
            per(self.uvmap.len()),
            per(self.mask.len()),
        );
        let (choose_n, model_n, corr_n) = (
            per(self.choose.len()),
            per(self.model.len()),
            per(self.corr_mat.len()),
        );
        let v = loader.mesh_vertex_count();
        // A store in a bucket: the batch's records fetched together, concurrently.
        loader.prefetch(indices);
        let mut keys = Vec::with_capacity(indices.len());
        for (k, &index) in indices.iter().enumerate() {
            let at = |len: usize| k * len..(k + 1) * len;
            let item = loader.item_into(
                index,
                epoch,
                arkit_data::loader::ItemPlanes {
                    img: &mut self.img[at(img_n)],
                    uvmap: &mut self.uvmap[at(uv_n)],
                },
            )?;
            let lengths_fit = item.mask.len() == mask_n
                && item.choose.len() == choose_n
                && item.model.len() == model_n
                && item.nocs.len() == 3 * choose_n
                && item.corr_vertices.len() == choose_n;
            if !lengths_fit {
                return Err(Error::invalid(
                    "batch",
                    format!(
                        "{}: the item's arrays do not have the batch's shapes (a bug in arkit_tool)",
                        item.key
                    ),
                ));
            }
            arkit_data::loader::widen_mask_into(&item.mask, &mut self.mask[at(mask_n)]);
            self.choose[at(choose_n)].copy_from_slice(&item.choose);
            self.model[at(model_n)].copy_from_slice(&item.model);
            self.nocs[at(3 * choose_n)].copy_from_slice(&item.nocs);
            if !self.ids.is_empty() {
                let ids = &mut self.ids[at(3 * choose_n)];
                for (o, &x) in ids.iter_mut().zip(item.corr_vertices.iter().flatten()) {
                    *o = x as i64;
                }
                let w = &mut self.weights[at(3 * choose_n)];
                for (o, &x) in w.iter_mut().zip(item.corr_weights.iter().flatten()) {
                    *o = x;
                }
            }
            if !self.corr_mat.is_empty() {
                // Every value written (old batches' values replaced).
                write_correspondence_matrix(
                    &mut self.corr_mat[at(corr_n)],
                    v,
                    &item.corr_vertices,
                    &item.corr_weights,
                );
            }
            self.tform[at(6)].copy_from_slice(&item.tform_inv);
            self.rt[at(16)].copy_from_slice(&item.rt);
            keys.push((item.image_path, item.key));
        }
        Ok(keys)
    }
}

/// The dense `n_pts x V` correspondence matrix of an item (`V` from its mesh).
fn dense_correspondences(item: &LoaderItem) -> Vec<f32> {
    let v = item.model.len() / 3;
    let mut m = vec![0f32; item.corr_vertices.len() * v];
    write_correspondence_matrix(&mut m, v, &item.corr_vertices, &item.corr_weights);
    m
}

fn item_dict<'py>(
    py: Python<'py>,
    item: LoaderItem,
    corr_mat: Option<Vec<f32>>,
    sparse: bool,
    eval_keys: bool,
    extras: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let s = (item.mask.len() as f64).sqrt() as usize;
    let n = item.choose.len();
    let v = item.model.len() / 3;
    let d = PyDict::new(py);
    d.set_item("img", item.img.into_pyarray(py).reshape([3, s, s])?)?;
    d.set_item("choose", item.choose.into_pyarray(py))?;
    d.set_item("model", item.model.into_pyarray(py).reshape([v, 3])?)?;
    d.set_item("uvmap", {
        let u = item.uvmap;
        let us = ((u.len() / 3) as f64).sqrt() as usize;
        u.into_pyarray(py).reshape([3, us, us])?
    })?;
    d.set_item("nocs", item.nocs.into_pyarray(py).reshape([n, 3])?)?;
    let mask: Vec<i64> = item.mask.iter().map(|&m| m as i64).collect();
    d.set_item("mask", mask.into_pyarray(py).reshape([s, s])?)?;
    if let Some(m) = corr_mat {
        d.set_item("corr_mat", m.into_pyarray(py).reshape([n, v])?)?;
    }
    if sparse {
        let ids: Vec<i64> = item
            .corr_vertices
            .iter()
            .flat_map(|t| t.map(|x| x as i64))
            .collect();
        let w: Vec<f32> = item.corr_weights.iter().flatten().copied().collect();
        d.set_item("corr_ids", ids.into_pyarray(py).reshape([n, 3])?)?;
        d.set_item("corr_weights", w.into_pyarray(py).reshape([n, 3])?)?;
    }
    if eval_keys {
        d.set_item(
            "tform_inv",
            item.tform_inv.to_vec().into_pyarray(py).reshape([2, 3])?,
        )?;
        d.set_item("R_t", item.rt.to_vec().into_pyarray(py).reshape([4, 4])?)?;
        d.set_item("img_path", item.image_path.to_string_lossy().into_owned())?;
        d.set_item("subjectid", &item.key.subject_id)?;
        d.set_item("imgid", &item.key.img_id)?;
        d.set_item("facial_action", &item.key.facial_action)?;
    }
    if extras {
        d.set_item("choose_box", item.choose_box.into_pyarray(py))?;
        if let Some(b) = item.official_box {
            d.set_item("box", b.to_vec().into_pyarray(py))?;
        }
        d.set_item("box_clipped", item.box_clipped)?;
        let c = item.crop;
        d.set_item("crop", (c.x0, c.y0, c.side, c.side_y))?;
        d.set_item("image_path", item.image_path.to_string_lossy().into_owned())?;
    }
    Ok(d)
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
struct Dataset {
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

/// Robust PnP (P3P + MSAC + Levenberg-Marquardt) with OpenCV's conventions:
/// `X_cam = R X + t`, pixels, `camera_matrix` 3x3, no distortion. Returns
/// `(success, rvec (3, 1), tvec (3, 1), inliers (k, 1) int32)`, or
/// `(False, None, None, None)`. Correspondences with a NaN or infinite coordinate are
/// left out (never inliers; the inlier indices are the caller's).
#[pyfunction]
#[pyo3(signature = (object_points, image_points, camera_matrix, reprojection_error=8.0, iterations_count=100, confidence=0.99, seed=0))]
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
fn solve_pnp_ransac<'py>(
    py: Python<'py>,
    object_points: PyReadonlyArray2<'py, f64>,
    image_points: PyReadonlyArray2<'py, f64>,
    camera_matrix: PyReadonlyArray2<'py, f64>,
    reprojection_error: f64,
    iterations_count: usize,
    confidence: f64,
    seed: u64,
) -> PyResult<(
    bool,
    Option<Py<PyAny>>,
    Option<Py<PyAny>>,
    Option<Py<PyAny>>,
)> {
    let (o, i, k) = (
        object_points.as_array(),
        image_points.as_array(),
        camera_matrix.as_array(),
    );
    if o.ncols() != 3 || i.ncols() != 2 || o.nrows() != i.nrows() {
        return Err(DataError::new_err(format!(
            "object_points must be (N, 3) and image_points (N, 2) with the same N; got {:?} and {:?}",
            o.shape(),
            i.shape()
        )));
    }
    if k.shape() != [3, 3] {
        return Err(DataError::new_err(format!(
            "camera_matrix must be 3x3, got {:?}",
            k.shape()
        )));
    }
    let object: Vec<Point3<f64>> = o
        .rows()
        .into_iter()
        .map(|r| Point3::new(r[0], r[1], r[2]))
        .collect();
    let image: Vec<Point2<f64>> = i
        .rows()
        .into_iter()
        .map(|r| Point2::new(r[0], r[1]))
        .collect();
    let intr = arkit_data::pose::Intrinsics {
        fx: k[[0, 0]],
        fy: k[[1, 1]],
        cx: k[[0, 2]],
        cy: k[[1, 2]],
    };
    let params = arkit_data::pose::RansacParams {
        reprojection_threshold_px: reprojection_error,
        max_iterations: iterations_count,
        confidence,
        seed,
    };
    let solved = py.detach(|| arkit_data::pose::solve_pnp_ransac(&object, &image, &intr, &params));
    match solved {
        Err(_) => Ok((false, None, None, None)),
        Ok(s) => {
            let r = s.rotation.scaled_axis();
            let rvec = vec![r.x, r.y, r.z].into_pyarray(py).reshape([3, 1])?;
            let t = s.translation;
            let tvec = vec![t.x, t.y, t.z].into_pyarray(py).reshape([3, 1])?;
            let inl: Vec<i32> = s.inliers.iter().map(|&x| x as i32).collect();
            let m = inl.len();
            let inliers = inl.into_pyarray(py).reshape([m, 1])?;
            Ok((
                true,
                Some(rvec.into_any().unbind()),
                Some(tvec.into_any().unbind()),
                Some(inliers.into_any().unbind()),
            ))
        }
    }
}

/// Projects canonical points `(N, 3)` with the release's `R_t` (4x4, row-vector form)
/// and camera for a `width x height` image: `(N, 2)` pixels (the release's y flip).
#[pyfunction]
fn project<'py>(
    py: Python<'py>,
    verts: PyReadonlyArray2<'py, f64>,
    r_t: PyReadonlyArray2<'py, f64>,
    width: u32,
    height: u32,
) -> PyResult<Bound<'py, PyAny>> {
    let (v, m) = (verts.as_array(), r_t.as_array());
    if v.ncols() != 3 || m.shape() != [4, 4] {
        return Err(DataError::new_err(format!(
            "verts must be (N, 3) and R_t 4x4; got {:?} and {:?}",
            v.shape(),
            m.shape()
        )));
    }
    let mut rt = [0f64; 16];
    for (k, x) in m.iter().enumerate() {
        rt[k] = *x;
    }
    let points: Vec<Point3<f64>> = v
        .rows()
        .into_iter()
        .map(|r| Point3::new(r[0], r[1], r[2]))
        .collect();
    let n = points.len();
    let out = run(py, || {
        let pose = Pose::from_release_rt(&rt)?;
        let camera = Camera::new(Camera::release_projection(), width, height)?;
        Ok(camera
            .project_all(&pose, &points)
            .iter()
            .flat_map(|p| [p.u, p.v])
            .collect::<Vec<f64>>())
    })?;
    Ok(out.into_pyarray(py).reshape([n, 2])?.into_any())
}

/// One prediction from Python: `(subject_id, facial_action, img_id, R_t or None)`.
type PredictionRow = (String, String, String, Option<Vec<f64>>);

/// The paper's metrics of `predictions` (`(subject_id, facial_action, img_id, R_t as 16
/// numbers or None)` rows, or a Parquet/CSV file's path) on `dir`: `eval --json`'s
/// output as JSON text.
#[pyfunction]
#[pyo3(signature = (dir, predictions=None, predictions_path=None, split=None))]
fn evaluate(
    py: Python<'_>,
    dir: PathBuf,
    predictions: Option<Vec<PredictionRow>>,
    predictions_path: Option<PathBuf>,
    split: Option<String>,
) -> PyResult<String> {
    run(py, || {
        let rows = match (predictions, predictions_path) {
            (Some(rows), None) => rows
                .into_iter()
                .enumerate()
                .map(|(i, (s, a, id, rt))| {
                    Ok(arkit_core::PredictionRecord {
                        key: SampleKey {
                            subject_id: s,
                            facial_action: a,
                            img_id: id,
                        },
                        rt: arkit_core::rt_of(rt.as_deref(), Path::new("predictions"), i)?,
                        verts: None,
                        mask_rle: None,
                    })
                })
                .collect::<arkit_core::Result<Vec<_>>>()?,
            (None, Some(path)) => arkit_data::store::read_predictions(&path)?,
            _ => {
                return Err(Error::invalid(
                    "predictions",
                    "give either rows or a file's path",
                ));
            }
        };
        let options = arkit_data::eval::EvalOptions {
            split,
            keep_worst: 0,
            ..Default::default()
        };
        let ev = arkit_data::eval::evaluate(&dir, &rows, &options)?;
        let p = &ev.problems;
        Ok(serde_json::json!({
            "summary": ev.summary,
            "problems": {
                "unknown": p.unknown.len(),
                "duplicates": p.duplicates.len(),
                "missing": p.missing,
                "non_rotations": p.non_rotations.len(),
            },
        })
        .to_string())
    })
}

/// The folder `arkit-tool crops` writes the store of dataset `dir` to for `compat` and
/// crop side `img_size` (where `ARKitFaceDataset(crop_store="auto")` looks).
#[pyfunction]
fn default_crop_store(dir: PathBuf, compat: &str, img_size: u32) -> PyResult<PathBuf> {
    Ok(FaceLoader::default_crop_store(
        &dir,
        RuleSet::parse(compat).map_err(py_err)?,
        img_size,
    ))
}

/// An image file decoded as the loader decodes it (`arkit_data::picture::read_rgb8_checked`: PNG,
/// JPEG or WebP, its size checked from the header against the limits before decoding, 16-bit
/// scaled to 8): `(H, W, 3)` uint8 RGB.
#[pyfunction]
fn read_image<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyAny>> {
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

/// A photo as people see it (`arkit_data::picture::read_photo_upright`): decoded as
/// `read_image` decodes it, then turned upright by its EXIF orientation. `(H, W, 3)`
/// uint8 RGB of the upright photo.
#[pyfunction]
fn read_photo_upright<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyAny>> {
    let (img, _) = run(py, || arkit_data::picture::read_photo_upright(&path))?;
    let (w, h) = img.dimensions();
    Ok(img
        .into_raw()
        .into_pyarray(py)
        .reshape([h as usize, w as usize, 3])?
        .into_any())
}

/// A photo made ready for the network as the official `demo.py` makes it
/// (`arkit_data::picture::demo_crop`): padded with black to a square, resized to `side`
/// (`cv2.resize`, bilinear), and the crop of `box` (`[x0, y0, x1, y1]` in the photo's
/// pixels; finite, `x0 < x1`, `y0 < y1`, overlapping the photo) by the 0.75 rule through
/// `cv2.warpAffine`. Returns a dict: `square` (side x
/// side x 3 uint8), `crop` (size x size x 3 uint8), `input` (the crop as the network
/// takes it: 3 x size x size float32, ImageNet-normalised exactly as `predict` does),
/// `pad_left`, `pad_top`, `scale` and `box_square` (the box in the square's pixels).
#[pyfunction]
#[pyo3(signature = (photo, r#box, size=192, side=800))]
fn photo_crop<'py>(
    py: Python<'py>,
    photo: numpy::PyReadonlyArray3<'py, u8>,
    r#box: [f64; 4],
    size: u32,
    side: u32,
) -> PyResult<Bound<'py, PyDict>> {
    use arkit_data::picture::{DemoSquare, demo_crop};
    let shape = photo.shape().to_vec();
    let limit = arkit_core::limits::MAX_IMAGE_SIDE as usize;
    if shape[2] != 3
        || !(1..=limit).contains(&shape[0])
        || !(1..=limit).contains(&shape[1])
        || !(2..=arkit_core::limits::MAX_CROP_SIZE).contains(&size)
        || !(1..=8192).contains(&side)
    {
        return Err(DataError::new_err(format!(
            "photo_crop: photo {shape:?}, size {size}, side {side}: expected (H, W, 3) \
             uint8 with H and W in 1..={limit}, size in 2..=4096, side in 1..=8192"
        )));
    }
    let raw: Vec<u8> = photo.as_array().iter().copied().collect();
    let (h, w) = (shape[0] as u32, shape[1] as u32);
    let (square, crop, frame, b) = run(py, || {
        arkit_data::pose::check_box(r#box, w, h)?;
        let img = image::RgbImage::from_raw(w, h, raw).expect("size matches");
        let frame = DemoSquare::of(w, h, side);
        let square = frame.image(&img);
        let b = frame.box_to_square(r#box);
        let crop = demo_crop(b, size)?.crop_image(&square);
        Ok::<_, Error>((square, crop, frame, b))
    })?;
    let d = PyDict::new(py);
    let side = side as usize;
    d.set_item(
        "square",
        square
            .into_raw()
            .into_pyarray(py)
            .reshape([side, side, 3])?,
    )?;
    let size = size as usize;
    let input = arkit_data::loader::normalise(crop.as_raw());
    d.set_item("input", input.into_pyarray(py).reshape([3, size, size])?)?;
    d.set_item(
        "crop",
        crop.into_raw().into_pyarray(py).reshape([size, size, 3])?,
    )?;
    d.set_item("pad_left", frame.pad_left)?;
    d.set_item("pad_top", frame.pad_top)?;
    d.set_item("scale", frame.scale())?;
    d.set_item("box_square", b.to_vec())?;
    Ok(d)
}

/// The pose of a face of a `width` x `height` photo from the network's correspondences
/// in the crop of `box` (as [`photo_crop`] cuts it at `size`): `pixels` (M flat crop
/// indices `y * size + x`) and `points` (M x 3 canonical metres), by our PnP (P3P + MSAC
/// RANSAC from `seed`, then Levenberg-Marquardt) in the official demo's camera, or the
/// photo's own with `focal_px`. `None` when PnP fails; else a dict: `R_t` (4 x 4, the
/// release's convention), `inliers`, `points` (distinct pixels used).
#[pyfunction]
#[pyo3(signature = (width, height, r#box, size, pixels, points, focal_px=None, threshold_px=8.0, seed=0))]
#[allow(clippy::too_many_arguments)]
fn photo_pose<'py>(
    py: Python<'py>,
    width: u32,
    height: u32,
    r#box: [f64; 4],
    size: u32,
    pixels: PyReadonlyArray1<'py, i64>,
    points: PyReadonlyArray2<'py, f32>,
    focal_px: Option<f64>,
    threshold_px: f64,
    seed: u64,
) -> PyResult<Option<Bound<'py, PyDict>>> {
    use arkit_data::picture::{DEMO_SIDE, DemoSquare, demo_crop};
    use arkit_data::pose::{PhotoCamera, face_pose};
    let limit = arkit_core::limits::MAX_IMAGE_SIDE;
    if !(1..=limit).contains(&width)
        || !(1..=limit).contains(&height)
        || !(2..=arkit_core::limits::MAX_CROP_SIZE).contains(&size)
    {
        return Err(DataError::new_err(format!(
            "photo_pose: photo {width}x{height}, crop {size}: sides in 1..={limit}, crop in 2..=4096"
        )));
    }
    let pts = points.as_array();
    if pts.ncols() != 3 {
        return Err(DataError::new_err(format!(
            "photo_pose: points must be (M, 3), got {:?}",
            pts.shape()
        )));
    }
    let n = size as i64 * size as i64;
    let px: Vec<u32> = pixels
        .as_array()
        .iter()
        .map(|&p| {
            if (0..n).contains(&p) {
                Ok(p as u32)
            } else {
                Err(DataError::new_err(format!(
                    "photo_pose: pixel index {p} outside the {size}x{size} crop"
                )))
            }
        })
        .collect::<PyResult<_>>()?;
    let p3: Vec<[f32; 3]> = pts.rows().into_iter().map(|r| [r[0], r[1], r[2]]).collect();
    let camera = focal_px.map_or(PhotoCamera::Demo, PhotoCamera::FocalPx);
    let ransac = arkit_data::pose::RansacParams {
        reprojection_threshold_px: threshold_px,
        seed,
        ..Default::default()
    };
    let found = run(py, || {
        arkit_data::pose::check_box(r#box, width, height)?;
        let square = DemoSquare::of(width, height, DEMO_SIDE);
        let crop = demo_crop(square.box_to_square(r#box), size)?;
        face_pose(&square, &crop, &camera, &px, &p3, &ransac)
    })?;
    let Some(f) = found else {
        return Ok(None);
    };
    let d = PyDict::new(py);
    d.set_item(
        "R_t",
        f.pose
            .to_release_rt()
            .to_vec()
            .into_pyarray(py)
            .reshape([4, 4])?,
    )?;
    d.set_item("inliers", f.inliers)?;
    d.set_item("points", f.points)?;
    Ok(Some(d))
}

/// The faces SeetaFace's frontal detector (embedded; docs/photos.md) finds in a photo
/// (H x W x 3 uint8): a list of `(box, score)`, boxes `[x0, y0, x1, y1]` in the photo's
/// pixels, left to right; empty when there is none.
#[pyfunction]
#[pyo3(signature = (photo, min_face_px=40, score_threshold=2.0))]
#[allow(clippy::type_complexity)]
fn detect_faces(
    py: Python<'_>,
    photo: numpy::PyReadonlyArray3<'_, u8>,
    min_face_px: u32,
    score_threshold: f64,
) -> PyResult<Vec<([f64; 4], f64)>> {
    let shape = photo.shape().to_vec();
    let limit = arkit_core::limits::MAX_IMAGE_SIDE as usize;
    if shape[2] != 3 || !(1..=limit).contains(&shape[0]) || !(1..=limit).contains(&shape[1]) {
        return Err(DataError::new_err(format!(
            "detect_faces: photo {shape:?}: expected (H, W, 3) uint8 with H and W in 1..={limit}"
        )));
    }
    let raw: Vec<u8> = photo.as_array().iter().copied().collect();
    let (h, w) = (shape[0] as u32, shape[1] as u32);
    let options = arkit_data::picture::DetectOptions {
        min_face_px,
        score_threshold,
    };
    let faces = run(py, || {
        let img = image::RgbImage::from_raw(w, h, raw).expect("size matches");
        arkit_data::picture::detect_faces(&img, &options)
    })?;
    Ok(faces.iter().map(|f| (f.bbox, f.score)).collect())
}

/// The face topology a converted dataset was converted with (see [`topology_for`]):
/// `triangles` (T x 3 uint32), `landmarks` (68 uint32 vertex ids), `uv` (V x 2 float32),
/// `vertex_count` and `source`.
#[pyfunction]
#[pyo3(signature = (dir, resources=None))]
fn topology<'py>(
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

/// Writes the dense correspondence matrices of `ids` (..., n, 3) int64 and `weights`
/// (..., n, 3) float32 into `out` (..., n, V) float32, C-contiguous and writeable: zeros
/// but for each row's weights at its vertex columns, the later of a repeated vertex's
/// weights staying, as the official loader assigns them, without the GIL. With
/// `previous_ids` (the ids `out` was last written with, and the caller's promise that
/// nothing else has written it since) only those columns are cleared before the new
/// weights go in; otherwise every value is written. A vertex id outside `0..V` or
/// shapes that do not fit raise `DataError` before anything is written.
#[pyfunction]
#[pyo3(signature = (out, ids, weights, previous_ids=None))]
fn write_correspondence_matrix_into<'py>(
    py: Python<'py>,
    out: Bound<'py, PyArrayDyn<f32>>,
    ids: numpy::PyReadonlyArrayDyn<'py, i64>,
    weights: numpy::PyReadonlyArrayDyn<'py, f32>,
    previous_ids: Option<numpy::PyReadonlyArrayDyn<'py, i64>>,
) -> PyResult<()> {
    let (shape, id_shape) = (out.shape().to_vec(), ids.shape().to_vec());
    let writeable: bool = out.getattr("flags")?.getattr("writeable")?.extract()?;
    let fits = !shape.is_empty()
        && id_shape.len() == shape.len()
        && id_shape.last() == Some(&3)
        && id_shape[..id_shape.len() - 1] == shape[..shape.len() - 1]
        && weights.shape() == id_shape.as_slice()
        && previous_ids
            .as_ref()
            .is_none_or(|p| p.shape() == id_shape.as_slice());
    if !fits || !out.is_c_contiguous() || !writeable {
        return Err(DataError::new_err(format!(
            "correspondence matrix: out {shape:?}, ids {id_shape:?}, weights {:?}, previous \
             ids {:?}: expected (..., n, V) C-contiguous writeable float32 and (..., n, 3)",
            weights.shape(),
            previous_ids.as_ref().map(|p| p.shape().to_vec())
        )));
    }
    let v = shape[shape.len() - 1];
    let triples = |ids: &numpy::PyReadonlyArrayDyn<'py, i64>, what: &str| {
        let mut out = Vec::with_capacity(ids.len() / 3);
        let mut row = [0u32; 3];
        for (i, &x) in ids.as_array().iter().enumerate() {
            if x < 0 || x as usize >= v {
                return Err(DataError::new_err(format!(
                    "correspondence matrix: row {}: {what}vertex id {x} outside 0..{v}",
                    i / 3
                )));
            }
            row[i % 3] = x as u32;
            if i % 3 == 2 {
                out.push(row);
            }
        }
        Ok(out)
    };
    let vertices = triples(&ids, "")?;
    let previous = previous_ids
        .as_ref()
        .map(|p| triples(p, "previous "))
        .transpose()?;
    let mut w = Vec::with_capacity(vertices.len());
    let mut row = [0f32; 3];
    for (i, &x) in weights.as_array().iter().enumerate() {
        row[i % 3] = x;
        if i % 3 == 2 {
            w.push(row);
        }
    }
    // SAFETY: `out` was checked C-contiguous and writeable; nothing else writes it while
    // the GIL is released (the caller owns it: a buffer it made for this matrix).
    let slice = unsafe { out.as_slice_mut()? };
    py.detach(|| match &previous {
        Some(previous) => rewrite_correspondence_matrix(slice, v, previous, &vertices, &w),
        None => write_correspondence_matrix(slice, v, &vertices, &w),
    });
    Ok(())
}

/// The rows of `a` (N, K) float64, or `DataError` naming `name` when it has not K columns.
fn fixed_rows<const K: usize>(
    a: &PyReadonlyArray2<'_, f64>,
    name: &str,
) -> PyResult<Vec<[f64; K]>> {
    let v = a.as_array();
    if v.ncols() != K {
        return Err(DataError::new_err(format!(
            "{name}: shape {:?}; expected (N, {K})",
            v.shape()
        )));
    }
    Ok(v.rows()
        .into_iter()
        .map(|r| std::array::from_fn(|k| r[k]))
        .collect())
}

/// Pairs the rows of two inputs, one of which may have a single row that goes with
/// every row of the other.
fn paired<A: Copy, B: Copy>(a: &[A], b: &[B], names: (&str, &str)) -> PyResult<Vec<(A, B)>> {
    match (a.len(), b.len()) {
        (n, m) if n == m => Ok(a.iter().copied().zip(b.iter().copied()).collect()),
        (_, 1) => Ok(a.iter().map(|&x| (x, b[0])).collect()),
        (1, _) => Ok(b.iter().map(|&y| (a[0], y)).collect()),
        (n, m) => Err(DataError::new_err(format!(
            "{} and {}: {n} and {m} rows; expected as many of each, or one of either",
            names.0, names.1
        ))),
    }
}

/// `f` of every item, without the GIL, as an (N, K) float64 array; an error of item
/// `i` of several names it (`pose i: ...`).
fn convert_each<'py, T: Send + Sync, const K: usize>(
    py: Python<'py>,
    items: Vec<T>,
    f: impl Fn(&T) -> arkit_core::Result<[f64; K]> + Send + Sync,
) -> PyResult<Bound<'py, PyAny>> {
    let n = items.len();
    let out = run(py, || {
        let mut out = Vec::with_capacity(n * K);
        for (i, item) in items.iter().enumerate() {
            let row = f(item).map_err(|e| {
                if n > 1 {
                    Error::invalid(format!("pose {i}"), e.reason())
                } else {
                    e
                }
            })?;
            out.extend_from_slice(&row);
        }
        Ok(out)
    })?;
    Ok(out.into_pyarray(py).reshape([n, K])?.into_any())
}

/// A 4x4 matrix from its 16 values row by row (math layout, `x' = M x`).
fn matrix_rows(m: &[f64; 16]) -> nalgebra::Matrix4<f64> {
    nalgebra::Matrix4::from_row_slice(m)
}

/// The 16 values of `m`, row by row.
fn matrix_values(m: &nalgebra::Matrix4<f64>) -> [f64; 16] {
    std::array::from_fn(|k| m[(k / 4, k % 4)])
}

/// OpenCV's `[rvec, tvec]` (N, 6) of release `R_t`s given as (N, 16) rows (each
/// `R_t` row by row; any rigid `R_t`, the face in front of the camera or not).
#[pyfunction]
fn poses_to_opencv<'py>(
    py: Python<'py>,
    r_t: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    convert_each(py, fixed_rows::<16>(&r_t, "R_t")?, |rt| {
        let (r, t) = Pose::from_rigid_rt(rt)?.to_opencv_rvec();
        Ok([r.x, r.y, r.z, t.x, t.y, t.z])
    })
}

/// Release `R_t`s (N, 16) of OpenCV's `[rvec, tvec]` rows (N, 6).
#[pyfunction]
fn poses_from_opencv<'py>(
    py: Python<'py>,
    rvec_tvec: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    convert_each(py, fixed_rows::<6>(&rvec_tvec, "rvec, tvec")?, |v| {
        finite(v, "rvec, tvec")?;
        let pose = Pose::from_opencv_rvec(
            &nalgebra::Vector3::new(v[0], v[1], v[2]),
            &nalgebra::Vector3::new(v[3], v[4], v[5]),
        );
        Ok(pose.to_release_rt())
    })
}

/// Release `R_t`s (N, 16) of ARKit's face anchor transforms seen from camera
/// transforms (each 4x4 in column form, `x_world = M x`, its 16 values row by row;
/// either input may have one row for all).
#[pyfunction]
fn poses_from_arkit<'py>(
    py: Python<'py>,
    face_anchor: PyReadonlyArray2<'py, f64>,
    camera: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    let a = fixed_rows::<16>(&face_anchor, "face_anchor_transform")?;
    let c = fixed_rows::<16>(&camera, "camera_transform")?;
    let pairs = paired(&a, &c, ("face_anchor_transform", "camera_transform"))?;
    convert_each(py, pairs, |(a, c)| {
        Ok(Pose::from_arkit(&matrix_rows(a), &matrix_rows(c))?.to_release_rt())
    })
}

/// ARKit's face anchor transforms (N, 16, column form row by row) of release `R_t`s
/// (N, 16) seen from camera transforms (N or 1, 16).
#[pyfunction]
fn poses_to_arkit<'py>(
    py: Python<'py>,
    r_t: PyReadonlyArray2<'py, f64>,
    camera: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    let p = fixed_rows::<16>(&r_t, "R_t")?;
    let c = fixed_rows::<16>(&camera, "camera_transform")?;
    let pairs = paired(&p, &c, ("R_t", "camera_transform"))?;
    convert_each(py, pairs, |(rt, c)| {
        let anchor = Pose::from_rigid_rt(rt)?.to_arkit(&matrix_rows(c))?;
        Ok(matrix_values(&anchor))
    })
}

/// The Euler angles (N, 3) of release `R_t`s (N, 16) in `convention` (`official`,
/// `wcpa`, `trg`, `6drepnet`, `img2pose`): that tool's order and unit.
#[pyfunction]
fn pose_angles<'py>(
    py: Python<'py>,
    r_t: PyReadonlyArray2<'py, f64>,
    convention: &str,
) -> PyResult<Bound<'py, PyAny>> {
    let c: AngleConvention = convention.parse().map_err(py_err)?;
    convert_each(py, fixed_rows::<16>(&r_t, "R_t")?, |rt| {
        Ok(c.angles(&Pose::from_rigid_rt(rt)?))
    })
}

/// Release `R_t`s (N, 16) of Euler angles (N or 1, 3) in `convention` and the
/// release's translations `R_t[3,:3]` (N or 1, 3).
#[pyfunction]
fn poses_from_angles<'py>(
    py: Python<'py>,
    angles: PyReadonlyArray2<'py, f64>,
    translation: PyReadonlyArray2<'py, f64>,
    convention: &str,
) -> PyResult<Bound<'py, PyAny>> {
    let c: AngleConvention = convention.parse().map_err(py_err)?;
    let a = fixed_rows::<3>(&angles, "angles")?;
    let t = fixed_rows::<3>(&translation, "translation")?;
    let pairs = paired(&a, &t, ("angles", "translation"))?;
    convert_each(py, pairs, |(a, t)| {
        finite(a, "angles")?;
        finite(t, "translation")?;
        Ok(c.from_angles(*a, nalgebra::Vector3::from(*t))
            .to_release_rt())
    })
}

/// TRG's row-vector `R_t`s (N, 16: `[[R'^T, 0], [t'^T, 1]]`, `R' = F R F`, `t' = F t`)
/// of release `R_t`s (N, 16).
#[pyfunction]
fn poses_to_trg<'py>(
    py: Python<'py>,
    r_t: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    convert_each(py, fixed_rows::<16>(&r_t, "R_t")?, |rt| {
        let (r, t) = Pose::from_rigid_rt(rt)?.to_trg();
        Ok(Pose::new(r, t).to_release_rt())
    })
}

/// Release `R_t`s (N, 16) of TRG's row-vector `R_t`s (N, 16).
#[pyfunction]
fn poses_from_trg<'py>(
    py: Python<'py>,
    r_t: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    convert_each(py, fixed_rows::<16>(&r_t, "TRG R_t")?, |rt| {
        let trg = Pose::from_rigid_rt(rt)?;
        Ok(Pose::from_trg(&trg.rotation(), &trg.translation_m()).to_release_rt())
    })
}

/// img2pose's `[rvec, t]` 6-vectors (N, 6) of release `R_t`s (N, 16).
#[pyfunction]
fn poses_to_img2pose<'py>(
    py: Python<'py>,
    r_t: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    convert_each(py, fixed_rows::<16>(&r_t, "R_t")?, |rt| {
        Ok(Pose::from_rigid_rt(rt)?.to_img2pose())
    })
}

/// Release `R_t`s (N, 16) of img2pose's `[rvec, t]` 6-vectors (N, 6).
#[pyfunction]
fn poses_from_img2pose<'py>(
    py: Python<'py>,
    dof: PyReadonlyArray2<'py, f64>,
) -> PyResult<Bound<'py, PyAny>> {
    convert_each(py, fixed_rows::<6>(&dof, "img2pose pose")?, |v| {
        finite(v, "img2pose pose")?;
        Ok(Pose::from_img2pose(v).to_release_rt())
    })
}

/// `DataError` (through `Error`) when a value of `v` is NaN or infinite.
fn finite(v: &[f64], name: &str) -> arkit_core::Result<()> {
    match v.iter().position(|x| !x.is_finite()) {
        Some(k) => Err(Error::invalid(
            name,
            format!("non-finite value {} at [{k}]", v[k]),
        )),
        None => Ok(()),
    }
}

// ---- ONNX export: the point choice (arkit_tool.onnx) ----

/// The pixels PerspNet reads, chosen from a predicted mask as `predict --model` chooses
/// them (`arkit_perspnet::predict_crop_raw`): the candidates are the mask's pixels in
/// flat order (every pixel when the mask is empty), and
/// `arkit_data::render::sample_points(len(candidates), m, seed)` picks `m` of
/// them (distinct, increasing, when there are more than `m`; else with wrap-around).
/// `mask`: bool, any shape, read in C order. Returns the `m` flat indices (int64).
#[pyfunction]
fn choose_points<'py>(
    py: Python<'py>,
    mask: numpy::PyReadonlyArrayDyn<'py, bool>,
    m: usize,
    seed: u64,
) -> PyResult<Bound<'py, numpy::PyArray1<i64>>> {
    if m == 0 || m > 1 << 20 {
        return Err(py_err(Error::invalid(
            "m",
            format!("{m} points: must be in 1..=1048576"),
        )));
    }
    let flat: Vec<bool> = mask.as_array().iter().copied().collect();
    if flat.is_empty() || flat.len() > u32::MAX as usize {
        return Err(py_err(Error::invalid(
            "mask",
            format!("{} pixels: must be in 1..=4294967295", flat.len()),
        )));
    }
    let chosen = py.detach(|| {
        let mut candidates: Vec<u32> = (0..flat.len() as u32)
            .filter(|&i| flat[i as usize])
            .collect();
        if candidates.is_empty() {
            candidates = (0..flat.len() as u32).collect();
        }
        arkit_data::render::sample_points(candidates.len(), m, seed)
            .into_iter()
            .map(|k| candidates[k as usize] as i64)
            .collect::<Vec<i64>>()
    });
    Ok(chosen.into_pyarray(py))
}

// ---- end of the ONNX block ----

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Loader>()?;
    m.add_class::<Dataset>()?;
    m.add_function(wrap_pyfunction!(solve_pnp_ransac, m)?)?;
    m.add_function(wrap_pyfunction!(project, m)?)?;
    m.add_function(wrap_pyfunction!(evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(read_image, m)?)?;
    m.add_function(wrap_pyfunction!(read_photo_upright, m)?)?;
    m.add_function(wrap_pyfunction!(photo_crop, m)?)?;
    m.add_function(wrap_pyfunction!(photo_pose, m)?)?;
    m.add_function(wrap_pyfunction!(detect_faces, m)?)?;
    m.add_function(wrap_pyfunction!(default_crop_store, m)?)?;
    m.add_function(wrap_pyfunction!(topology, m)?)?;
    m.add_function(wrap_pyfunction!(write_correspondence_matrix_into, m)?)?;
    m.add_function(wrap_pyfunction!(poses_to_opencv, m)?)?;
    m.add_function(wrap_pyfunction!(poses_from_opencv, m)?)?;
    m.add_function(wrap_pyfunction!(poses_from_arkit, m)?)?;
    m.add_function(wrap_pyfunction!(poses_to_arkit, m)?)?;
    m.add_function(wrap_pyfunction!(pose_angles, m)?)?;
    m.add_function(wrap_pyfunction!(poses_from_angles, m)?)?;
    m.add_function(wrap_pyfunction!(poses_to_trg, m)?)?;
    m.add_function(wrap_pyfunction!(poses_from_trg, m)?)?;
    m.add_function(wrap_pyfunction!(poses_to_img2pose, m)?)?;
    m.add_function(wrap_pyfunction!(poses_from_img2pose, m)?)?;
    m.add_function(wrap_pyfunction!(choose_points, m)?)?; // ONNX block
    m.add("DataError", m.py().get_type::<DataError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
