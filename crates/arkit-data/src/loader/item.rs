//! `loader`: one training sample as the official PyTorch loader returns it, computed on
//! the fly from a converted dataset: what the Python package's `ARKitFaceDataset`
//! serves.
//!
//! The official `ARKitDataset.get_item` (`data/arkit_dataset.py` of the official code)
//! returns, per sample: `img` (the `S x S` crop, `ToTensor` + ImageNet `Normalize`,
//! channels first), `choose` (`n_pts` crop pixel indices), `model` (the mesh, 1220 x 3),
//! `uvmap` (3 x S x S, the UV position map in [-1, 1]), `nocs` (the points' canonical
//! positions times 4.5), `mask` (S x S, 0/1), `corr_mat` (n_pts x 1220: each point's
//! triangle's three vertex weights) and, in evaluation, `tform_inv` (crop pixel to image,
//! 2 x 3) and `R_t`. [`FaceLoader::item`] computes them for one sample; the vertex ids
//! and weights are kept sparse ([`LoaderItem::corr_vertices`]), the dense matrix is the
//! caller's choice.
//!
//! Two rule sets ([`RuleSet`]):
//! - [`RuleSet::Official`]: every value by the official loader's rules: its integer box
//!   ([`crate::crop::official::official_box`]: `int()` of the landmarks' box edges), the
//!   `cv2` affine map and `cv2.warpAffine` resampling ([`crate::crop::official`]), its rasterizer over the whole
//!   image (screen-space weights; held only over the window the face can cover,
//!   `FaceRenderer::render_window_mask`, the rest being no face), its point choice (face pixels of the full-resolution
//!   mask sliced `mask[top:bottom+1, left:right+1]` with Python's slice rules, drawn
//!   without repetition or repeated cyclically, mapped to crop pixels by the affine map
//!   and `floor`), its UV map (the UV triangles drawn at `uv * (S - 1)`, the ring at 1.1
//!   times the contour in the `4.5 v + 0.5` space, `OfficialUvLayout`).
//! - [`RuleSet::Exact`]: ours, as `render` stores them: the square box at pixel centres,
//!   our bilinear crop, our rasterizer at crop resolution (perspective-correct weights),
//!   points drawn from the crop mask, our UV map (texel centres, `--uv-size` = `S`).
//!
//! Training mode ([`LoaderMode::Train`]) adds the official online augmentation: the box
//! centre moved by up to 0.15 of the landmarks' box size in x and y, its half-side scaled
//! by 0.95-1.05, then a colour jitter with torchvision's `ColorJitter(0.3, 0.3, 0.2,
//! 0.01)` ranges ([`jitter_colour`]). Every random draw comes from [`Rng::for_stream`] of
//! `(seed, epoch, index)`, so an item is the same whichever worker process computes it.
//!
//! Where the official loader fails (its box leaves the image's top or left edge, the
//! slice of a negative index is empty and `np.pad` raises; its `__getitem__` then trains
//! on a random other sample), [`FaceLoader::item`] returns an error saying so in
//! evaluation mode; in training mode the box jitter is drawn again (up to
//! `JITTER_DRAWS` times, then the box without jitter) so a usable box is never replaced
//! by another sample.
//!
//! Tested in `tests/loader.rs` (every field against the library's render path and
//! values derived by hand, determinism across calls, the official slice rule) and by the
//! Python package's tests against a numpy re-implementation of the official formulas.

use crate::crop::official::{
    LandmarkExtent, affine_transform, box_crop, official_box, warp_mask_in,
};
use crate::crop::rules::{MaskRule, UvLayout};
use crate::crop::{CropTransform, RuleSet};
use crate::lanes;
use crate::lanes::jitter::UNIT;
use crate::loader::colour_jitter::jitter_colour;
use crate::loader::official_uv::{OfficialUvLayout, official_organ_triangles};
use crate::mesh::topology::FaceTopology;
use crate::render::face::{FaceRenderer, WindowMask, sample_points};
use crate::render::uv_map::{UvMapper, UvTexels};
use crate::store::crop_store::{CropStore, StoredCrop, StoredRecord, WindowPart};
use crate::store::dataset::Dataset;
use crate::store::face_targets::{canonical_position, mask_pixel_indices};
use arkit_core::Rng;
use arkit_core::SampleKey;
use arkit_core::VisibilityBuffer;
use arkit_core::conventions::{Camera, Pose};
use arkit_core::{Error, Result};
use nalgebra::Point3;
use std::path::{Path, PathBuf};

mod exact_item;
mod official_item;

/// Training (random box jitter and colour jitter) or evaluation (neither).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LoaderMode {
    /// The official training transform.
    Train,
    /// The official test transform.
    Eval,
}

impl LoaderMode {
    /// `"train"` or `"eval"`.
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "train" => Ok(LoaderMode::Train),
            "eval" => Ok(LoaderMode::Eval),
            _ => Err(Error::invalid(
                "mode",
                format!("'{s}': expected 'train' or 'eval'"),
            )),
        }
    }
}

/// What [`FaceLoader::open`] takes.
#[derive(Clone, Debug)]
pub struct LoaderOptions {
    /// The split to serve (`"train"`, `"test"`, ...), or `None` for every sample. The
    /// split of `split` when the dataset has a `splits.json`, else the listed split.
    pub split: Option<String>,
    /// Training or evaluation.
    pub mode: LoaderMode,
    /// Whose rules (`--compat`, Python's `compat=`).
    pub rules: RuleSet,
    /// Crop side `S` (the official 192), 16..=1024.
    pub img_size: u32,
    /// Points per sample (the official 1024), 1..=65536.
    pub n_pts: usize,
    /// Seed of every random draw.
    pub seed: u64,
}

impl LoaderOptions {
    /// Checks the ranges.
    pub fn validate(&self) -> Result<()> {
        if !(16..=1024).contains(&self.img_size) {
            return Err(Error::invalid(
                "img_size",
                format!("{}: must be 16..=1024", self.img_size),
            ));
        }
        if !(1..=65536).contains(&self.n_pts) {
            return Err(Error::invalid(
                "n_pts",
                format!("{}: must be 1..=65536", self.n_pts),
            ));
        }
        Ok(())
    }
}

/// How often a training box jitter is drawn again when the official box fails.
pub(crate) const JITTER_DRAWS: usize = 10;

