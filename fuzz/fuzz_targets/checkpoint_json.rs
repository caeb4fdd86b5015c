#![no_main]
//! Fuzz target `checkpoint_json`: see `arkit_perspnet::fuzz_entry::checkpoint_json`.

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = arkit_perspnet::fuzz_entry::checkpoint_json(data);
});
