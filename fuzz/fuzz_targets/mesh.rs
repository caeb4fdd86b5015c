#![no_main]
//! Fuzz target `mesh`: see `arkit_data::fuzz_entry::mesh`.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = arkit_data::fuzz_entry::mesh(data);
});
