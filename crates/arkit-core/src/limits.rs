//! Every limit on what the readers accept, in one place.
//!
//! The rule: no size read from a file (a zip directory entry, an `.npy` header's shape,
//! a run length, a blob length, a map side) is trusted. Each is checked, with overflow-
//! safe arithmetic, against what the file can actually hold and against one of the
//! limits below *before* anything is allocated from it, and compressed data is inflated
//! through a reader capped at the limit, so a hostile or corrupt file costs at most
//! about the limit in memory and is refused with an error naming the file.
//!
//! The values are far above what the release (and everything `arkit-tool` writes) needs;
//! each constant says what it bounds, what real files need, and why that value.
//!
//! Tested: the `.npy` / `.npz` limits by `tests/bounded_memory.rs` (crafted bytes at and
//! just over each limit, with the peak allocation measured under a counting allocator),
//! the mask and UV limits by `target_codec`'s tests, the `targets` table's sizes by
//! `arkit_tool::targets_table`'s tests, and everything by the fuzz targets in `fuzz/`
//! (run with a memory limit, so an unbounded allocation is a crash). The consistency
//! of the values is checked at compile time below.

/// Largest `.npy` header (the dict literal after the length field), in bytes.
///
/// numpy itself refuses headers above 10 000 bytes (`max_header_size` of `np.load`,
/// since numpy 1.24); the release's headers are 118 bytes (64-byte aligned dicts such as
/// `{'descr': '<f4', 'fortran_order': False, 'shape': (1220, 3), }`).
pub const MAX_NPY_HEADER_BYTES: usize = 10_000;

/// Largest data of one array (shape product times element size), in bytes: 256 MiB.
///
/// Bounds every `.npy` file and every `.npz` member, checked from the header before the
/// data is read. The release's largest arrays are `verts` / `verts_gt` (1220 x 3
/// float32, 14 640 bytes); the topology files `arkit-tool` reads (triangles, UVs,
/// landmarks, template) are below 100 KB. 256 MiB leaves room for any array a user could
/// reasonably feed the tool while keeping a hostile file's cost bounded.
pub const MAX_ARRAY_BYTES: u64 = 256 << 20;

/// Largest total of array data in one `.npz` archive, in bytes: 256 MiB.
///
/// Each member is also bounded by [`MAX_ARRAY_BYTES`]; this bounds the sum, so that many
/// deflated members cannot add up to gigabytes. An `_info.npz` of the release holds
/// about 60 KB of arrays.
pub const MAX_NPZ_ARRAY_BYTES: u64 = 256 << 20;

/// Most members (arrays) in one `.npz` archive: 64.
///
/// Checked before any member is opened. The release's `_info.npz` files have 10 keys
/// (`verts`, `R_t`, `verts_gt`, `faceAnchortransform`, `cameratransform`,
/// `projectionMatrix`, `euler_angles`, `translation`, `points2d`, ...).
pub const MAX_NPZ_MEMBERS: usize = 64;

/// Largest `.npz` file read, in bytes: 64 MiB.
///
/// Checked on the file's length before it is read (and the read itself is capped, for
/// files whose length lies, such as pipes). The release's `_info.npz` files are about
/// 100 KB (`savez`, uncompressed).
pub const MAX_NPZ_FILE_BYTES: u64 = 64 << 20;

/// Largest number of bytes accepted after an array's data, in a `.npy` file or an
/// `.npz` member: 4096.
///
/// numpy's `np.load` ignores bytes after the data, and `np.save` never writes any; we
/// accept (and ignore) a few, as numpy does, but refuse more, because an unbounded tail
/// would have to be read (or inflated) to be skipped: a file with gigabytes after a
/// valid array is refused instead of read.
pub const MAX_NPY_TRAILING_BYTES: u64 = 4096;

/// Largest `.npy` file read, in bytes: [`MAX_ARRAY_BYTES`] plus the largest header and
/// the trailing allowance. Checked on the file's length before reading.
pub const MAX_NPY_FILE_BYTES: u64 =
    MAX_ARRAY_BYTES + 12 + MAX_NPY_HEADER_BYTES as u64 + MAX_NPY_TRAILING_BYTES;

/// Largest side of a crop in a `targets` file (`crop_size`), in pixels: 4096.
///
/// `render` writes 192- or 256-pixel crops (PerspNet uses 192); a mask of 4096 x 4096
/// is 16 M pixels.
pub const MAX_CROP_SIZE: u32 = 4096;

