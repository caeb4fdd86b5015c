#![no_main]
//! Fuzz target `crops_json`: see `arkit_data::fuzz_entry::crops_json`.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = arkit_data::fuzz_entry::crops_json(data);
});