/// ImageNet channel means (RGB), the official `Normalize`'s (and the network's input).
pub const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
/// ImageNet channel standard deviations (RGB), see [`IMAGENET_MEAN`].
pub const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// One sample as the official loader returns it (see the module docs). Arrays are
/// row-major and channels first where the official tensors are.
#[derive(Clone, Debug, PartialEq)]
pub struct LoaderItem {
    /// The sample's key.
    pub key: SampleKey,
    /// The image file (absolute), or the dataset folder for an embedded image.
    pub image_path: PathBuf,
    /// `3 x S x S`, normalised (empty from [`FaceLoader::item_into`], which writes it
    /// into the caller's plane).
    pub img: Vec<f32>,
    /// `n_pts` crop pixel indices (`row * S + col`).
    pub choose: Vec<i64>,
    /// The mesh, `1220 x 3` (metres, canonical frame).
    pub model: Vec<f32>,
    /// `3 x S x S` in [-1, 1] (`-1` where no UV triangle covers the texel; empty from
    /// [`FaceLoader::item_into`], which writes it into the caller's plane, and in the
    /// items `train` builds from stored targets, whose loss takes no UV map).
    pub uvmap: Vec<f32>,
    /// `n_pts x 3`: each point's canonical position times 4.5.
    pub nocs: Vec<f32>,
    /// `S x S` crop face mask.
    pub mask: Vec<u8>,
    /// `n_pts`: the three vertex ids of each point's triangle.
    pub corr_vertices: Vec<[u32; 3]>,
    /// `n_pts`: their weights (sum 1).
    pub corr_weights: Vec<[f32; 3]>,
    /// Crop pixel `(col, row)` to image point: `[a, b, c, d, e, f]`, `u = a col + b row +
    /// c`, `v = d col + e row + f` (the official `tform_inv`).
    pub tform_inv: [f64; 6],
    /// `R_t`, row-major.
    pub rt: [f64; 16],
    /// The crop.
    pub crop: CropTransform,
    /// [`RuleSet::Official`] only: the integer box `[left, top, right, bottom]`.
    pub official_box: Option<[i64; 4]>,
    /// [`RuleSet::Official`] only: the chosen points as indices into the flattened
    /// `mask[top:bottom+1, left:right+1]` (the official `choose` before it is mapped).
    pub choose_box: Vec<i64>,
    /// [`RuleSet::Official`] only: whether the box leaves the image, so that the slice
    /// is clipped (right or bottom) or wrapped (left or top, Python's negative indices)
    /// and the official mapping of points to crop pixels misplaces them (points mapped
    /// outside the crop are then replaced by a random pixel, as the official loader does).
    pub box_clipped: bool,
}

/// Where [`FaceLoader::item_into`] writes an item's two image-sized arrays instead of
/// allocating them: slices of a caller's batch arrays, for instance, so that a batch is
/// computed in place with no copy per sample.
#[derive(Debug)]
pub struct ItemPlanes<'a> {
    /// `3 x S x S`: what [`LoaderItem::img`] would hold.
    pub img: &'a mut [f32],
    /// `3 x U x U` ([`FaceLoader::uvmap_size`]): what [`LoaderItem::uvmap`] would hold.
    pub uvmap: &'a mut [f32],
}

/// An item's image-sized arrays: in the item, or in a caller's [`ItemPlanes`].
enum Planes<'a> {
    Owned,
    Borrowed(ItemPlanes<'a>),
}

impl Planes<'_> {
    /// The normalised crop `rgb`: returned, or written into the caller's plane (then
    /// an empty vector is returned).
    fn img(&mut self, rgb: &[u8]) -> Vec<f32> {
        match self {
            Planes::Owned => normalise(rgb),
            Planes::Borrowed(p) => {
                normalise_into(rgb, p.img);
                Vec::new()
            }
        }
    }

    /// A `len`-value UV map: `fill` writes every value of it (`-1` where uncovered), in
    /// one pass; returned, or written into the caller's plane (then an empty vector is
    /// returned).
    fn uvmap(&mut self, len: usize, fill: impl FnOnce(&mut [f32])) -> Vec<f32> {
        match self {
            Planes::Owned => {
                let mut v = vec![0f32; len];
                fill(&mut v);
                v
            }
            Planes::Borrowed(p) => {
                fill(p.uvmap);
                Vec::new()
            }
        }
    }
}

/// One row of the index [`FaceLoader`] keeps per sample (the mesh is read per item).
#[derive(Clone, Debug)]
struct IndexRow {
    /// The samples table's row, without its landmarks and without its mesh unless the
    /// image is embedded (the release may then be gone).
    sample: crate::store::samples_table::SampleRecord,
    /// The split served (`split`'s assignment, else the listed one).
    split: String,
    /// The sample's `_info.npz`.
    info_path: PathBuf,
    /// Its samples shard and row there (its record in a crop store).
    location: (usize, usize),
}

/// A visibility buffer lent by a [`FaceLoader`]'s pool; returned to it when dropped.
struct KeptBuffer<'a> {
    pool: &'a std::sync::Mutex<Vec<VisibilityBuffer>>,
    buffer: VisibilityBuffer,
}

impl std::ops::Deref for KeptBuffer<'_> {
    type Target = VisibilityBuffer;
    fn deref(&self) -> &VisibilityBuffer {
        &self.buffer
    }
}

impl std::ops::DerefMut for KeptBuffer<'_> {
    fn deref_mut(&mut self) -> &mut VisibilityBuffer {
        &mut self.buffer
    }
}

impl Drop for KeptBuffer<'_> {
    fn drop(&mut self) {
        let buffer = std::mem::replace(&mut self.buffer, VisibilityBuffer::new(0, 0));
        self.pool
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(buffer);
    }
}

/// Where an item's crop pixels come from.
enum PixelSource {
    /// The decoded full-resolution image.
    Image(image::RgbImage),
    /// A crop store's record: the window around the evaluation crop, not yet decoded.
    Stored(StoredRecord),
}

impl PixelSource {
    /// The pixels of `crop` (interleaved RGB, `S x S`). From a store, an evaluation
    /// crop must be the stored box (else the store does not belong to this loader).
    fn crop(&self, crop: &CropTransform, train: bool, key: &SampleKey) -> Result<Vec<u8>> {
        match self {
            PixelSource::Image(image) => Ok(crop.crop_image(image).into_raw()),
            PixelSource::Stored(stored) => {
                if !train && *crop != stored.eval_crop {
                    return Err(Error::invalid(
                        "crop store",
                        format!(
                            "{key}: the stored box {:?} is not the evaluation box {crop:?} computed from its mesh: the store was made with other rules or another topology; run `arkit-tool crops` again",
                            stored.eval_crop
                        ),
                    ));
                }
                stored.crop_pixels(crop)
            }
        }
    }
}

