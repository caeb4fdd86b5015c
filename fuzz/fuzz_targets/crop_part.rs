#![no_main]
//! Fuzz target `crop_part`: see `arkit_data::fuzz_entry::crop_part`.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = arkit_data::fuzz_entry::crop_part(data);
});
