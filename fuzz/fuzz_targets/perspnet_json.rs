#![no_main]
//! Fuzz target `perspnet_json`: see `arkit_perspnet::fuzz_entry::perspnet_json`.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = arkit_perspnet::fuzz_entry::perspnet_json(data);
});
