#![no_main]
//! Fuzz target `targets_blobs`: see `arkit_core::fuzz_entry::targets_blobs`.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = arkit_core::fuzz_entry::targets_blobs(data);
});
