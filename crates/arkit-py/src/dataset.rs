//! `arkit_tool.ARKitFaceDataset` (`_dataset.py`): `Loader`, one sample after another, or
//! a batch, as the official PyTorch loader returns them, in numpy arrays that own the
//! Rust buffers (or the caller's arrays, reused); and where the crop store of a dataset
//! is by default (`default_crop_store`).

use crate::converted::topology_for;
use crate::errors::{DataError, py_err, run};
use arkit_core::{Error, SampleKey};
use arkit_data::crop::RuleSet;
use arkit_data::loader::{
    FaceLoader, LoaderItem, LoaderMode, LoaderOptions, write_correspondence_matrix,
};
use numpy::{IntoPyArray, PyArrayDyn, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::{Path, PathBuf};

/// One sample after another as the official loader returns them.
#[pyclass(module = "arkit_tool._native", frozen)]
pub(crate) struct Loader {
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

/// The folder `arkit-tool crops` writes the store of dataset `dir` to for `compat` and
/// crop side `img_size` (where `ARKitFaceDataset(crop_store="auto")` looks).
#[pyfunction]
pub(crate) fn default_crop_store(dir: PathBuf, compat: &str, img_size: u32) -> PyResult<PathBuf> {
    Ok(FaceLoader::default_crop_store(
        &dir,
        RuleSet::parse(compat).map_err(py_err)?,
        img_size,
    ))
}