/// Python's `range(len)[start:stop]` for a step of 1: the clipped, wrapped bounds.
fn python_slice(start: i64, stop: i64, len: i64) -> std::ops::Range<i64> {
    let fix = |i: i64| {
        if i < 0 { (i + len).max(0) } else { i.min(len) }
    };
    let (a, b) = (fix(start), fix(stop));
    a..b.max(a)
}

/// The official `tform_inv` of a crop ([`LoaderItem::tform_inv`]): crop pixel
/// `(col, row)` to image point by the crop's sampling rule.
pub fn tform_inv(crop: &CropTransform) -> [f64; 6] {
    let o = crop.rules.sample_offset();
    let s = crop.size as f64;
    let (sx, sy) = (crop.side / s, crop.side_y / s);
    [sx, 0.0, crop.x0 + o * sx, 0.0, sy, crop.y0 + o * sy]
}

/// `ToTensor` then `Normalize(IMAGENET_MEAN, IMAGENET_STD)` of an interleaved RGB crop:
/// channels first. Each value depends on its byte and channel only, so the formula is
/// evaluated once per byte value and channel (a 3 x 256 table) and looked up (eight
/// pixels a gather where the CPU has AVX2): the same values, without two divisions per
/// value.
pub fn normalise(rgb: &[u8]) -> Vec<f32> {
    let mut out = vec![0f32; rgb.len()];
    normalise_into(rgb, &mut out);
    out
}

/// [`normalise`] into `out` (`rgb.len()` values, channels first).
///
/// # Panics
/// When `out.len() != rgb.len()`.
fn normalise_into(rgb: &[u8], out: &mut [f32]) {
    assert_eq!(out.len(), rgb.len(), "one value per byte");
    let table: [[f32; 256]; 3] = std::array::from_fn(|k| {
        std::array::from_fn(|v| (UNIT[v] - IMAGENET_MEAN[k]) / IMAGENET_STD[k])
    });
    let n = rgb.len() / 3;
    let (r, rest) = out.split_at_mut(n);
    let (g, b) = rest.split_at_mut(n);
    // Sixteen pixels at a time where the SIMD level has AVX-512 VBMI: the same table,
    // held in registers; else eight at a time from AVX2 up, the table read by gathers.
    lanes::normalise::lookup_planes(rgb, [r, g, b], &table);
}

/// A mask's bytes (0 or 1) widened to `int64` into `out`, as a batch's `mask` holds
/// them: on x86-64 with AVX-512 eight at a time, written with streaming stores (whole
/// 64-byte lines, realigned to the plane); the rest one at a time. The same values
/// either way (tested).
///
/// # Panics
/// When `out` is not one value per byte of `mask`.
pub fn widen_mask_into(mask: &[u8], out: &mut [i64]) {
    assert_eq!(mask.len(), out.len(), "one value per mask byte");
    lanes::normalise::widen_mask(mask, out);
}

/// A converted dataset served sample by sample (see the module docs). Holds a small
/// index per sample (key, image path, size, `R_t`); the mesh is read from the sample's
/// `_info.npz` per item (checked against the table's `R_t`), as the official loader
/// reads it.
#[derive(Debug)]
pub struct FaceLoader {
    dataset: Dataset,
    rows: Vec<IndexRow>,
    renderer: FaceRenderer,
    camera_projection: nalgebra::Matrix4<f64>,
    uv_texels: UvTexels,
    uv: UvMapper,
    official_uv: OfficialUvLayout,
    options: LoaderOptions,
    /// Visibility buffers kept between items (an 800x800 buffer is 13 MB to allocate,
    /// a 192x192 crop's 0.7 MB to allocate and zero).
    buffers: std::sync::Mutex<Vec<VisibilityBuffer>>,
    /// The crop store items read their pixels and meshes from, when opened.
    store: Option<CropStore>,
    /// Records fetched ahead by [`FaceLoader::prefetch`], by sample index (at most
    /// [`PREFETCH_RECORDS`]; the oldest dropped first).
    prefetched: std::sync::Mutex<Prefetched>,
    /// Signalled when a fetch under way ends.
    prefetch_done: std::sync::Condvar,
}

/// The most records [`FaceLoader::prefetch`] holds (bounded memory: about 50 KB a
/// record at `S = 192`).
const PREFETCH_RECORDS: usize = 1024;

/// Records fetched ahead, by sample index, and the order they came in; the indices
/// whose fetch is under way (an item of one of them waits for it).
#[derive(Debug, Default)]
struct Prefetched {
    records: std::collections::HashMap<usize, StoredRecord>,
    order: std::collections::VecDeque<usize>,
    in_flight: std::collections::HashSet<usize>,
}

impl FaceLoader {
    /// Opens `dir` (what `convert` wrote) for `options`, with `topology` (the one the
    /// dataset was converted with; checked) and, for [`RuleSet::Official`], the release's
    /// UV triangles `uv_triangles` when known.
    pub fn open(
        dir: &Path,
        topology: FaceTopology,
        uv_triangles: Option<Vec<[u32; 3]>>,
        options: LoaderOptions,
    ) -> Result<Self> {
        options.validate()?;
        let dataset = Dataset::open(dir)?;
        crate::store::manifest::check_topology(dataset.manifest(), &topology)?;
        let splits = crate::store::splits::SplitLookup::read(dir)?;
        let layout = crate::ingest::discover::DiscoveredInput {
            root: dataset.image_root().to_path_buf(),
            kind: dataset.manifest().layout,
            lists: Vec::new(),
        };
        let mut rows = Vec::new();
        for shard in dataset.shards() {
            for (position, mut r) in dataset.read_samples(shard)?.into_iter().enumerate() {
                let split = splits.of(&r);
                if options.split.as_deref().is_some_and(|s| s != split) {
                    continue;
                }
                let info_path = dataset
                    .image_root()
                    .join(layout.info_relative(&r.split, &r.key));
                r.landmarks_2d = Vec::new();
                if r.jpeg.is_none() {
                    r.verts = Vec::new();
                }
                rows.push(IndexRow {
                    sample: r,
                    split,
                    info_path,
                    location: (shard.index, position),
                });
            }
        }
        let uv = UvMapper::derive(&topology)?;
        let uv_texels = uv.texels(options.img_size);
        let release_uv = uv_triangles.map(|t| {
            let mut coords = topology.uv.clone();
            coords.extend_from_slice(&topology.uv_extension);
            (t, coords)
        });
        let official_uv =
            OfficialUvLayout::new(&uv, release_uv, topology.vertex_count, options.img_size)?;
        // The official loader reads the projection matrix as float32
        // (`np.loadtxt(..., dtype=np.float32)`): its screen positions follow those values.
        let rules = options.rules.book();
        let projection = rules.projection(Camera::release_projection());
        let topology_uv = topology.uv.clone();
        let mut renderer = FaceRenderer::new(topology, projection)?.with_rules(options.rules);
        if rules.mask() == MaskRule::WarpedFromImage {
            // The holes as the official mask closes them. The layout's loops are the
            // mouth's and the two eyes'; the official list has the eyes first.
            let l = &official_uv.centroid_loops;
            if l.len() == 3 {
                let organs = official_organ_triangles([&l[1], &l[2], &l[0]], &topology_uv);
                renderer.set_hole_triangles(&organs)?;
            }
        }
        Ok(FaceLoader {
            dataset,
            rows,
            renderer,
            camera_projection: projection,
            uv_texels,
            uv,
            official_uv,
            options,
            buffers: std::sync::Mutex::new(Vec::new()),
            store: None,
            prefetched: Default::default(),
            prefetch_done: std::sync::Condvar::new(),
        })
    }

