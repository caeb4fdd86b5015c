#![no_main]
//! Fuzz target `torch_pickle`: see `arkit_core::fuzz_entry::torch_pickle`.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = arkit_core::fuzz_entry::torch_pickle(data);
});
