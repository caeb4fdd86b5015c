//! `arkit_core`: the parts of `arkit-tool` that need neither polars nor candle, and that
//! every reader of untrusted files goes through.
//!
//! Namespaces (`pub mod`), named by their path:
//!
//! - [`conventions`]: [`Pose`] (the release's `R_t`) and [`Camera`] (its projection).
//! - [`limits`]: every bound on what the readers accept, documented in one place.
//! - [`atomic_file`]: writes that never leave a half-written file.
//! - [`lanes`]: which vector lanes (SSE2, AVX2, AVX-512) the kernels use.
//! - [`release`]: the release's files: `_info.npz` annotations, list CSVs, layout.
//! - [`torch_pickle`]: a bounded reader of `torch.save(state_dict)` archives.
//!
//! Everything else is named at the crate root (the one block of `pub use` below):
//!
//! - the one error type, naming the file and the problem: [`Error`], [`ErrorKind`],
//!   [`Result`];
//! - NumPy `.npy` / `.npz` reading (bounded, see [`limits`]) and writing: [`read_npy`],
//!   [`read_npz`], [`NpyArray`], [`write_npy`], [`write_npz`];
//! - the release's types: its layout ([`ReleaseLayout`], [`SampleKey`], [`Split`]) and
//!   an `_info.npz` annotation ([`InfoAnnotation`]), read and written by [`release`];
//! - the byte codecs of the `targets` blobs (masks as run lengths ([`rle_encode`]),
//!   UV-map delta planes ([`encode_uv_map`]), [`Correspondences`]), and the predictions
//!   CSV ([`parse_predictions_csv`], [`PredictionRecord`]);
//! - the types of the bounded reader of `torch.save(state_dict)` archives
//!   ([`TorchZip`], [`TorchTensor`]; no code from the file is run), opened by
//!   [`torch_pickle::open`];
//! - the CPU triangle rasterizer core ([`VisibilityBuffer`],
//!   [`rasterize_mesh_official`]);
//! - the seeded random streams that make output reproducible ([`Rng`], [`splitmix64`]).
//!
//! The fuzz targets in `fuzz/` link this crate alone, so they build in seconds.

#![deny(missing_docs)]

// `pub mod`: namespaces users name. `atomic_file`'s verbs (`publish`, `write_bytes`) say
// "atomically" only through its name; `conventions` is the one place the release's
// conventions are stated; `lanes` is the vector-lane switch (`lanes::level()`);
// `limits` lists every bound together, each read as `limits::MAX_X`; `release` is the
// release's own files (`release::read_info`, `release::write_lists`), its types also at
// the root; `torch_pickle::open` needs its module's name.
pub mod atomic_file;
pub mod conventions;
#[doc(hidden)]
pub mod fuzz_entry;
pub mod lanes;
pub mod limits;
pub mod release;
pub mod torch_pickle;

pub(crate) mod error;
pub(crate) mod npy;
pub(crate) mod predictions_csv;
pub(crate) mod raster;
pub(crate) mod rng;
pub(crate) mod target_codec;

// What the crate offers besides those namespaces: the error type, the readers and
// writers of the release's files, the rasterizer core, the seeded random streams.
pub use self::{
    conventions::{Camera, EulerAngles, Pose},
    error::{Error, ErrorKind, Result},
    npy::{
        ArrayData, DType, NpyArray, Npz, NpzCompression, parse_npy, parse_npz, read_npy, read_npz,
        write_npy, write_npz,
    },
    predictions_csv::{PredictionRecord, parse_csv as parse_predictions_csv, rt_of},
    raster::{
        BadTriangle, Culling, Fragment, MAX_VIEWPORT, PixelWindow, ScreenVertex, TriangleSetup,
        VisibilityBuffer, official_weights, rasterize_mesh_official, rasterize_mesh_official_in,
        rasterize_official_visibility_in,
    },
    release::{ARKIT_VERTEX_COUNT, InfoAnnotation, ListRow, ReleaseLayout, SampleKey, Split},
    rng::{Rng, splitmix64},
    target_codec::{
        Correspondences, decode_correspondences, decode_uv_map, encode_correspondences,
        encode_uv_map, mask_len, pack_u16_le, pack_u32_le, rle_decode, rle_encode, unpack_u32_le,
    },
    torch_pickle::{TorchDType, TorchTensor, TorchZip},
};