    /// Where `crops` writes the store of a dataset for these options by default:
    /// `DIR/crops/<rules>-<S>` (`exact-192`, `official-192`, ...).
    pub fn default_crop_store(dir: &Path, rules: RuleSet, img_size: u32) -> PathBuf {
        dir.join("crops")
            .join(format!("{}-{img_size}", rules.name()))
    }

    /// Reads pixels and meshes from the crop store in `dir` from now on (checked
    /// against this loader's dataset, rules, crop side and topology: see
    /// [`CropStore::open`]).
    pub fn open_crop_store(&mut self, dir: &Path) -> Result<()> {
        self.store = Some(CropStore::open(
            dir,
            &self.dataset,
            self.options.rules,
            self.options.img_size,
            self.renderer.topology().vertex_count,
        )?);
        Ok(())
    }

    /// [`FaceLoader::open_crop_store`] for a dataset opened from a bucket: the store's
    /// manifest read from `dir` (its mirror), its part files by ranged GETs from
    /// `remote` at `relative` (`crops/official-192`); see
    /// [`RemoteDataset::open_crop_store`](crate::storage::RemoteDataset::open_crop_store).
    pub fn open_remote_crop_store(
        &mut self,
        dir: &Path,
        remote: &crate::storage::RemoteDataset,
        relative: &str,
    ) -> Result<()> {
        self.store = Some(remote.open_crop_store(
            dir,
            relative,
            &self.dataset,
            self.options.rules,
            self.options.img_size,
            self.renderer.topology().vertex_count,
        )?);
        Ok(())
    }

    /// Fetches the crop-store records of samples `indices` now, concurrently when the
    /// store is in a bucket, and keeps them (at most 1,024; the oldest dropped) for the
    /// items of those samples that follow, each record used once. Nothing to do
    /// without a store or for a local one. A record that fails is not kept: its item
    /// reads it again and reports the error, naming it.
    pub fn prefetch(&self, indices: &[usize]) {
        let claimed = self.claim_prefetch(indices);
        self.fetch_claimed(claimed);
    }