/// Largest side of a UV position map (`uv_size`), in texels: 4096.
///
/// `render` writes 192 x 192 maps (PerspNet's); a 4096 x 4096 map is 96 MiB of
/// float16 positions, the largest blob a `targets` row can make the reader allocate.
pub const MAX_UV_SIZE: u32 = 4096;

/// Largest width or height of a sample's image (`image_width`, `image_height`), in
/// pixels: 65 535, the largest a JPEG can declare. The release's images are 1280 x 720
/// (portrait or landscape).
pub const MAX_IMAGE_SIDE: u32 = 65_535;

/// Most pixels of one decoded mask (crop mask or full-image mask): 2^26 (67 M, 8192 x
/// 8192), so a decoded mask is at most 64 MiB. Run lengths are summed (in `u64`) and
/// compared with the mask's size before the mask is allocated. The release's images
/// have 0.92 M pixels; crops at [`MAX_CROP_SIZE`] have 16.8 M.
pub const MAX_MASK_PIXELS: u64 = 1 << 26;

/// Largest dense tensor built from one stored row (`points x vertex_count` float32
/// correspondence matrix), in bytes: the same bound as one array, [`MAX_ARRAY_BYTES`].
/// PerspNet's is 1024 x 1220 x 4 = 5 MB.
pub const MAX_DENSE_BYTES: u64 = MAX_ARRAY_BYTES;

// Compile-time checks: what real files need fits, with room, and every bound stays far
// below what the machine can hold.
const _: () = {
    assert!(MAX_NPY_HEADER_BYTES >= 118);
    assert!(MAX_ARRAY_BYTES >= 1220 * 3 * 8);
    assert!(MAX_NPZ_FILE_BYTES >= 100_000);
    assert!(MAX_NPZ_MEMBERS >= 10);
    assert!(MAX_MASK_PIXELS >= 1280 * 720);
    assert!(MAX_MASK_PIXELS >= MAX_CROP_SIZE as u64 * MAX_CROP_SIZE as u64);
    // A UV map blob at the limit is at most one array's size.
    assert!(MAX_UV_SIZE as u64 * MAX_UV_SIZE as u64 * 6 <= MAX_ARRAY_BYTES);
    assert!(MAX_NPY_FILE_BYTES < 1 << 30);
    assert!(MAX_NPZ_ARRAY_BYTES < 1 << 30);
};

/// A release image larger than this (bytes) is refused before it is read (the release's
/// 800x800 JPEGs are about 100 KiB). Tested in `tests/hostile.rs` of the root crate
/// through `convert`.
pub const MAX_IMAGE_FILE_BYTES: u64 = 64 << 20;

/// Images smaller than this (either side, pixels) are refused by `convert`: no face
/// crop can be taken from them (the release's are 1280x720 and larger).
pub const MIN_IMAGE_SIDE: u32 = 32;

/// A face whose 68 landmarks span fewer pixels than this (both ways) is refused by
/// `convert` as degenerate (an all-zero or collapsed mesh); the release's faces span
/// hundreds of pixels.
pub const MIN_FACE_SPAN_PX: f64 = 8.0;

/// Largest frame JSON of an ARKit capture (`import-arkit`) read, in bytes: 16 MiB,
/// checked on the file's length before it is read. A frame with the anchor's 1,220
/// vertices written as decimal text is about 100 KB.
pub const MAX_CAPTURE_JSON_BYTES: u64 = 16 << 20;

// ---------------------------------------------------------------------------------------
// Weight files: `torch.save` checkpoints (`torch_pickle`) and safetensors headers.
// The official `paper` network's state_dict has 206 tensors, a 30 KB pickle, a largest
// tensor of 9.4 MB (`cnn.resnet18_8s.layer4` convolutions) and a 20 KB safetensors header.

/// Largest `data.pkl` of a `torch.save` archive read, in bytes: 16 MiB, checked on the
/// zip directory's size and again while reading. A state_dict's pickle takes about 150
/// bytes per tensor (30 KB for `paper`).
pub const MAX_PICKLE_BYTES: u64 = 16 << 20;

/// Deepest nesting of containers (tuples, lists, dicts) and of MARKs in a pickle: 32.
/// A state_dict nests 4 deep (the dict, a tensor's arguments, its size tuple; the
/// `_metadata` dicts). Refusing deeper pickles bounds every walk over the objects.
pub const MAX_PICKLE_DEPTH: usize = 32;

