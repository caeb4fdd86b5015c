//! `crop_store`: every sample's crop pixels and mesh stored once, so that the loader
//! ([`crate::loader::item::FaceLoader`]) reads one small record instead of decoding the
//! release's JPEG and `_info.npz` for every sample in every epoch.
//!
//! Contract. A record holds, for one sample, one rule set (`exact` or `official`) and
//! crop side `S`: the evaluation crop's box, the mesh (`V x 3` float32) and the crop
//! *window* around that box (crop pixels `-m..S + m`, [`margin`]), resampled from the
//! full-resolution image as the crop is; every codec is lossless, so evaluation crops
//! are bit for bit those of the JPEG, and a training crop (whose jittered box lies
//! inside the window) is resampled from the window, slightly smoother (docs/python.md).
//! [`CropStore::open`] checks the manifest against the dataset and each part file's
//! header and index; [`CropStore::read`] checks each record (CRC, then that it is this
//! dataset's, shard's, row's and sample's) before anything is decoded, and refuses a
//! store of an earlier format with "rerun `arkit-tool crops`". Files are written under
//! a temporary name and renamed, `crops.json` last. The writing of a whole dataset, which
//! computes each record with the loader, is `loader::crops_dataset`.
//!
//! One file per concern, none importing another in a cycle: `format` (the bytes
//! on disk and the window's geometry, a leaf), `codec/` (the window codecs, one file
//! each, and their one table), `mesh_codec`, `manifest` (`crops.json`), `records` (a
//! record's bytes and checks), `writer`, `reader`. Tested here (`tests.rs`, and each
//! file's own tests) and in `tests/crop_store.rs`: items equal with and without the
//! store, and every way a store can be wrong refused, naming the file.

mod codec;
mod format;
mod manifest;
mod mesh_codec;
mod reader;
mod records;
mod writer;
mod zstd_frame;

#[cfg(test)]
mod tests;

// What the store offers: the loader opens and reads it, the benches time its codecs,
// the tests read its manifest and headers.
pub use self::{
    codec::{
        WindowCodec, decode_window, encode_window, predict_rect, unpredict_in_place, unpredict_rect,
    },
    format::{FORMAT, HEADER_BYTES, PixelRect, WindowPart, margin, window_parts, window_side},
    manifest::{CropShard, CropStoreManifest, MissingCrop, read_manifest},
    mesh_codec::{decode_mesh, encode_mesh},
    reader::CropStore,
    records::{StoredCrop, StoredRecord},
};
// What only `loader::crops_dataset` uses, to write a store.
pub(crate) use self::{
    format::{MANIFEST_FILE, MAX_KEY_BYTES, key_field_bytes},
    manifest::write_manifest,
    reader::{check_for_loader, reseal_part},
    records::encode_record,
    writer::write_shard_file,
};