    /// [`FaceLoader::prefetch`] on a thread of its own: the records are claimed (marked
    /// under way, so that the items of those samples wait for them) before this returns,
    /// and fetched by the thread. For processes that do not fork afterwards (DataLoader
    /// workers).
    pub fn prefetch_in_background(self: &std::sync::Arc<Self>, indices: &[usize]) {
        let claimed = self.claim_prefetch(indices);
        if claimed.is_empty() {
            return;
        }
        let loader = self.clone();
        std::thread::spawn(move || {
            let _ = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                loader.fetch_claimed(claimed)
            }));
        });
    }

    /// Marks the records of `indices` that are neither held nor under way as under way:
    /// their sample, location and key.
    fn claim_prefetch(&self, indices: &[usize]) -> Vec<(usize, (usize, usize), String)> {
        let Some(store) = &self.store else {
            return Vec::new();
        };
        if !store.is_remote() {
            return Vec::new();
        }
        let mut p = self.prefetched.lock().unwrap_or_else(|p| p.into_inner());
        let mut keys = Vec::new();
        for &i in indices {
            if p.records.contains_key(&i) || p.in_flight.contains(&i) {
                continue;
            }
            if let Some(r) = self.rows.get(i) {
                p.in_flight.insert(i);
                keys.push((i, r.location, r.sample.key.to_string()));
            }
        }
        keys
    }

    /// Fetches the claimed records, keeps those that check out, and ends their claims.
    fn fetch_claimed(&self, keys: Vec<(usize, (usize, usize), String)>) {
        let Some(store) = &self.store else { return };
        if keys.is_empty() {
            return;
        }
        let wanted: Vec<(usize, usize, &str)> = keys
            .iter()
            .map(|(_, (shard, row), key)| (*shard, *row, key.as_str()))
            .collect();
        let got = store.read_many(&wanted);
        self.keep_prefetched(
            keys.iter()
                .zip(got)
                .filter_map(|((i, _, _), r)| r.ok().map(|record| (*i, record)))
                .collect(),
        );
        let mut p = self.prefetched.lock().unwrap_or_else(|p| p.into_inner());
        for (i, _, _) in &keys {
            p.in_flight.remove(i);
        }
        drop(p);
        self.prefetch_done.notify_all();
    }

    /// The record of sample `index` fetched ahead, waiting for its fetch when one is
    /// under way; `None` when there is none (the item reads it then).
    fn take_prefetched(&self, index: usize) -> Option<StoredRecord> {
        let mut p = self.prefetched.lock().unwrap_or_else(|p| p.into_inner());
        loop {
            if let Some(record) = p.records.remove(&index) {
                p.order.retain(|&i| i != index);
                return Some(record);
            }
            if !p.in_flight.contains(&index) {
                return None;
            }
            p = self
                .prefetch_done
                .wait(p)
                .unwrap_or_else(|p| p.into_inner());
        }
    }

    /// The crop-store record of sample `index` as stored (its bytes, for a transport
    /// of the caller's: see [`FaceLoader::supply_record`]); an error without a store.
    pub fn record_bytes(&self, index: usize) -> Result<Vec<u8>> {
        let row = self.row(index)?;
        let store = self
            .store
            .as_ref()
            .ok_or_else(|| Error::invalid("record", "the loader reads no crop store"))?;
        store.raw_record(row.location.0, row.location.1)
    }

    /// Takes `bytes` (what [`FaceLoader::record_bytes`] gave, carried by other means) as
    /// the record of sample `index` for its next item, after every check a record read
    /// from the store gets; kept as [`FaceLoader::prefetch`] keeps records.
    pub fn supply_record(&self, index: usize, bytes: Vec<u8>) -> Result<()> {
        let row = self.row(index)?;
        let store = self
            .store
            .as_ref()
            .ok_or_else(|| Error::invalid("record", "the loader reads no crop store"))?;
        let (shard, r) = row.location;
        let record = store.record_from_bytes(shard, r, &row.sample.key.to_string(), bytes)?;
        self.keep_prefetched(vec![(index, record)]);
        Ok(())
    }

    fn keep_prefetched(&self, records: Vec<(usize, StoredRecord)>) {
        let mut p = self.prefetched.lock().unwrap_or_else(|p| p.into_inner());
        for (i, record) in records {
            if p.records.insert(i, record).is_none() {
                p.order.push_back(i);
            }
            while p.order.len() > PREFETCH_RECORDS {
                if let Some(old) = p.order.pop_front() {
                    p.records.remove(&old);
                }
            }
        }
    }

    /// The crop store in use, if any.
    pub fn crop_store(&self) -> Option<&CropStore> {
        self.store.as_ref()
    }

    /// Vertices of the meshes served (the topology's).
    pub fn mesh_vertex_count(&self) -> usize {
        self.renderer.topology().vertex_count
    }

    /// The samples shard and row of sample `index`.
    pub fn location(&self, index: usize) -> Option<(usize, usize)> {
        self.rows.get(index).map(|r| r.location)
    }

    /// What a crop store keeps of sample `index` (read from the release, not from a
    /// store): its mesh, its evaluation box and the crop window around it.
    pub fn stored_crop(&self, index: usize) -> Result<StoredCrop> {
        let row = self.row(index)?;
        let verts = self.mesh(index)?;
        let image = self.dataset.image(&row.sample)?;
        let pose = Pose::from_release_rt(&row.sample.rt)?;
        let landmarks = self.landmarks(row, &verts, &pose)?;
        let eval_crop = self.eval_crop(row, &landmarks)?;
        let s = self.options.img_size;
        let first = -(crate::store::crop_store::margin(s) as i64);
        let w = crate::store::crop_store::window_side(s);
        let window = eval_crop.crop_window(&image, first, w);
        Ok(StoredCrop {
            eval_crop,
            verts,
            window: image::RgbImage::from_raw(w as u32, w as u32, window).expect("window size"),
            part: WindowPart::Whole,
        })
    }

    /// The 68 landmarks of `verts` at `pose` in image pixels.
    fn landmarks(
        &self,
        row: &IndexRow,
        verts: &[Point3<f32>],
        pose: &Pose,
    ) -> Result<Vec<(f64, f64)>> {
        let camera = Camera::new(
            self.camera_projection,
            row.sample.image_width,
            row.sample.image_height,
        )?;
        let points: Vec<Point3<f64>> = self
            .renderer
            .topology()
            .landmarks
            .iter()
            .map(|&i| verts[i as usize].cast())
            .collect();
        Ok(camera
            .project_all(pose, &points)
            .iter()
            .map(|p| (p.u, p.v))
            .collect())
    }

    /// The evaluation crop of these landmarks under the loader's rules: ours, or the
    /// official integer box (an error when that box is empty).
    fn eval_crop(&self, row: &IndexRow, landmarks: &[(f64, f64)]) -> Result<CropTransform> {
        let rules = self.options.rules;
        rules
            .book()
            .crop_around(landmarks, self.options.img_size)
            .map_err(|why| {
                Error::invalid(format!("{rules} box"), format!("{}: {why}", row.sample.key))
            })
    }

    /// Samples served.
    pub fn len(&self) -> usize {
        self.rows.len()
    }

    /// Whether no sample is served.
    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// The options.
    pub fn options(&self) -> &LoaderOptions {
        &self.options
    }

    /// The key and split of sample `index`.
    pub fn key(&self, index: usize) -> Option<(&SampleKey, &str)> {
        self.rows
            .get(index)
            .map(|r| (&r.sample.key, r.split.as_str()))
    }

    /// The dataset.
    pub fn dataset(&self) -> &Dataset {
        &self.dataset
    }

    /// The mesh of sample `index`, read from its `_info.npz` and checked against the
    /// samples table (its `R_t` must be the table's, bit for bit); from the table for a
    /// dataset with embedded images.
    pub fn mesh(&self, index: usize) -> Result<Vec<Point3<f32>>> {
        let row = self.row(index)?;
        if row.sample.jpeg.is_some() {
            return Ok(row
                .sample
                .verts
                .chunks_exact(3)
                .map(|c| Point3::new(c[0], c[1], c[2]))
                .collect());
        }
        let info = arkit_core::release::read_info(&row.info_path)?;
        if info.rt != row.sample.rt {
            return Err(Error::format(
                &row.info_path,
                format!(
                    "R_t differs from the samples table's for {}: the file changed since convert",
                    row.sample.key
                ),
            ));
        }
        if info.verts.len() != self.renderer.topology().vertex_count {
            return Err(Error::format(
                &row.info_path,
                format!(
                    "{} vertices, the topology has {}",
                    info.verts.len(),
                    self.renderer.topology().vertex_count
                ),
            ));
        }
        Ok(info.verts)
    }

    fn row(&self, index: usize) -> Result<&IndexRow> {
        self.rows.get(index).ok_or_else(|| {
            Error::invalid(
                "index",
                format!("{index}: the dataset serves {} samples", self.rows.len()),
            )
        })
    }

    /// Sample `index` of epoch `epoch` (the epoch matters in training mode only).
    pub fn item(&self, index: usize, epoch: u64) -> Result<LoaderItem> {
        self.item_with(index, epoch, Planes::Owned)
    }

    /// As [`FaceLoader::item`], with `img` and `uvmap` written into `planes` (the
    /// item's own two vectors are left empty): the same values, bit for bit (tested),
    /// without allocating them. The planes must hold `3 x S x S` and `3 x U x U` values
    /// ([`FaceLoader::uvmap_size`]); other lengths are refused.
    pub fn item_into(
        &self,
        index: usize,
        epoch: u64,
        planes: ItemPlanes<'_>,
    ) -> Result<LoaderItem> {
        let s = self.options.img_size as usize;
        let u = self.uvmap_size() as usize;
        if planes.img.len() != 3 * s * s || planes.uvmap.len() != 3 * u * u {
            return Err(Error::invalid(
                "item planes",
                format!(
                    "{} and {} values given for img and uvmap; expected {} and {}",
                    planes.img.len(),
                    planes.uvmap.len(),
                    3 * s * s,
                    3 * u * u
                ),
            ));
        }
        self.item_with(index, epoch, Planes::Borrowed(planes))
    }

    /// The side, in texels, of an item's `uvmap` (`S` under both rule sets).
    pub fn uvmap_size(&self) -> u32 {
        match self.options.rules.book().uv_layout() {
            UvLayout::TexelCentres => self.options.img_size,
            UvLayout::Official => self.official_uv.size(),
        }
    }

    fn item_with(&self, index: usize, epoch: u64, planes: Planes<'_>) -> Result<LoaderItem> {
        let row = self.row(index)?;
        let (verts, source) = match &self.store {
            Some(store) => {
                let (shard, r) = row.location;
                // The record must be this sample's (checked in every mode).
                // The window is decoded when the crop is known, as much of it as the
                // crop reaches.
                let mut stored = match self.take_prefetched(index) {
                    Some(record) => record,
                    None => store.read(shard, r, &row.sample.key.to_string())?,
                };
                (
                    std::mem::take(&mut stored.verts),
                    PixelSource::Stored(stored),
                )
            }
            None => (
                self.mesh(index)?,
                PixelSource::Image(self.dataset.image(&row.sample)?),
            ),
        };
        let pose = Pose::from_release_rt(&row.sample.rt)?;
        let epoch = match self.options.mode {
            LoaderMode::Train => epoch,
            LoaderMode::Eval => 0,
        };
        let stream = (epoch << 40) ^ index as u64;
        let mut rng = Rng::for_stream(self.options.seed, stream);
        let landmarks = self.landmarks(row, &verts, &pose)?;
        let train = self.options.mode == LoaderMode::Train;
        let mut item = match self.options.rules.book().mask() {
            MaskRule::Crop => self.exact(
                row, &verts, &pose, &source, &landmarks, train, &mut rng, planes,
            )?,
            MaskRule::WarpedFromImage => self.official(
                row, &verts, &pose, &source, &landmarks, train, &mut rng, planes,
            )?,
        };
        item.model = verts.iter().flat_map(|p| [p.x, p.y, p.z]).collect();
        Ok(item)
    }

    /// A training jitter `(dx, dy, scale)` for landmarks whose box has side `size`.
    fn draw_jitter(rng: &mut Rng, size: f64) -> (f64, f64, f64) {
        let r = 0.15 * size;
        let dx = rng.uniform(-r, r);
        let dy = rng.uniform(-r, r);
        (dx, dy, rng.uniform(0.95, 1.05))
    }

    fn image_path(&self, row: &IndexRow) -> PathBuf {
        match row.sample.jpeg {
            Some(_) => self.dataset.dir().to_path_buf(),
            None => self.dataset.image_root().join(&row.sample.image_path),
        }
    }

    /// A visibility buffer from the loader's pool (or a new one), given back when
    /// dropped: items reuse its allocation instead of allocating and zeroing one each.
    fn take_buffer(&self) -> KeptBuffer<'_> {
        let kept = self.buffers.lock().unwrap_or_else(|e| e.into_inner()).pop();
        KeptBuffer {
            pool: &self.buffers,
            buffer: kept.unwrap_or_else(|| VisibilityBuffer::new(1, 1)),
        }
    }
}

