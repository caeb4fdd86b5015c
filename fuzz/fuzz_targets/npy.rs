#![no_main]
//! Fuzz target `npy`: see `arkit_core::fuzz_entry::npy`.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = arkit_core::fuzz_entry::npy(data);
});
