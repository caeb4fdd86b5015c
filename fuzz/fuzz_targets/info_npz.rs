#![no_main]
//! Fuzz target `info_npz`: see `arkit_core::fuzz_entry::info_npz`.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = arkit_core::fuzz_entry::info_npz(data);
});