/// The release's UV triangles (`tris_2500x3_202110.npy`) from a resources folder, when
/// the file is there: `(N, 3)` integer vertex ids.
pub fn read_uv_triangles(resources: &Path) -> Result<Option<Vec<[u32; 3]>>> {
    let path = resources.join("tris_2500x3_202110.npy");
    if !path.exists() {
        return Ok(None);
    }
    let a = arkit_core::read_npy(&path)?;
    if a.shape().len() != 2 || a.shape()[1] != 3 {
        return Err(Error::format(
            &path,
            format!("expected shape (N, 3), found {:?}", a.shape()),
        ));
    }
    let v = a.to_f64_vec();
    if v.iter()
        .any(|&x| x < 0.0 || x.fract() != 0.0 || x > u32::MAX as f64)
    {
        return Err(Error::format(
            &path,
            "vertex ids must be non-negative integers",
        ));
    }
    Ok(Some(
        v.chunks_exact(3)
            .map(|c| [c[0] as u32, c[1] as u32, c[2] as u32])
            .collect(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn official_uv_map_in_lanes_is_the_per_texel_definition() {
        // The layout's runs and lanes against each texel computed straight from the
        // official raster of the UV triangles (the one the layout is read from): the
        // same bits, on meshes whose colours run past [0, 1] on both sides, with a NaN
        // among them.
        let face = crate::mesh::synthetic_face::builtin();
        let topology = &face.topology;
        let uv = UvMapper::derive(topology).unwrap();
        let mut r = Rng::new(8);
        for size in [64u32, 192, 640] {
            let layout = OfficialUvLayout::new(&uv, None, topology.vertex_count, size).unwrap();
            // At 640 some runs are longer than two registers of lanes (eight each), so the
            // loop over a run's registers is exercised.
            assert!(size < 640 || layout.covered.iter().any(|r| r.len > 16));
            let vb = OfficialUvLayout::raster(&uv.uv, &uv.triangles, size).unwrap();
            for case in 0..4 {
                let mut verts: Vec<Point3<f32>> = (0..topology.vertex_count)
                    .map(|_| {
                        let mut q = || r.uniform(-0.2, 0.2) as f32 * (1 + case) as f32;
                        Point3::new(q(), q(), q())
                    })
                    .collect();
                // x = -1/9 puts a colour at zero or a hair off it; a NaN stays NaN
                // through the clamp.
                verts[3].x = -1.0 / 9.0;
                verts[5].y = f32::NAN;
                let colors = layout.colours(&verts);
                let n = (size * size) as usize;
                let mut want = vec![-1f32; 3 * n];
                for (i, &t) in vb.triangle.iter().enumerate() {
                    if t == VisibilityBuffer::EMPTY {
                        continue;
                    }
                    let [a, b, c] = uv.triangles[t as usize].map(|v| colors[v as usize]);
                    let wt = vb.bary[i];
                    for ch in 0..3 {
                        let value = wt[0] * a[ch] + wt[1] * b[ch] + wt[2] * c[ch];
                        want[ch * n + i] = value.clamp(0.0, 1.0) * 2.0 - 1.0;
                    }
                }
                let mut got = vec![7f32; 3 * n];
                layout.uv_map_into(&verts, &mut got);
                let bits = |m: &[f32]| m.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&got), bits(&want), "size {size}, case {case}");
                let mut scalar = vec![7f32; 3 * n];
                let planes = layout.planes_uncovered_filled(&mut scalar);
                lanes::uv::covered_scalar(&layout.covered, &layout.weights, &colors, planes);
                assert_eq!(bits(&scalar), bits(&want), "size {size}, case {case}");
                // Each level the CPU has on its own, whichever `uv_map_into` picked.
                for level in lanes::available() {
                    let mut wide = vec![7f32; 3 * n];
                    let planes = layout.planes_uncovered_filled(&mut wide);
                    lanes::uv::covered_at(level, &layout.covered, &layout.weights, &colors, planes);
                    assert_eq!(
                        bits(&wide),
                        bits(&want),
                        "{level}, size {size}, case {case}"
                    );
                }
                assert!(got.iter().any(|x| x.is_nan()) && got.contains(&1.0));
            }
        }
    }

    #[test]
    fn python_slices_clip_and_wrap_as_python_does() {
        // mask[top:bottom+1] of an 800-row image.
        assert_eq!(python_slice(10, 301, 800), 10..301);
        assert_eq!(python_slice(700, 901, 800), 700..800);
        // A negative start counts from the end: [-5:301] is [795:301], empty.
        assert_eq!(python_slice(-5, 301, 800), 795..795);
        // ... unless the stop is past it.
        assert_eq!(python_slice(-5, 900, 800), 795..800);
        assert_eq!(python_slice(-900, 5, 800), 0..5);
    }

    #[test]
    fn organ_strips_start_at_the_smallest_u_and_keep_the_official_vertex_order() {
        // A six-vertex loop whose smallest u is its third vertex (12): local 0..5 are
        // 12, 13, 14, 15, 10, 11. The strip [0,1,5], [1,2,5], [2,5,4], [2,3,4]; an eye's
        // third triangle is listed [2,4,5], the mouth's last [2,4,3] (the official order).
        let lp = [10u32, 11, 12, 13, 14, 15];
        let mut uv = vec![[0.5f32, 0.5]; 16];
        for (k, &v) in lp.iter().enumerate() {
            uv[v as usize] = [[0.3, 0.2, 0.1, 0.4, 0.6, 0.5][k], 0.5];
        }
        let t = official_organ_triangles([&lp, &lp, &lp], &uv);
        let eye = [[12, 13, 11], [13, 14, 11], [14, 10, 11], [14, 15, 10]];
        let mouth = [[12, 13, 11], [13, 14, 11], [14, 11, 10], [14, 10, 15]];
        assert_eq!(t[..4], eye);
        assert_eq!(t[4..8], eye);
        assert_eq!(t[8..], mouth);
    }

    #[test]
    fn the_official_box_truncates_toward_zero_with_and_without_jitter() {
        // Landmarks spanning x 100..200, y 50..130: size 100, centre (150, 90).
        let l = LandmarkExtent::of([(100.0, 50.0), (200.0, 130.0), (150.0, 90.0)]);
        assert_eq!((l.cx, l.cy, l.size), (150.0, 90.0, 100.0));
        assert_eq!(official_box(l, None), [75.0, 15.0, 225.0, 165.0]);
        // Centre moved by (10.5, -20.25), half-side 0.75 * 1.02 * 100 = 76.5.
        let b = official_box(l, Some((10.5, -20.25, 1.02)));
        assert_eq!(b, [84.0, -6.0, 237.0, 146.0]);
        // int() truncates toward zero: -6.75 -> -6, not -7.
        assert_eq!((90.0f64 - 20.25 - 76.5).trunc(), -6.0);
    }

    #[test]
    fn a_widened_mask_is_its_bytes_as_int64_at_every_alignment_and_length() {
        // Lengths around the lanes' groups of eight and the 64-byte lines, written at
        // every 8-byte offset of a line: the values, and nothing outside them.
        let mut r = Rng::new(4);
        for len in [0usize, 1, 7, 8, 9, 15, 16, 17, 64, 71, 200, 36_864] {
            let mask: Vec<u8> = (0..len).map(|_| r.below(2) as u8).collect();
            for off in 0..8 {
                let mut out = vec![-7i64; len + 16];
                widen_mask_into(&mask, &mut out[off..off + len]);
                let want: Vec<i64> = mask.iter().map(|&m| m as i64).collect();
                assert_eq!(out[off..off + len], want, "length {len}, offset {off}");
                assert!(out[..off].iter().chain(&out[off + len..]).all(|&v| v == -7));
            }
        }
    }

    #[test]
    fn normalisation_is_to_tensor_then_imagenet_normalize() {
        // The table gives the formula's bits for every byte in every channel (256
        // pixels: the AVX2 groups where the CPU has them; 259 below: and the rest).
        let all: Vec<u8> = (0..=255u8).flat_map(|v| [v, 255 - v, v / 2]).collect();
        let out = normalise(&all);
        for (i, p) in all.chunks_exact(3).enumerate() {
            for k in 0..3 {
                let direct = (p[k] as f32 / 255.0 - IMAGENET_MEAN[k]) / IMAGENET_STD[k];
                assert_eq!(out[k * 256 + i].to_bits(), direct.to_bits());
            }
        }
        let odd: Vec<u8> = (0..259 * 3).map(|i| (i * 7 % 256) as u8).collect();
        let out = normalise(&odd);
        for (i, p) in odd.chunks_exact(3).enumerate() {
            for k in 0..3 {
                let direct = (p[k] as f32 / 255.0 - IMAGENET_MEAN[k]) / IMAGENET_STD[k];
                assert_eq!(out[k * 259 + i].to_bits(), direct.to_bits(), "pixel {i}");
            }
        }
        // Each level the CPU has, whichever `normalise` took: every byte value in
        // every channel (5 and 11 are odd, so each channel runs through all 256 in 256
        // pixels), twice, against the direct formula.
        let every: Vec<u8> = (0..512usize)
            .flat_map(|j| [j as u8, (j * 5 + 1) as u8, (j * 11 + 7) as u8])
            .collect();
        let table: [[f32; 256]; 3] = std::array::from_fn(|k| {
            std::array::from_fn(|v| (UNIT[v] - IMAGENET_MEAN[k]) / IMAGENET_STD[k])
        });
        for level in crate::lanes::available() {
            for vbmi in [false, true] {
                let mut planes = [0, 1, 2].map(|_| vec![f32::NAN; 512]);
                let [r, g, b] = &mut planes;
                crate::lanes::normalise::lookup_planes_at(level, vbmi, &every, [r, g, b], &table);
                for (i, p) in every.chunks_exact(3).enumerate() {
                    for k in 0..3 {
                        let direct = (p[k] as f32 / 255.0 - IMAGENET_MEAN[k]) / IMAGENET_STD[k];
                        assert_eq!(
                            planes[k][i].to_bits(),
                            direct.to_bits(),
                            "{level} {vbmi}, pixel {i}"
                        );
                    }
                }
            }
        }
        let out = normalise(&[255, 0, 128, 0, 255, 64]);
        // Channels first: R of pixel 0, R of pixel 1, G..., B...
        assert!((out[0] - (1.0 - 0.485) / 0.229).abs() < 1e-6);
        assert!((out[1] - (0.0 - 0.485) / 0.229).abs() < 1e-6);
        assert!((out[3] - (1.0 - 0.456) / 0.224).abs() < 1e-6);
        assert!((out[4] - (128.0 / 255.0 - 0.406) / 0.225).abs() < 1e-6);
    }

    #[test]
    fn options_out_of_range_are_refused_naming_the_option() {
        let o = LoaderOptions {
            split: None,
            mode: LoaderMode::Eval,
            rules: RuleSet::Exact,
            img_size: 8,
            n_pts: 1024,
            seed: 0,
        };
        assert!(o.validate().unwrap_err().to_string().contains("img_size"));
        let o = LoaderOptions {
            img_size: 192,
            n_pts: 0,
            ..o
        };
        assert!(o.validate().unwrap_err().to_string().contains("n_pts"));
        assert!(RuleSet::parse("opencv").is_err() && LoaderMode::parse("test").is_err());
    }

    #[test]
    fn a_third_rule_set_cuts_renders_and_loads() {
        use crate::ingest::synth::{self, FaceSource, SynthOptions};
        use crate::ingest::{self, ConvertOptions, ValidationContext};

        // A synthetic release of four 256x256 images, converted.
        let tmp = tempfile::tempdir().unwrap();
        let (release, data) = (tmp.path().join("release"), tmp.path().join("pq"));
        let options = SynthOptions {
            subjects: 2,
            images_per_subject: 2,
            width: 256,
            height: 256,
            ..SynthOptions::default()
        };
        synth::generate(&FaceSource::builtin(), &options, &release, &|| {}).unwrap();
        let topology = crate::mesh::builtin().topology.clone();
        let context = ValidationContext {
            projection: Camera::release_projection(),
            topology: topology.clone(),
            embed_images: false,
        };
        let convert = ConvertOptions {
            input: release,
            output: data.clone(),
            resources: None,
            rows_per_shard: 4,
            embed_images: false,
            shard_index: 0,
            shard_count: 1,
            overwrite: false,
        };
        ingest::convert(&convert, &context, &|_| {}).unwrap();
        let dataset = Dataset::open(&data).unwrap();
        let ours_renderer =
            FaceRenderer::new(topology.clone(), Camera::release_projection()).unwrap();
        let probe_renderer = ours_renderer.clone().with_rules(RuleSet::Probe);
        let as_ours = |c: &CropTransform| CropTransform {
            rules: RuleSet::Exact,
            ..*c
        };
        let mut vb = VisibilityBuffer::new(1, 1);
        for sample in dataset.read_all_samples().unwrap() {
            let verts: Vec<Point3<f32>> = (sample.verts.chunks(3))
                .map(|c| Point3::new(c[0], c[1], c[2]))
                .collect();
            let pose = Pose::from_release_rt(&sample.rt).unwrap();
            let (w, h) = (sample.image_width, sample.image_height);
            // The crop: ours widened about the same centre, following the probe's rules.
            let ours = RuleSet::Exact
                .crop_around_landmarks(&sample.landmarks_2d, 128)
                .unwrap();
            let probe =
                (probe_renderer.crop_of(&verts, &pose, (w, h), &sample.landmarks_2d, 128)).unwrap();
            assert_eq!(probe.rules, RuleSet::Probe);
            assert!((probe.side - ours.side * crate::crop::probe::HALF_SIDE / 0.75).abs() < 1e-9);
            let centre = |c: &CropTransform| (c.x0 + c.side / 2.0, c.y0 + c.side_y / 2.0);
            let (a, b) = (centre(&ours), centre(&probe));
            assert!((a.0 - b.0).abs() < 1e-9 && (a.1 - b.1).abs() < 1e-9);
            // Its pixels are our resampling of its box.
            let image = dataset.image(&sample).unwrap();
            assert_eq!(probe.crop_image(&image), as_ours(&probe).crop_image(&image));
            // Its targets are ours over its box; the wider box holds a smaller face.
            let t = (probe_renderer.render(&verts, &pose, w, h, &probe, &mut vb)).unwrap();
            let want =
                (ours_renderer.render(&verts, &pose, w, h, &as_ours(&probe), &mut vb)).unwrap();
            assert_eq!(
                (&t.mask, &t.corr_vertices),
                (&want.mask, &want.corr_vertices)
            );
            let narrower = (ours_renderer.render(&verts, &pose, w, h, &ours, &mut vb)).unwrap();
            let face = |m: &[bool]| m.iter().filter(|&&m| m).count();
            assert!(0 < face(&t.mask) && face(&t.mask) < face(&narrower.mask));
        }
        // The loader's items under the probe's rules: its box, and the render's mask there.
        let open = |rules| {
            let options = LoaderOptions {
                split: None,
                mode: LoaderMode::Eval,
                rules,
                img_size: 128,
                n_pts: 64,
                seed: 5,
            };
            FaceLoader::open(&data, topology.clone(), None, options).unwrap()
        };
        let (ours_loader, probe_loader) = (open(RuleSet::Exact), open(RuleSet::Probe));
        assert_eq!(probe_loader.len(), 4);
        for i in 0..probe_loader.len() {
            let (ours, probe) = (
                ours_loader.item(i, 0).unwrap(),
                probe_loader.item(i, 0).unwrap(),
            );
            assert_eq!(probe.crop.rules, RuleSet::Probe);
            assert!(
                (probe.crop.side - ours.crop.side * crate::crop::probe::HALF_SIDE / 0.75).abs()
                    < 1e-9
            );
            let verts = probe_loader.mesh(i).unwrap();
            let pose = Pose::from_release_rt(&probe.rt).unwrap();
            let t = ours_renderer
                .render(&verts, &pose, 256, 256, &as_ours(&probe.crop), &mut vb)
                .unwrap();
            let mask: Vec<u8> = t.mask.iter().map(|&m| m as u8).collect();
            assert_eq!(probe.mask, mask);
            assert_eq!(probe.uvmap.len(), 3 * 128 * 128);
            assert_ne!(probe.mask, ours.mask);
        }
    }
}
