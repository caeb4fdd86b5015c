#![no_main]
//! Fuzz target `crop_window`: see `arkit_data::fuzz_entry::crop_window`.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = arkit_data::fuzz_entry::crop_window(data);
});
