#![no_main]
//! Fuzz target `dataset_json`: see `arkit_data::fuzz_entry::dataset_json`.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = arkit_data::fuzz_entry::dataset_json(data);
});
