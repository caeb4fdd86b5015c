#![no_main]
//! Fuzz target `list_csv`: see `arkit_core::fuzz_entry::list_csv`.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = arkit_core::fuzz_entry::list_csv(data);
});