/// Most memo entries of a pickle: 2^20. A state_dict writes about 8 per tensor.
pub const MAX_PICKLE_MEMO: usize = 1 << 20;

/// Most objects (strings, tuples, dicts, tensors, ...) a pickle may build: 2^20, about
/// 12 per tensor in a state_dict.
pub const MAX_PICKLE_OBJECTS: usize = 1 << 20;

/// Most bytes of objects a pickle may build (strings, container slots, the stack and
/// the memo, each counted as it is made): 64 MiB, 400 times what `paper` needs.
/// Objects fetched from the memo are shared, never copied, so this bounds what a pickle
/// that refers to one entry many times costs.
pub const MAX_PICKLE_ALLOC_BYTES: u64 = 64 << 20;

/// Most tensors (and storages) in one state_dict: 65 536.
pub const MAX_TORCH_TENSORS: usize = 65_536;

/// Largest storage of one tensor in a `torch.save` archive, in bytes: 256 MiB (the same
/// bound as one array, [`MAX_ARRAY_BYTES`]). Checked from the pickle's declared size,
/// against the member's size in the zip directory, and while reading.
pub const MAX_TORCH_STORAGE_BYTES: u64 = MAX_ARRAY_BYTES;

/// Largest total of the storages of one `torch.save` archive, in bytes: 4 GiB. The
/// tensors are read one at a time, after their names and shapes have been matched with
/// the network's, so memory follows the network's size, not this bound.
pub const MAX_TORCH_DATA_BYTES: u64 = 4 << 30;

/// Largest JSON header of a safetensors file, in bytes: 16 MiB, checked on the length
/// field before the header is read (the safetensors library's own bound is 100 MB).
pub const MAX_SAFETENSORS_HEADER_BYTES: u64 = 16 << 20;

const _: () = {
    assert!(MAX_PICKLE_BYTES >= 30_000);
    assert!(MAX_PICKLE_DEPTH >= 4);
    assert!(MAX_PICKLE_ALLOC_BYTES < 1 << 30);
    assert!(MAX_TORCH_STORAGE_BYTES >= 9_437_184);
    assert!(MAX_SAFETENSORS_HEADER_BYTES >= 20_000);
};

// ---- Decoded images -------------------------------------------------------------------
//
// Every image reader (`convert`'s release JPEGs, `convert --format biwi`'s PNGs,
// `import-arkit`'s captures, the converted dataset's images for `render`, `crops`,
// `predict`, the loader and `augment`, Python's `read_image`) decodes through one
// function (`arkit_data::image_decode`), which reads the size and colour type from the
// image's header and checks them against these limits *before* any pixel is decoded. A
// few hundred bytes of PNG can declare 16000 x 16000 16-bit pixels (1.5 GiB decoded);
// such an image is refused, not decoded. Images are decoded one per thread, so a run's
// image memory is at most the number of threads times [`MAX_DECODED_IMAGE_BYTES`].

/// Most pixels of one decoded image: 2^24 (16.8 M, for example 4096 x 4096 or 5461 x
/// 3072). The release's images are 1280 x 720 (0.92 M), BIWI's 640 x 480, an iPhone's
/// captured frame 1920 x 1440 (2.8 M), a 12 MP photo 4032 x 3024 (12.2 M).
pub const MAX_DECODED_IMAGE_PIXELS: u64 = 1 << 24;

/// Most bytes one image's decoding may hold: the decoder's output in the file's own
/// colour type (3 bytes a pixel for 8-bit RGB, 6 for 16-bit RGB, 8 for 16-bit RGBA) plus
/// the 8-bit RGB copy every reader works on when the file is not already 8-bit RGB:
/// 128 MiB. An 8-bit RGB image at [`MAX_DECODED_IMAGE_PIXELS`] needs 48 MiB; a 16-bit
/// RGB one may have at most 14.9 M pixels (9 bytes a pixel).
pub const MAX_DECODED_IMAGE_BYTES: u64 = 128 << 20;

const _: () = {
    // The release's images, BIWI's and 12 MP photos fit, in any colour type.
    assert!(MAX_DECODED_IMAGE_PIXELS >= 4032 * 3024);
    assert!(4032 * 3024 * (8 + 3) <= MAX_DECODED_IMAGE_BYTES);
    assert!(MAX_DECODED_IMAGE_PIXELS * 3 <= MAX_DECODED_IMAGE_BYTES);
    assert!(MAX_DECODED_IMAGE_BYTES < 1 << 30);
};
