#![no_main]
//! Fuzz target `npz`: see `arkit_core::fuzz_entry::npz`.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = arkit_core::fuzz_entry::npz(data);
});
